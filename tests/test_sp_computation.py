"""Per-segment attributes (sp.computation.segment_attributes) beyond their oracle: the
arguments it refuses (by name, and as the numpy reference fails), and the NaN its minima and
maxima keep. Its equivalence to ``segment_attributes_reference`` is a case family of
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
