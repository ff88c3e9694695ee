"""Per-segment attributes (sp.computation.segment_attributes) beyond their oracle: the
arguments it refuses (by name, and as the numpy reference fails), and the NaN its minima and
maxima keep; and each segment's texture (segment_roughness) on surfaces and foliage. Its
equivalence to ``segment_attributes_reference`` is a case family of
test_kernel_equivalence.py."""

from __future__ import annotations

import numpy as np
import pytest
from kernel_reference.computation_reference import segment_attributes_reference
from kernel_scenes import attribute_scene

from sp.computation import (
    ComputationError,
    _segment_box,
    _segment_runs,
    _segment_sums,
    segment_attributes,
    segment_roughness,
)


def test_fewer_segments_than_labelled_is_an_error():
    labels, *rest = attribute_scene(4, 16, 64, 60, False)
    K = int(labels.max()) + 1
    with pytest.raises(ComputationError, match="n_segments"):
        segment_attributes(labels, *rest, n_segments=K - 1)
    with pytest.raises(ValueError):  # the reference fails too (mismatched shapes)
        segment_attributes_reference(labels, *rest, n_segments=K - 1)


def test_mismatched_shapes_are_named():
    labels, xyz, inten, rng, t_off, ground = attribute_scene(5, 16, 64, 5, False)
    with pytest.raises(ComputationError, match="points"):
        segment_attributes(labels, xyz[:, :-1], inten, rng, t_off, ground)
    with pytest.raises(ComputationError, match="ground_z"):
        segment_attributes(labels, xyz, inten, rng, t_off, ground[:-1])


def test_points_that_are_not_finite_fail_as_in_the_reference():
    labels, xyz, inten, rng, t_off, ground = attribute_scene(7, 16, 64, 5, False)
    xyz[labels == 0] = np.nan
    for f in (segment_attributes, segment_attributes_reference):
        with pytest.raises(np.linalg.LinAlgError):
            f(labels, xyz, inten, rng, t_off, ground)


def test_kernel_minima_and_maxima_are_nan_with_a_nan_point():
    """The point NaN never reaches them through segment_attributes (the decomposition fails
    first, as in the reference), but they keep ``np.minimum.reduceat``'s NaN."""
    lab = np.array([0, 0, -1, 1, 1, 1])
    p = np.arange(18.0).reshape(6, 3)
    p[4, 2] = np.nan
    runs, first = _segment_runs(lab, -1)
    ones = np.ones(6)
    n, c, _cov, z0, z1, g_n, g_sum, *_ = _segment_sums(runs, first, p, ones, ones, lab, ones)
    assert list(n) == [2, 3] and z0[0] == 2.0 and z1[0] == 5.0
    assert np.isnan(z0[1]) and np.isnan(z1[1])
    p[4] = np.nan
    _center, length, width, *_ = _segment_box(
        runs, first, p, c, np.ones(2), np.zeros(2), z0, z1, g_n, g_sum
    )
    assert length[0] == 3.0 and width[0] == 3.0
    assert np.isnan(length[1]) and np.isnan(width[1])


def _range_image(rng: np.random.Generator, H: int = 8, W: int = 360) -> tuple:
    """Labels and ranges (m) of three segments seen by a LADAR with 2 cm range noise: 0 a
    plane seen obliquely (range growing along the row), 1 a bush whose returns come from
    0.2 m inside it on average (exponentially distributed), 2 a smooth curved body (a car's
    flank or a rock) across the wrap of the columns."""
    labels = np.full((H, W), -1, np.int64)
    r = np.full((H, W), 50.0)
    cols = np.arange(W)
    labels[2:6, 100:140] = 0
    r[2:6, 100:140] = 10.0 / np.cos(np.deg2rad(np.linspace(20, 60, 40)))
    labels[2:6, 200:230] = 1
    r[2:6, 200:230] = 15.0 + rng.exponential(0.2, (4, 30))
    body = (cols < 10) | (cols >= W - 10)
    labels[1:7, body] = 2
    x = ((cols[body] + 10) % W - 10) / 10.0  # -1 .. 1 across the wrap
    r[1:7, body] = 8.0 + 0.5 * x**2
    r += rng.normal(0.0, 0.02, r.shape)
    return labels, r


def test_roughness_tells_foliage_from_surfaces():
    labels, r = _range_image(np.random.default_rng(5))
    plane, bush, body = segment_roughness(labels, r, 3)
    # 2 cm noise: a second difference of it has a mean |.| of 0.02 * sqrt(6) * sqrt(2 / pi)
    assert 0.02 < plane < 0.06 and 0.02 < body < 0.06
    assert bush > 0.2


def test_roughness_needs_triples_of_one_segment_in_a_row():
    labels = np.full((3, 20), -1, np.int64)
    r = np.full((3, 20), 10.0)
    labels[0, 2:6] = 0  # 2 triples
    labels[1, 2:9] = 1  # 5 triples
    labels[2, ::2] = 2  # every other column: no two side by side
    r[1, 2:9] = 10.0 + 0.01 * np.array([0, 1, 0, 1, 0, 1, 0])  # second differences of 2 cm
    r[1, 5] = 30.0  # a return through a window, or from the object beside: 3 triples of 5
    rough = segment_roughness(labels, r, 4)
    assert np.isnan(rough[0]) and np.isnan(rough[2]) and np.isnan(rough[3])
    assert rough[1] > 1.0  # 3 of the 5 triples are the jump: the median is one of them
    # back on the surface; a jump at column 3 touches 2 triples of 5: the median is the surface's
    r[1, 5] = 10.01
    r[1, 3] = 30.0
    assert segment_roughness(labels, r, 4)[1] == pytest.approx(0.02, abs=0.01)


def test_roughness_refuses_a_range_image_of_another_shape():
    labels = np.zeros((4, 10), np.int64)
    with pytest.raises(ComputationError, match=r"range_m \(4, 9\)"):
        segment_roughness(labels, np.zeros((4, 9)), 1)
