"""The compiled per-segment attributes (sp.computation.segment_attributes) against the numpy
definition (segment_attributes_reference): every field of SegmentAttributes the same, to the
last bit, on random label images (no, one and ~60 segments, one-pixel, planar and collinear
segments, segments interleaved pixel by pixel, labels with gaps, points 1000 m from the
origin, unknown ground and NaN / infinite intensities and NaN ranges), with more segments
asked for than labelled, on other dtypes and strided inputs, and on a simulated sweep as the
pipeline computes it.

Why exact and not a tolerance: the kernel adds each segment's pixels in flat order, the
order ``np.bincount`` adds them in, with the reference's expressions (no reordering, no
fused multiply-add), and hands the same covariance matrices to the same ``np.linalg.eigh``.
A tolerance would not be safer: the yaw of a nearly round footprint, and with it the
extents along it, change by a lot for a last-bit change of the covariance.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from kernel_reference.computation_reference import segment_attributes_reference

from sp.computation import (
    ComputationError,
    SegmentAttributes,
    _segment_box,
    _segment_runs,
    _segment_sums,
    segment_attributes,
)

FIELDS = [f.name for f in dataclasses.fields(SegmentAttributes)]


def scene(
    seed: int, H: int, W: int, n_blobs: int, far: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Arguments of segment_attributes: labels (H, W) int64, points (H, W, 3) float64 m,
    intensity (H, W) float32, range (H, W) float32 m, time offsets (H, W) int64 ns, ground
    height (H, W) float64 m.

    ``n_blobs`` rectangles of pixels on a rough surface; with ``n_blobs > 1`` also a planar
    and a collinear segment, pixels of existing segments scattered over the image (segments
    interleaved in flat order), labels below -1 (no segment), one-pixel segments and no
    pixel of segment 2 (a segment without pixels inside 0..K-1). ``far``: the points about
    1000 m from the origin (sums of large numbers: rounding).
    """
    g = np.random.default_rng(seed)
    labels = np.full((H, W), -1, np.int64)
    for k in range(n_blobs):
        h, w = g.integers(1, max(2, H // 3)), g.integers(1, max(2, W // 12))
        i, j = g.integers(0, H - h + 1), g.integers(0, W - w + 1)
        labels[i : i + h, j : j + w] = k
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    xyz = np.stack(
        [0.2 * cols, 0.1 * rows, np.sin(0.05 * cols) + 0.3 * rows / H], axis=-1
    ) + g.normal(0.0, 0.05, (H, W, 3))
    k = n_blobs
    if n_blobs > 1:
        # a planar segment (z constant: zero smallest eigenvalue) and a collinear one
        labels[H - 2 :, : W // 8] = k
        xyz[H - 2 :, : W // 8, 2] = 0.5
        labels[0, W // 2 : W // 2 + W // 8] = k + 1
        xyz[0, W // 2 : W // 2 + W // 8, 1:] = 2.0
        k += 2
        # scattered pixels of existing segments, and "no segment" written as -7
        scatter = g.random((H, W)) < 0.05
        labels[scatter] = g.integers(0, k, int(scatter.sum()))
        labels[g.random((H, W)) < 0.02] = -7
        for _ in range(5):  # one-pixel segments
            labels[g.integers(0, H), g.integers(0, W)] = k
            k += 1
        labels[labels == 2] = -1  # a gap in the labels: segment 2 without pixels
        labels[H - 1, 0] = n_blobs  # (the planar segment's pixel with a NaN range below)
    if far:
        xyz += np.array([1000.0, -1500.0, 40.0])
    intensity = g.uniform(0.0, 100.0, (H, W)).astype(np.float32)
    intensity[g.random((H, W)) < 0.1] = np.nan
    intensity.flat[g.integers(0, H * W, 3)] = np.inf
    intensity.flat[g.integers(0, H * W, 3)] = -np.inf
    rng = np.linalg.norm(xyz, axis=-1).astype(np.float32)
    if n_blobs > 1:
        # one NaN range in the planar segment: the reference's minimum is NaN
        rng[H - 1, 0] = np.nan
    t_off = g.integers(0, 100_000_000, (H, W))
    ground = xyz[..., 2] - g.uniform(0.0, 2.0, (H, W))
    ground[g.random((H, W)) < 0.3] = np.nan
    ground.flat[g.integers(0, H * W, 3)] = np.inf
    ground[labels == 0] = np.nan  # a segment without ground below it
    return labels, xyz, intensity, rng, t_off, ground


def assert_same(*args, **kwargs) -> SegmentAttributes:
    """The compiled and the numpy attributes are the same in every field (values, NaN
    where the reference has NaN, dtype and shape); returns the reference's."""
    got = segment_attributes(*args, **kwargs)
    want = segment_attributes_reference(*args, **kwargs)
    assert len(got) == len(want)
    for name in FIELDS:
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name, strict=True)
    return want


@pytest.mark.parametrize("far", [False, True])
@pytest.mark.parametrize("n_blobs", [0, 1, 60])
@pytest.mark.parametrize("H, W", [(16, 64), (64, 1024)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kernel_gives_the_reference_attributes(seed, H, W, n_blobs, far):
    args = scene(seed, H, W, n_blobs, far)
    want = assert_same(*args)
    labels = args[0]
    assert len(want) == labels.max(initial=-1) + 1
    if n_blobs == 0:
        assert len(want) == 0
    elif n_blobs == 1:
        assert len(want) == 1 and want.n_pixels[0] == (labels == 0).sum()
    else:
        # the cases the scene is built to hold are there
        assert (want.n_pixels == 1).any()  # one-pixel segments
        assert want.n_pixels[2] == 0 and want.range_m[2] == np.inf  # the gap
        assert np.isnan(want.range_m[n_blobs]) and np.isfinite(want.range_m[0])
        assert np.isfinite(want.ground_z_m).all()  # the segment's lowest point without ground
        assert np.isfinite(want.intensity).all()  # NaN and inf intensities as nan_to_num
        if far:
            assert (np.abs(want.centroid_xyz[want.n_pixels > 0, 0]) > 900.0).all()


def test_more_segments_than_labelled():
    labels, *rest = scene(3, 64, 1024, 60, True)
    K = int(labels.max()) + 1
    want = assert_same(labels, *rest, n_segments=K + 5)
    assert len(want) == K + 5
    extra = want.take(np.arange(K, K + 5))
    assert (extra.n_pixels == 0).all() and np.isinf(extra.range_m).all()
    assert (extra.length_m == 0.0).all() and (extra.height_m == 0.0).all()
    # and none labelled at all, several segments asked for
    assert len(assert_same(np.full_like(labels, -1), *rest, n_segments=3)) == 3


def test_fewer_segments_than_labelled_is_an_error():
    labels, *rest = scene(4, 16, 64, 60, False)
    K = int(labels.max()) + 1
    with pytest.raises(ComputationError, match="n_segments"):
        segment_attributes(labels, *rest, n_segments=K - 1)
    with pytest.raises(ValueError):  # the reference fails too (mismatched shapes)
        segment_attributes_reference(labels, *rest, n_segments=K - 1)


def test_mismatched_shapes_are_named():
    labels, xyz, inten, rng, t_off, ground = scene(5, 16, 64, 5, False)
    with pytest.raises(ComputationError, match="points"):
        segment_attributes(labels, xyz[:, :-1], inten, rng, t_off, ground)
    with pytest.raises(ComputationError, match="ground_z"):
        segment_attributes(labels, xyz, inten, rng, t_off, ground[:-1])


def test_other_dtypes_and_strided_inputs():
    """int32 labels, float32 points and ranges, float64 intensity, int32 time offsets; then
    views with strides (every other column of wider images)."""
    labels, xyz, inten, rng, t_off, ground = scene(6, 64, 1024, 60, True)
    assert_same(
        labels.astype(np.int32),
        xyz.astype(np.float32),
        inten.astype(np.float64),
        rng,
        t_off.astype(np.int32),
        ground,
    )
    wide = [np.repeat(a, 2, axis=1) for a in (labels, xyz, inten, rng, t_off, ground)]
    views = [a[:, ::2] for a in wide]
    assert not views[0].flags.c_contiguous and not views[1].flags.c_contiguous
    assert len(assert_same(*views)) == labels.max() + 1


def test_points_that_are_not_finite_fail_as_in_the_reference():
    labels, xyz, inten, rng, t_off, ground = scene(7, 16, 64, 5, False)
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


@pytest.fixture(scope="module")
def pipeline_calls():
    """The arguments of every segment_attributes call of the pipeline on a few simulated
    sweeps (before and after the merge of collinear pieces)."""
    import kd_store
    import sp.level4_objects
    from fixtures.simulate import simulate
    from logs.types import GroundTruthPose, LadarScan, TransformFrame
    from wm.entities import KDSensoryProcessor

    calls = []

    def recording(*args, **kwargs):
        calls.append((args, kwargs))
        return segment_attributes(*args, **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(sp.level4_objects, "segment_attributes", recording)
    try:
        proc = KDSensoryProcessor(kd_store.open(":memory:"))
        T_body_ladar = T_world_body = None
        for f in simulate("default", seconds=0.35):
            if isinstance(f, TransformFrame) and f.child_frame_id == "ladar":
                T_body_ladar = f.T_parent_child
            elif isinstance(f, GroundTruthPose):
                T_world_body = f.T_parent_child
            elif isinstance(f, LadarScan) and T_body_ladar is not None:
                if T_world_body is not None:
                    proc.process(f, T_world_body @ T_body_ladar)
    finally:
        mp.undo()
    return calls


def test_kernel_gives_the_reference_attributes_on_simulated_sweeps(pipeline_calls):
    assert len(pipeline_calls) >= 3
    for args, kwargs in pipeline_calls:
        want = assert_same(*args, **kwargs)
        assert len(want) >= 5 and (want.n_pixels > 0).all()
