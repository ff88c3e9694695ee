"""Compiled kernels against their numpy oracles: one parametrised harness.

Each :class:`Case` names a kernel, the inputs it is called on (a generator of argument
tuples, seeded per parameter), the kernel call, the reference call (the oracles in
``tests/kernel_reference``) and the comparison: ``np.testing.assert_array_equal`` where the
kernel is the reference bit for bit, a tolerance where it is the reference to rounding. A
case's ``check`` holds the assertions about what the inputs exercised (both answers occur,
something was found), given every call's results. Argument checks of the kernels and tests of
their behaviour beyond the reference are in the modules' own test files.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import pytest
from conftest import REAL_DATA
from kernel_reference.computation_reference import (
    ground_below_reference,
    ground_plane_reference,
    segment_attributes_reference,
)
from kernel_reference.covariance_reference import psd_mask_reference
from kernel_reference.egosphere_reference import to_egosphere_reference
from kernel_reference.ground_reference import column_walk_reference, refine_reference
from kernel_reference.poses_reference import deskew_to_world_reference
from kernel_reference.pyramid_reference import register_reference
from kernel_reference.sweep_points_reference import sweep_points_reference
from kernel_reference.voxels_reference import first_per_voxel_reference
from kernel_scenes import (
    attribute_scene,
    crops,
    non_ground,
    random_scan,
    scan_of,
    segment_scene,
    texture,
)

from core.geometry import interpolate_pose, rotvec_to_matrix, se3, transform_points
from kd_store.covariance import pack_covariance, psd_mask
from logs.types import LadarScan
from maps.pyramid import Match, register
from sp.computation import SegmentAttributes, ground_below, ground_plane, segment_attributes
from sp.egosphere import EgosphereConfig, to_egosphere
from sp.ground import GroundConfig, column_walk, refine
from sp.segments import SegmentConfig, label_objects, label_objects_reference
from sp.sweep_points import sweep_points
from sp.voxels import first_per_voxel
from wm.poses import PoseTrack, deskew_to_world

Args = tuple[Any, ...]
Call = tuple[Args, Any, Any]  # (arguments, kernel's result, reference's result)


@dataclass(frozen=True)
class Case:
    """A kernel and its oracle on a family of inputs.

    inputs(param) yields argument tuples; kernel(*args) and reference(*args) are compared
    by compare(got, want, args); check(param, calls) asserts what the inputs exercised.
    """

    name: str
    params: list[Any]
    inputs: Callable[[Any], Iterator[Args]]
    kernel: Callable[..., Any]
    reference: Callable[..., Any]
    compare: Callable[[Any, Any, Args], None]
    check: Callable[[Any, list[Call]], None] | None = None
    marks: list[Any] = field(default_factory=list)


def _equal(got: Any, want: Any, args: Args) -> None:
    """Bit for bit (NaN where NaN)."""
    np.testing.assert_array_equal(got, want)


# --- sp.ground: column walk and refinement (the same masks) ---------------------------------


def _ground_scene(seed: int, h: int = 64, w: int = 256, p_invalid: float = 0.1):
    """A LADAR-like egosphere (sensor 1.8 m up, beams from +0.3 to -0.4 rad) with noise,
    raised returns (objects) and holes; x, y, z (H, W) float64 m, zero where invalid, as
    ground_mask gives; valid (H, W) bool."""
    rng = np.random.default_rng(seed)
    el = np.linspace(0.3, -0.4, h)[:, None]
    az = np.linspace(-np.pi, np.pi, w, endpoint=False)[None]
    rng_m = np.minimum(1.8 / np.maximum(np.tan(-el), 0.02), 80.0)
    rng_m = rng_m * (1 + 0.05 * rng.standard_normal((h, w)))
    z = rng_m * np.tan(el) + 0.05 * rng.standard_normal((h, w))
    z[rng.random((h, w)) < 0.05] += rng.uniform(0.1, 2.0)
    valid = rng.random((h, w)) >= p_invalid
    x, y = rng_m * np.cos(az), rng_m * np.sin(az)
    return (*(np.where(valid, a, 0.0) for a in (x, y, z)), valid)


GROUND_SCENES = [(0, 0.1), (1, 0.0), (2, 0.6), (3, 1.0)]  # (seed, fraction invalid)
WALK_HEIGHTS_M = (1.2, 1.8, 2.5)


def _walk_inputs(param: tuple[int, float]) -> Iterator[Args]:
    seed, p_invalid = param
    x, y, z, valid = _ground_scene(seed, p_invalid=p_invalid)
    r = np.hypot(x, y)
    for h in WALK_HEIGHTS_M:
        yield r, z, valid, h, GroundConfig()


def _walk_check(param: tuple[int, float], calls: list[Call]) -> None:
    walk = calls[-1][1]
    assert param[1] == 1.0 or walk.any()


def _refine_grounds(param: tuple[int, float]) -> Iterator[tuple[np.ndarray, ...]]:
    """x, y, z, valid, ground, r: the scene with the walk's mask (last height), a random
    mask, none and every valid pixel as ground."""
    seed, p_invalid = param
    cfg = GroundConfig()
    x, y, z, valid = _ground_scene(seed, p_invalid=p_invalid)
    r = np.hypot(x, y)
    walk = column_walk(r, z, valid, WALK_HEIGHTS_M[-1], cfg)
    rng = np.random.default_rng(seed)
    for ground in (walk, rng.random(valid.shape) < 0.5, np.zeros_like(valid), valid):
        yield x, y, z, valid, ground, r


def _refine_inputs(param: tuple[int, float]) -> Iterator[Args]:
    for x, y, z, valid, ground, _ in _refine_grounds(param):
        yield x, y, z, valid, ground, GroundConfig()


def _refine_given_ranges_inputs(param: tuple[int, float]) -> Iterator[Args]:
    yield from _refine_grounds(param)


DEGENERATE_GROUND = GroundConfig(n_sectors=1, cell_m=0.5)


def _degenerate_scenes() -> Iterator[tuple[np.ndarray, ...]]:
    """1 x 1, 1 x 7 and 9 x 1 images, each with a NaN return that claims to be valid."""
    for shape in ((1, 1), (1, 7), (9, 1)):
        x, y, z, valid = (a[: shape[0], : shape[1]] for a in _ground_scene(5, 9, 7, 0.2))
        z = z.copy()
        z[0, 0] = np.nan
        yield x, y, z, valid


def _degenerate_walk_inputs(_: None) -> Iterator[Args]:
    for x, y, z, valid in _degenerate_scenes():
        yield np.hypot(x, y), z, valid, 1.8, DEGENERATE_GROUND


def _degenerate_refine_inputs(_: None) -> Iterator[Args]:
    for x, y, z, valid in _degenerate_scenes():
        walk = column_walk(np.hypot(x, y), z, valid, 1.8, DEGENERATE_GROUND)
        for ground in (walk, valid, ~valid):
            yield x, y, z, valid, ground, DEGENERATE_GROUND


# --- sp.computation: ground below each pixel, ground plane ------------------------------------


def _ground_below_inputs(param: tuple[int, float]) -> Iterator[Args]:
    seed, p_ground = param
    rng = np.random.default_rng(seed)
    shape = (64, 300)
    ground = rng.random(shape) < p_ground
    z = rng.normal(0.0, 2.0, shape)
    r = np.abs(rng.normal(20.0, 15.0, shape))
    r[rng.random(shape) < 0.05] = np.nan  # empty pixels
    z[rng.random(shape) < 0.02] = np.nan
    for r_m in (None, r):
        for slope, reach in ((0.3, 15.0), (0.0, 1.0), (2.0, 100.0)):
            yield ground, z, r_m, slope, reach


def _ground_below_check(param: tuple[int, float], calls: list[Call]) -> None:
    assert param[1] == 0.0 or np.isfinite(calls[-1][1]).any()


def _ground_below_degenerate_inputs(_: None) -> Iterator[Args]:
    for shape in ((1, 1), (1, 5), (6, 1)):
        ground = np.ones(shape, dtype=bool)
        z, r = np.arange(np.prod(shape), dtype=float).reshape(shape), np.ones(shape)
        yield ground, z, r


def _ground_plane_inputs(param: tuple[int, float]) -> Iterator[Args]:
    """A tilted noisy plane 60 m wide, far from the origin, partly marked ground."""
    seed, p_ground = param
    rng = np.random.default_rng(seed)
    centre = np.array([1000.0, -2000.0, 51.9])
    xy = centre[:2] + rng.uniform(-30, 30, (64, 128, 2))
    z = (
        50.0
        + 0.05 * (xy[..., 0] - 1000)
        - 0.02 * (xy[..., 1] + 2000)
        + rng.normal(0, 0.03, xy.shape[:2])
    )
    xyz = np.dstack([xy, z])
    ground = rng.random((64, 128)) < p_ground
    yield xyz, ground, centre, 20.0


def _ground_plane_compare(got: Any, want: Any, args: Args) -> None:
    """The same plane, roughness and count (None under 10 points), and the plane it is."""
    if want is None:
        assert got is None
        return
    assert got is not None and got[2] == want[2] > 10
    np.testing.assert_allclose(got[0], want[0], rtol=1e-9, atol=1e-12)
    assert got[1] == pytest.approx(want[1], rel=1e-6)
    np.testing.assert_allclose(got[0][:2], [0.05, -0.02], atol=0.01)  # the plane it is
    assert got[1] == pytest.approx(0.03, rel=0.2)


# --- kd_store.covariance: the compiled PSD test against the unrolled numpy factorisation -----


def _covariances(n: int, seed: int) -> np.ndarray:
    """(n, 6, 6): PSD, rank-deficient (PSD by the tolerance or not), indefinite, zero, NaN,
    inf and huge matrices mixed."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 6, 6))
    A[1::4, :, 3:] = 0.0  # rank 3
    C = A @ A.transpose(0, 2, 1)
    C[2::5] -= np.eye(6) * rng.uniform(1e-12, 1.0, (len(C[2::5]), 1, 1))  # some indefinite
    C[3::11] = 0.0
    C[4::13, 1, 1] = np.nan
    C[5::17, 0, 5] = C[5::17, 5, 0] = np.inf
    C[6::19] *= 1e150
    return C


def _psd_inputs(param: tuple[int, int]) -> Iterator[Args]:
    """Every tolerance without and then with a given scale (7 for every matrix)."""
    n, seed = param
    cov21 = pack_covariance(_covariances(n, seed))
    for tol in (1e-9, 0.0, 1e-3):
        yield cov21, tol
        yield cov21, tol, np.full(n, 7.0)


def _psd_check(param: tuple[int, int], calls: list[Call]) -> None:
    n = param[0]
    got = calls[-2][1]  # the last tolerance, scale from the matrices
    if n >= 500:
        assert 0 < got.sum() < n  # both answers occur


# --- sp.sweep_points: sensor, gravity-aligned and world points of each pixel ----------------


def _random_sweep(seed: int, p_invalid: float):
    """A random 16 x 64 sweep (some beams empty, NaN where no return) as an egosphere image,
    with a random sensor pose (4, 4) and per-column poses (64, 4, 4)."""
    rng = np.random.default_rng(seed)
    n = 16 * 64
    az = rng.uniform(-np.pi, np.pi, n)
    el = np.radians(rng.uniform(-14.0, 14.0, n))
    r = rng.uniform(1.0, 80.0, n)
    xyz = np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    )
    keep = rng.random(n) >= p_invalid
    scan = LadarScan(
        1_000_000_000, "ladar", xyz[keep].astype(np.float32), np.ones(int(keep.sum()), np.float32),
        rng.integers(0, 100_000_000, int(keep.sum())).astype(np.int64),
    )  # fmt: skip
    img = to_egosphere(scan, EgosphereConfig(n_rows=16, n_cols=64))
    rot = rng.normal(0, 0.3, 3)
    T = se3(rotvec_to_matrix(rot), rng.normal(0, 50, 3))
    T_prev = se3(rotvec_to_matrix(rot + rng.normal(0, 0.05, 3)), T[:3, 3] - rng.normal(0, 1, 3))
    T_cols = interpolate_pose(T_prev, T, rng.uniform(0.5, 1.5, img.valid_first.shape[1]))
    return img, T, T_cols


def _sweep_points_inputs(param: tuple[bool, float, int]) -> Iterator[Args]:
    per_column, p_invalid, seed = param
    img, T, T_cols = _random_sweep(seed, p_invalid)
    yield img, T[:3, :3], T_cols if per_column else T[None]


def _sweep_points_compare(got: Any, want: Any, args: Args) -> None:
    for name, g, w in zip(("xyz_s", "xyz_g", "xyz_w", "row_el"), got, want, strict=True):
        assert g.shape == w.shape, name
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-9, err_msg=name)
        assert np.array_equal(np.isnan(g), np.isnan(w)), name


def _sweep_points_check(param: tuple[bool, float, int], calls: list[Call]) -> None:
    got = calls[-1][1]
    if param[1] == 1.0:
        assert np.isnan(got[3]).all() and not got[0].any()


# --- wm.poses: de-skewing a sweep to the world slice by slice ---------------------------------


@dataclass
class _DeskewScene:
    """A two-pose track, the sensor mount and points with their times in the sweep."""

    track: PoseTrack
    T0: np.ndarray
    T1: np.ndarray
    T_body_sensor: np.ndarray
    pts: np.ndarray
    off: np.ndarray


def _deskew_scene(seed: int, order: str, dtype: type) -> _DeskewScene:
    rng = np.random.default_rng(seed)
    track = PoseTrack()
    T0 = se3(rotvec_to_matrix(rng.normal(0, 0.5, 3)), rng.normal(0, 100, 3))
    T1 = T0 @ se3(rotvec_to_matrix([0, 0, 0.2]), [1.5, 0.1, 0.0])
    track.add(0, T0)
    track.add(100_000_000, T1)
    T_body_sensor = se3(rotvec_to_matrix([0.0, 0.05, 0.0]), [0.3, 0.0, 1.9])
    n = 5000
    off = np.sort(rng.integers(0, 100_000_000, n))
    off[0], off[-1] = 0, 99_999_999
    if order == "shuffled":
        off = rng.permutation(off)
    pts = rng.uniform(-60, 60, (n, 3)).astype(dtype)
    return _DeskewScene(track, T0, T1, T_body_sensor, pts, off)


def _deskew_inputs(param: tuple[type, str, int]) -> Iterator[Args]:
    dtype, order, seed = param
    s = _deskew_scene(seed, order, dtype)
    yield s.pts, s.off, 0, s.track, s.T_body_sensor, 8


def _deskew_compare(got: Any, want: Any, args: Args) -> None:
    assert got.dtype == np.float64 and got.shape == (len(args[0]), 3)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def _deskew_check(param: tuple[type, str, int], calls: list[Call]) -> None:
    """A point at the start and one at the end of the sweep move with the first and last
    slice's pose."""
    s = _deskew_scene(param[2], param[1], param[0])
    got = calls[-1][1]
    span = int(s.off.max())
    for i, b in ((int(np.argmin(s.off)), 0), (int(np.argmax(s.off)), 7)):
        T = interpolate_pose(s.T0, s.T1, (b + 0.5) / 8 * span / 100_000_000) @ s.T_body_sensor
        np.testing.assert_allclose(got[i], transform_points(T, s.pts[i : i + 1].astype(float))[0])


# --- sp.voxels: the first point of each voxel ---------------------------------------------------


def _voxel_inputs(param: tuple[float, int]) -> Iterator[Args]:
    voxel_m, seed = param
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.normal(0, 10, (4000, 3)), rng.uniform(-3, 3, (4000, 3))])
    pts[::7] = pts[1::7][: len(pts[::7])]  # repeats: later copies are never kept
    yield pts, voxel_m


def _voxel_check(param: tuple[float, int], calls: list[Call]) -> None:
    """Increasing indices, one per voxel, and KISS-ICP's down-sampling keeps the same points."""
    from kiss_icp.voxelization import voxel_down_sample

    (pts, voxel_m), got, _ = calls[-1]
    assert np.all(np.diff(got) > 0)
    keys = np.floor(pts / voxel_m)
    assert len(np.unique(keys[got], axis=0)) == len(got) == len(np.unique(keys, axis=0))
    kiss = voxel_down_sample(pts, voxel_m)
    assert {tuple(p) for p in np.asarray(kiss)} == {tuple(p) for p in pts[got]}


# --- sp.computation: per-segment attributes (every field, to the last bit) -------------------
#
# Why exact and not a tolerance: the kernel adds each segment's pixels in flat order, the
# order ``np.bincount`` adds them in, with the reference's expressions (no reordering, no
# fused multiply-add), and hands the same covariance matrices to the same ``np.linalg.eigh``.
# A tolerance would not be safer: the yaw of a nearly round footprint, and with it the
# extents along it, change by a lot for a last-bit change of the covariance.

ATTRIBUTE_FIELDS = [f.name for f in dataclasses.fields(SegmentAttributes)]


def _same_attributes(got: Any, want: Any, args: Args) -> None:
    """Every field the same (values, NaN where the reference has NaN, dtype and shape)."""
    assert len(got) == len(want)
    for name in ATTRIBUTE_FIELDS:
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name, strict=True)


def _attribute_inputs(param: tuple[int, tuple[int, int], int, bool]) -> Iterator[Args]:
    """No, one and ~60 segments (one-pixel, planar and collinear ones, interleaved pixel by
    pixel, labels with gaps, unknown ground, NaN / infinite intensities and NaN ranges),
    near and 1000 m from the origin (kernel_scenes.attribute_scene)."""
    seed, (H, W), n_blobs, far = param
    yield attribute_scene(seed, H, W, n_blobs, far)


def _attribute_check(param: tuple[int, tuple[int, int], int, bool], calls: list[Call]) -> None:
    """The cases the scene is built to hold are there."""
    _, _, n_blobs, far = param
    args, _, want = calls[-1]
    labels = args[0]
    assert len(want) == labels.max(initial=-1) + 1
    if n_blobs == 0:
        assert len(want) == 0
    elif n_blobs == 1:
        assert len(want) == 1 and want.n_pixels[0] == (labels == 0).sum()
    else:
        assert (want.n_pixels == 1).any()  # one-pixel segments
        assert want.n_pixels[2] == 0 and want.range_m[2] == np.inf  # the gap
        assert np.isnan(want.range_m[n_blobs]) and np.isfinite(want.range_m[0])
        assert np.isfinite(want.ground_z_m).all()  # the segment's lowest point without ground
        assert np.isfinite(want.intensity).all()  # NaN and inf intensities as nan_to_num
        if far:
            assert (np.abs(want.centroid_xyz[want.n_pixels > 0, 0]) > 900.0).all()


def _more_segments_inputs(_: None) -> Iterator[Args]:
    """More segments asked for than labelled; then none labelled, several asked for."""
    labels, *rest = attribute_scene(3, 64, 1024, 60, True)
    yield labels, *rest, int(labels.max()) + 6
    yield np.full_like(labels, -1), *rest, 3


def _more_segments_check(_: None, calls: list[Call]) -> None:
    (args, _, want), (_, _, none) = calls
    K = int(args[0].max()) + 1
    assert len(want) == K + 5
    extra = want.take(np.arange(K, K + 5))
    assert (extra.n_pixels == 0).all() and np.isinf(extra.range_m).all()
    assert (extra.length_m == 0.0).all() and (extra.height_m == 0.0).all()
    assert len(none) == 3


def _attribute_dtype_inputs(_: None) -> Iterator[Args]:
    """int32 labels, float32 points and ranges, float64 intensity, int32 time offsets; then
    views with strides (every other column of wider images)."""
    labels, xyz, inten, rng, t_off, ground = attribute_scene(6, 64, 1024, 60, True)
    yield (labels.astype(np.int32), xyz.astype(np.float32), inten.astype(np.float64), rng,
           t_off.astype(np.int32), ground)  # fmt: skip
    wide = [np.repeat(a, 2, axis=1) for a in (labels, xyz, inten, rng, t_off, ground)]
    yield tuple(a[:, ::2] for a in wide)


def _attribute_dtype_check(_: None, calls: list[Call]) -> None:
    views, _, want = calls[-1]
    assert not views[0].flags.c_contiguous and not views[1].flags.c_contiguous
    assert len(want) == views[0].max() + 1


@functools.cache
def _pipeline_attribute_calls() -> list[Args]:
    """The arguments of every segment_attributes call of the pipeline on a few simulated
    sweeps (before and after the merge of collinear pieces)."""
    import kd_store
    import sp.level4_objects
    from fixtures.simulate import simulate
    from logs.types import GroundTruthPose, TransformFrame
    from wm.entities import KDSensoryProcessor

    calls: list[Args] = []

    def recording(*args: Any, **kwargs: Any) -> SegmentAttributes:
        assert not kwargs  # the harness passes arguments by position
        calls.append(args)
        return segment_attributes(*args)

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


def _pipeline_attribute_inputs(_: None) -> Iterator[Args]:
    yield from _pipeline_attribute_calls()


def _pipeline_attribute_check(_: None, calls: list[Call]) -> None:
    assert len(calls) >= 3
    for _, _, want in calls:
        assert len(want) >= 5 and (want.n_pixels > 0).all()


# --- sp.egosphere: the image of a scan (bit for bit, the NaN of an empty pixel too) ----------

# the reference casts NaN angles of dropped points to int32
EGOSPHERE_CAST = pytest.mark.filterwarnings(
    "ignore:invalid value encountered in cast:RuntimeWarning"
)


def _same_image(got: Any, want: Any, args: Args) -> None:
    """The same point in every pixel and layer, the same ranges (NaN where empty, to the
    bit), the same memory layout, drop and overflow counts."""
    scan, cfg = args
    shape = (cfg.n_rows, cfg.n_cols, cfg.max_returns)
    assert got.point_index.shape == want.point_index.shape == shape
    assert got.point_index.dtype == np.int32 and got.range_m.dtype == np.float32
    # the same memory layout (the reference's (K, rows, cols) arrays seen as (rows, cols, K))
    assert got.point_index.strides == want.point_index.strides
    assert got.range_m.strides == want.range_m.strides
    np.testing.assert_array_equal(got.point_index, want.point_index)
    np.testing.assert_array_equal(np.isnan(got.range_m), np.isnan(want.range_m))
    np.testing.assert_array_equal(got.range_m, want.range_m)
    # bit for bit, the NaN of an empty pixel too (the reference's is the all-ones key's half,
    # or np.nan in the layers it did not need to compute)
    np.testing.assert_array_equal(got.range_m.view(np.uint32), want.range_m.view(np.uint32))
    assert (got.n_dropped, got.n_overflow) == (want.n_dropped, want.n_overflow)
    assert got.n_dropped + got.n_overflow + int(got.valid.sum()) == scan.n_points


def _egosphere_inputs(param: tuple[int, int, bool, int]) -> Iterator[Args]:
    seed, n, with_ring, max_returns = param
    scan = random_scan(seed, n, with_ring, sweep_order=seed == 1)
    yield scan, EgosphereConfig(n_rows=64, n_cols=1024, max_returns=max_returns)


def _egosphere_check(param: tuple[int, int, bool, int], calls: list[Call]) -> None:
    img = calls[-1][1]
    assert img.n_dropped > 0  # NaN, near and out-of-span points were all there
    assert img.valid[..., 0].any()
    if param[1] == 70_000:  # several points per pixel: later layers and overflow exercised
        assert img.valid[..., -1].any() and img.n_overflow > 0


EGOSPHERE_GRIDS = {
    "100-cols": EgosphereConfig(n_rows=48, n_cols=100, max_returns=3),
    "no-ring-rows": EgosphereConfig(n_rows=48, n_cols=100, max_returns=2, use_ring=False),
    "ring-zero-at-top": EgosphereConfig(n_rows=64, n_cols=2048, ring_zero_at_bottom=False),
    # 0.7 m rounds down in float32: the reference keeps a range of float32(0.7)
    "min-range-0.7": EgosphereConfig(n_rows=16, n_cols=333, max_returns=1, min_range_m=0.7),
    "full-span": EgosphereConfig(elevation_min_deg=-90.0, elevation_max_deg=90.0, max_returns=4),
}


def _egosphere_grid_inputs(param: tuple[int, str]) -> Iterator[Args]:
    seed, grid = param
    for with_ring in (True, False):
        yield random_scan(10 + seed, 30_000, with_ring), EGOSPHERE_GRIDS[grid]


def _every_image_has_returns(_: Any, calls: list[Call]) -> None:
    assert all(got.valid.any() for _, got, _ in calls)


def _min_range_inputs(_: None) -> Iterator[Args]:
    """A point at float32(0.7) m and one a float below: numpy compares the float32 ranges
    with float32(min_range_m), which for 0.7 is below 0.7."""
    r = np.float32(0.7)
    below = np.nextafter(r, np.float32(0))
    assert float(below) < float(r) < 0.7
    scan = scan_of(np.array([[r, 0.0, 0.0], [below, 0.0, 0.0]]))
    assert np.linalg.norm(scan.points_xyz, axis=1).tolist() == [r, below]
    yield scan, EgosphereConfig(n_rows=4, n_cols=8, max_returns=1, min_range_m=0.7)


def _min_range_check(_: None, calls: list[Call]) -> None:
    img = calls[-1][1]
    assert img.point_index[img.valid].tolist() == [0] and img.n_dropped == 1


def _tie_inputs(max_returns: int) -> Iterator[Args]:
    """Four copies of one point and its mirror in z on one beam: one pixel, one range."""
    p = [12.0, 3.0, -0.5]
    pts = np.array([p, p, [12.0, 3.0, 0.5], p, [30.0, 7.5, -1.25]], np.float32)
    ring = np.full(len(pts), 5, np.uint16)
    yield scan_of(pts, ring), EgosphereConfig(n_rows=8, n_cols=16, max_returns=max_returns)


def _tie_check(max_returns: int, calls: list[Call]) -> None:
    """Ties in range go to the lower index."""
    (scan, _), img, _ = calls[-1]
    rows, cols = np.nonzero(img.valid[..., 0])
    assert len(rows) == 1
    assert img.point_index[rows[0], cols[0]].tolist() == [0, 1, 2][:max_returns]
    assert img.n_overflow == scan.n_points - max_returns


def _empty_scan_inputs(param: tuple[bool, int]) -> Iterator[Args]:
    """An empty scan; then one whose every point is dropped (NaN, too near, out of the beams
    or above the elevation span)."""
    with_ring, max_returns = param
    cfg = EgosphereConfig(n_rows=8, n_cols=32, max_returns=max_returns)
    yield scan_of(np.zeros((0, 3)), np.zeros(0, np.uint16) if with_ring else None), cfg
    pts = np.array([[np.nan, 1.0, 0.0], [0.1, 0.0, 0.0], [5.0, 0.0, 0.0]], np.float32)
    ring = np.array([0, 1, 99], np.uint16) if with_ring else None  # the last out of the beams
    if not with_ring:
        pts[2] = [5.0, 0.0, 4.0]  # 38 degrees up, above the elevation span
    yield scan_of(pts, ring), cfg


def _empty_scan_check(_: tuple[bool, int], calls: list[Call]) -> None:
    (_, empty, _), (_, dropped, _) = calls
    assert not empty.valid.any() and np.isnan(empty.range_m).all()
    assert empty.n_dropped == 0 and empty.n_overflow == 0
    assert not dropped.valid.any() and dropped.n_dropped == 3


def _ring_dtype_inputs(ring_dtype: type) -> Iterator[Args]:
    """Other ring dtypes are read as the reference reads them."""
    scan = random_scan(7, 5_000, with_ring=True)
    scan.ring = scan.ring.astype(ring_dtype)
    yield scan, EgosphereConfig(n_rows=64, n_cols=512, max_returns=2)


def _strided_scan_inputs(_: None) -> Iterator[Args]:
    """KITTI-like (N, 4) records whose first three columns are the points: a strided view."""
    scan = random_scan(3, 10_000, with_ring=False)
    records = np.concatenate([scan.points_xyz, scan.intensity[:, None]], axis=1)
    scan.points_xyz = records[:, :3]
    assert not scan.points_xyz.flags.c_contiguous
    yield scan, EgosphereConfig(max_returns=2)


# --- sp.segments: level-4 grouping (the same labels, exactly) --------------------------------

# every rule that has its own code path on and off: the row gap (links across empty rows),
# the range step, the near join of small far pieces; min_pixels drops speckle or not
SEGMENT_CONFIGS = [
    SegmentConfig(row_gap=g, step_m=s, near_pixels=n, min_pixels=k)
    for g, s, n, k in itertools.product((0, 2), (0.0, 0.2), (0, 10), (1, 4))
] + [
    # no range scaling along rows (r * 0, NaN for an infinite range), near join from 0 m
    SegmentConfig(join_per_rad=0.0, near_min_range_m=0.0, min_pixels=1),
    SegmentConfig(row_gap=5, step_m=0.05, step_frac=0.0, near_m=1.0, near_pixels=30),
]


def _label_objects_reference(*args: Any) -> np.ndarray:
    with np.errstate(invalid="ignore"):  # the reference's inf * 0 when join_per_rad is 0
        return label_objects_reference(*args)


def _same_labels(got: Any, want: Any, args: Args) -> None:
    assert got.dtype == want.dtype == np.int64 and got.shape == want.shape
    bad = np.flatnonzero(got.reshape(-1) != want.reshape(-1))
    assert bad.size == 0, f"{bad.size} pixels differ under {args[-1]}, first at {bad[:5]}"


SEGMENT_DTYPES = [
    (np.float64, np.float32, float),  # the pipeline's: float32 ranges, Python float steps
    (np.float64, np.float32, np.float64),  # numpy scalar steps: float64 limits
    (np.float64, np.float64, float),
    (np.float32, np.float32, float),
]


def _segment_inputs(param: tuple[tuple[int, int], int, tuple[type, type, type]]) -> Iterator[Args]:
    (H, W), seed, (xyz_dtype, rng_dtype, step_type) = param
    xyz, rng, valid, row_step, col_step = segment_scene(seed, H, W)
    mask = non_ground(xyz, valid, seed)
    assert mask.sum() > 0.05 * H * W  # a scene, not an empty image
    xyz, rng = xyz.astype(xyz_dtype), rng.astype(rng_dtype)
    for cfg in SEGMENT_CONFIGS:
        yield xyz, rng, mask, step_type(row_step), step_type(col_step), cfg


def _segment_check(_: Any, calls: list[Call]) -> None:
    """The configurations group the scene differently."""
    assert len({int(want.max()) + 1 for _, _, want in calls}) > 1


def _segment_any_mask_inputs(seed: int) -> Iterator[Args]:
    """A mask that is not a subset of the returns: links to pixels without a range (NaN, inf,
    0, -1; xyz 0) take numpy's NaN rules (np.minimum / np.maximum propagate NaN)."""
    xyz, rng, valid, row_step, col_step = segment_scene(seed, 64, 1024)
    mask = np.random.default_rng(seed).random(valid.shape) < np.where(valid, 0.8, 0.3)
    assert (mask & ~valid).sum() > 1000
    for cfg in SEGMENT_CONFIGS:
        yield xyz, rng, mask, row_step, col_step, cfg
        yield xyz, rng.astype(np.float32), mask, row_step, col_step, cfg


@functools.cache
def _simulated_grouping_sweep() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A simulated sweep as the pipeline groups it: float64 points, float32 ranges (inf where
    empty), a non-ground mask."""
    from fixtures.simulate import simulate

    scan = next(f for f in simulate("default", seconds=0.25) if isinstance(f, LadarScan))
    img = to_egosphere(scan, EgosphereConfig(n_rows=64, n_cols=1024, max_returns=1))
    valid = img.valid_first
    xyz = np.where(valid[..., None], img.xyz[..., 0, :], 0.0).astype(np.float64)
    rng = np.where(valid, img.range_first, np.inf)
    return xyz, rng, valid & (xyz[..., 2] > -1.5)


def _segment_simulated_inputs(_: None) -> Iterator[Args]:
    """Python float angular steps, as the pipeline passes them."""
    xyz, rng, mask = _simulated_grouping_sweep()
    assert rng.dtype == np.float32 and mask.sum() > 500
    for cfg in [SegmentConfig(min_pixels=1), SegmentConfig(), *SEGMENT_CONFIGS]:
        yield xyz, rng, mask, math.radians(1.0), 2 * math.pi / 1024, cfg


def _segment_simulated_check(_: None, calls: list[Call]) -> None:
    assert all(want.max() >= 10 for _, _, want in calls)  # objects were found


def _segment_degenerate_inputs(param: tuple[tuple[int, int], str]) -> Iterator[Args]:
    """No mask pixel, every pixel in the mask, and every pixel in the mask with no range; tiny
    images where the wrap links a pixel to itself or to its neighbour twice."""
    (H, W), fill = param
    xyz, rng, _, row_step, _ = segment_scene(7, 64, 64)
    xyz, rng = xyz[:H, :W].copy(), rng[:H, :W].copy()
    if fill == "all_no_range":
        rng[:] = np.nan
        xyz[:] = 0.0
    mask = np.full((H, W), fill != "none")
    for cfg in SEGMENT_CONFIGS:
        yield xyz, rng, mask, row_step, 2 * np.pi / W, cfg


def _segment_degenerate_check(param: tuple[tuple[int, int], str], calls: list[Call]) -> None:
    (H, W), fill = param
    for args, _, want in calls:
        cfg = args[-1]
        if fill == "none" or cfg.min_pixels > H * W:
            assert (want == -1).all()
        elif cfg.min_pixels == 1:
            assert (want >= 0).all()


def _segment_full_mask_inputs(_: None) -> Iterator[Args]:
    """Every pixel of a 64 x 1024 scene in the mask (the ground too: one large component)."""
    xyz, rng, valid, row_step, col_step = segment_scene(5, 64, 1024)
    for cfg in SEGMENT_CONFIGS[:4]:
        yield xyz, rng, np.ones_like(valid), row_step, col_step, cfg


def _some_segment(_: None, calls: list[Call]) -> None:
    assert all(want.max() >= 1 for _, _, want in calls)


def _segment_other_dtype_inputs(_: None) -> Iterator[Args]:
    """An integer mask and float16 ranges are not the kernel's: the reference answers."""
    xyz, rng, valid, row_step, col_step = segment_scene(6, 16, 64)
    mask = non_ground(xyz, valid, 6)
    for m, r in [(mask.astype(np.uint8), rng), (mask, rng.astype(np.float16))]:
        yield xyz, r, m, row_step, col_step, SegmentConfig(min_pixels=1)


# The dtypes of the reference's arithmetic, at the boundaries where they decide: numpy forms
# ``r * step`` and ``max(join_m, .)`` in float32 for float32 ranges and Python float steps, in
# float64 for numpy float64 steps, and the range-step prefilter in the range's dtype; links
# whose distance falls between the float32 and the float64 limit tell them apart (random
# scenes almost never hold one).

ONLY_LINKS = SegmentConfig(min_pixels=1, near_pixels=0)
LINKS = {  # (di, dj, H, W): the second pixel of the link, the image that holds it
    "next": (0, 1, 1, 8),
    "next_but_one": (0, 2, 1, 8),
    "row_below": (1, 0, 2, 4),
    "across_an_empty_row": (2, 0, 3, 4),
}


def _link_image(di: int, dj: int, H: int, W: int, d: float, r: float):
    """Two mask pixels (0, 0) and (di, dj) with range ``r`` (float32) whose points lie ``d``
    apart; no other return."""
    xyz = np.zeros((H, W, 3))
    xyz[di, dj, 0] = d
    rng = np.full((H, W), np.nan, dtype=np.float32)
    rng[0, 0] = rng[di, dj] = r
    mask = np.isfinite(rng)
    return xyz, rng, mask


def _joined(labels: np.ndarray, mask: np.ndarray) -> bool:
    """The mask pixels (all grouped: min_pixels 1) are one segment."""
    assert (labels[mask] >= 0).all() and (labels[~mask] == -1).all()
    return np.unique(labels[mask]).size == 1


def _link_limits(link: str) -> tuple[np.float32, float, float]:
    """A range at which the float32 and float64 products of the link's limit differ, and the
    two limits."""
    di, dj, _, _ = LINKS[link]
    row_step, col_step = math.radians(1.0), 2 * math.pi / 1024
    cfg = ONLY_LINKS
    base = dj * col_step * cfg.join_per_rad if di == 0 else di * row_step * cfg.join_per_rad_row
    for r in np.float32(60.0) + np.arange(100, dtype=np.float32) * np.float32(0.01):
        lim32 = float(np.float32(r) * np.float32(base))
        lim64 = float(np.float64(r) * base)
        if lim32 != lim64:
            return r, lim32, lim64
    pytest.fail("no range with differing products")


def _distance_limit_inputs(link: str) -> Iterator[Args]:
    """A link halfway between its float32 and float64 limit, with Python float steps, then
    numpy float64 steps."""
    r, lim32, lim64 = _link_limits(link)
    yield from _both_step_types(link, 0.5 * (lim32 + lim64), r)


def _both_step_types(link: str, d: float, r: float) -> Iterator[Args]:
    """The link image at distance ``d`` (range ``r``), with Python float and numpy float64
    angular steps."""
    di, dj, H, W = LINKS[link]
    for step_type in (float, np.float64):
        xyz, rng, mask = _link_image(di, dj, H, W, d, r)
        yield (
            xyz,
            rng,
            mask,
            step_type(math.radians(1.0)),
            step_type(2 * math.pi / 1024),
            ONLY_LINKS,
        )


def _distance_limit_check(link: str, calls: list[Call]) -> None:
    """float32 limit for Python float steps, float64 for numpy ones: opposite answers."""
    _, lim32, lim64 = _link_limits(link)
    (args_f, got_f, _), (args_64, got_64, _) = calls
    assert _joined(got_f, args_f[2]) == (lim32 > lim64)
    assert _joined(got_64, args_64[2]) == (lim64 > lim32)


def _join_floor_inputs(link: str) -> Iterator[Args]:
    """join_m (0.6) is float32 0.6000000238 against a float32 limit, 0.6 against a float64 one."""
    yield from _both_step_types(link, 0.5 * (0.6 + float(np.float32(0.6))), 2.0)


def _joined_then_not(_: Any, calls: list[Call]) -> None:
    """Joined in the first call's dtype (float32), not in the second's (float64)."""
    assert [_joined(got, args[2]) for args, got, _ in calls] == [True, False]


def _range_step_inputs(_: None) -> Iterator[Args]:
    """A step just over the float64 threshold (so the float64 rule cuts it) but not over the
    float32 one: with float32 ranges the prefilter keeps the link, with float64 it is cut."""
    cfg = ONLY_LINKS
    ra = np.linspace(0.01, 0.05, 200_001).astype(np.float32)
    thr32 = cfg.step_m + cfg.step_frac * ra  # the reference's expression on float32 ranges
    thr64 = cfg.step_m + cfg.step_frac * ra.astype(np.float64)
    rb = (ra + thr64).astype(np.float32)
    hit = (np.abs(rb - ra) <= thr32) & (rb.astype(np.float64) - ra.astype(np.float64) > thr64)
    assert hit.any()
    k = int(np.flatnonzero(hit)[0])
    # p, a | b, q along a row: flat on both sides of the step, the link a - b 0.1 m long
    rng = np.array([[ra[k], ra[k], rb[k], rb[k], np.nan, np.nan]], dtype=np.float32)
    xyz = np.zeros((1, 6, 3))
    xyz[0, 2, 0] = 0.1
    mask = np.array([[False, True, True, False, False, False]])
    for dtype in (np.float32, np.float64):
        yield xyz, rng.astype(dtype), mask, math.radians(1.0), 2 * math.pi / 6, cfg


# --- maps.pyramid: the compiled climb of an unmasked search ----------------------------------


def _register(ref: np.ndarray, mov: np.ndarray, kwargs: dict[str, Any]) -> Match:
    return register(ref, mov, **kwargs)


def _register_reference(ref: np.ndarray, mov: np.ndarray, kwargs: dict[str, Any]) -> Match:
    return register_reference(ref, mov, **kwargs)


def _same_match(got: Any, want: Any, args: Args) -> None:
    """The same peak, surface and confidence to float32 rounding, the same levels."""
    np.testing.assert_allclose(got.shift_rc, want.shift_rc, atol=1e-4)
    np.testing.assert_allclose(got.surface, want.surface, atol=2e-5)
    assert abs(got.peak - want.peak) < 2e-5
    assert abs(got.confidence - want.confidence) < 1e-4
    assert got.levels_used == want.levels_used
    # the compiled climb sums only the offsets it visits
    assert (
        0 < got.multiply_adds <= want.multiply_adds or got.multiply_adds == want.multiply_adds == 0
    )


def _texture_match_inputs(param: tuple[int, tuple[int, int]]) -> Iterator[Args]:
    seed, shift = param
    ref, mov = crops(texture((320, 320), seed), shift, (256, 256))
    yield ref, mov, {"max_shift_px": 16}
    yield ref, mov, {}  # no limit: each level climbs as far as it must


def _limit_match_inputs(kwargs: dict[str, Any]) -> Iterator[Args]:
    ref, mov = crops(texture((320, 320), 7), (9, -13), (256, 256))
    yield ref, mov, kwargs


def _unequal_match_inputs(_: None) -> Iterator[Args]:
    """Images of unequal shapes, then small ones."""
    base = texture((300, 300), 11)
    yield base[20:276, 30:250], base[15:215, 33:233], {}
    small_ref, small_mov = crops(texture((64, 64), 12, blur=1.0), (1, -2), (24, 24), pad=8)
    yield small_ref, small_mov, {}


def _flat_match_inputs(_: None) -> Iterator[Args]:
    flat = np.full((64, 64), 3.0, np.float32)
    yield flat, flat, {}


def _no_confidence(_: None, calls: list[Call]) -> None:
    assert calls[-1][1].confidence == 0.0


def _edge_match_inputs(_: None) -> Iterator[Args]:
    """Stripes along the rows, moved 2.5 px across them."""
    _, c = np.mgrid[0:256, 0:256].astype(np.float64)
    stripes = np.sin(c / 7.0) + 0.5 * np.sin(c / 3.1)
    moved = np.sin((c - 2.5) / 7.0) + 0.5 * np.sin((c - 2.5) / 3.1)
    yield stripes, moved, {}


def _edge_match_compare(got: Any, want: Any, args: Args) -> None:
    """Along the rows every offset correlates alike up to rounding: where the climb stops
    there is arbitrary (and the confidence 0); across them both find the shift."""
    assert abs(got.shift_rc[1] - want.shift_rc[1]) < 1e-3
    assert abs(got.shift_rc[1] - 2.5) < 0.1
    assert got.confidence == want.confidence == 0.0


def _real_frame_inputs(_: None) -> Iterator[Args]:
    """A KITTI frame and the same frame moved by (9, -13): ``moving = ref + (9, -13)``."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real recordings not found at {REAL_DATA} (set WM_REAL_DATA to their folder)")
    img = cv2.imread(str(REAL_DATA / "kitti-flow" / "frame1.png"), cv2.IMREAD_GRAYSCALE)
    ref = img[60:316, 400:656].astype(np.float32)
    mov = img[51:307, 413:669].astype(np.float32)
    yield ref, mov, {"max_shift_px": 16}


def _real_frame_check(_: None, calls: list[Call]) -> None:
    assert np.abs(calls[-1][1].shift_rc - (9, -13)).max() < 0.05


def _product(*axes: list[Any]) -> list[tuple[Any, ...]]:
    """Every combination, the first axis varying slowest (as stacked parametrize marks)."""
    return list(itertools.product(*axes))


CASES = [
    Case("column_walk", GROUND_SCENES, _walk_inputs, column_walk, column_walk_reference,
         _equal, _walk_check),
    Case("refine", GROUND_SCENES, _refine_inputs, refine, refine_reference, _equal),
    Case("refine_given_ranges", GROUND_SCENES, _refine_given_ranges_inputs,
         lambda x, y, z, v, g, r: refine(x, y, z, v, g, GroundConfig(), r_m=r),
         lambda x, y, z, v, g, r: refine(x, y, z, v, g, GroundConfig()), _equal),
    Case("column_walk_degenerate", [None], _degenerate_walk_inputs, column_walk,
         column_walk_reference, _equal,
         marks=[pytest.mark.filterwarnings("ignore:invalid value encountered")]),
    Case("refine_degenerate", [None], _degenerate_refine_inputs, refine, refine_reference,
         _equal, marks=[pytest.mark.filterwarnings("ignore:invalid value encountered")]),
    Case("ground_below", [(0, 0.5), (1, 0.05), (2, 1.0), (3, 0.0)], _ground_below_inputs,
         ground_below, ground_below_reference, _equal, _ground_below_check),
    Case("ground_below_degenerate", [None], _ground_below_degenerate_inputs, ground_below,
         ground_below_reference, _equal),
    Case("ground_plane", _product(range(3), [0.0005, 0.3, 1.0]), _ground_plane_inputs,
         ground_plane, ground_plane_reference, _ground_plane_compare),
    Case("psd_mask", [(0, 0), (1, 1), (3, 2), (500, 3), (20_000, 4)], _psd_inputs, psd_mask,
         psd_mask_reference, _equal, _psd_check,
         marks=[pytest.mark.filterwarnings("ignore::RuntimeWarning")]),  # reference: inf, 1e150
    Case("sweep_points", _product([False, True], [0.0, 0.4, 1.0], range(4)),
         _sweep_points_inputs, sweep_points, sweep_points_reference, _sweep_points_compare,
         _sweep_points_check),
    Case("deskew_to_world", _product([np.float32, np.float64], ["firing", "shuffled"], range(3)),
         _deskew_inputs, deskew_to_world, deskew_to_world_reference, _deskew_compare,
         _deskew_check),
    Case("first_per_voxel", _product([0.05, 0.5, 3.0], range(3)), _voxel_inputs,
         first_per_voxel, first_per_voxel_reference, _equal, _voxel_check),
    Case("segment_attributes",
         _product(range(3), [(16, 64), (64, 1024)], [0, 1, 60], [False, True]),
         _attribute_inputs, segment_attributes, segment_attributes_reference, _same_attributes,
         _attribute_check),
    Case("segment_attributes_more_segments", [None], _more_segments_inputs, segment_attributes,
         segment_attributes_reference, _same_attributes, _more_segments_check),
    Case("segment_attributes_dtypes_strides", [None], _attribute_dtype_inputs,
         segment_attributes, segment_attributes_reference, _same_attributes,
         _attribute_dtype_check),
    Case("segment_attributes_simulated", [None], _pipeline_attribute_inputs, segment_attributes,
         segment_attributes_reference, _same_attributes, _pipeline_attribute_check),
    Case("to_egosphere", _product(range(3), [1_000, 20_000, 70_000], [True, False], [1, 2, 3]),
         _egosphere_inputs, to_egosphere, to_egosphere_reference, _same_image, _egosphere_check,
         marks=[EGOSPHERE_CAST]),
    Case("to_egosphere_grids", _product(range(2), list(EGOSPHERE_GRIDS)), _egosphere_grid_inputs,
         to_egosphere, to_egosphere_reference, _same_image, _every_image_has_returns,
         marks=[EGOSPHERE_CAST]),
    Case("to_egosphere_min_range", [None], _min_range_inputs, to_egosphere,
         to_egosphere_reference, _same_image, _min_range_check, marks=[EGOSPHERE_CAST]),
    Case("to_egosphere_ties", [1, 2, 3], _tie_inputs, to_egosphere, to_egosphere_reference,
         _same_image, _tie_check, marks=[EGOSPHERE_CAST]),
    Case("to_egosphere_empty", _product([True, False], [1, 2, 3]), _empty_scan_inputs,
         to_egosphere, to_egosphere_reference, _same_image, _empty_scan_check,
         marks=[EGOSPHERE_CAST]),
    Case("to_egosphere_ring_dtypes", [np.int64, np.int32, np.uint8, np.float32],
         _ring_dtype_inputs, to_egosphere, to_egosphere_reference, _same_image,
         _every_image_has_returns, marks=[EGOSPHERE_CAST]),
    Case("to_egosphere_strided", [None], _strided_scan_inputs, to_egosphere,
         to_egosphere_reference, _same_image, _every_image_has_returns, marks=[EGOSPHERE_CAST]),
    Case("label_objects",
         _product([(16, 64), (16, 1024), (64, 64), (64, 1024)], [0, 1, 2], SEGMENT_DTYPES),
         _segment_inputs, label_objects, _label_objects_reference, _same_labels, _segment_check),
    Case("label_objects_any_mask", [3, 4], _segment_any_mask_inputs, label_objects,
         _label_objects_reference, _same_labels),
    Case("label_objects_simulated", [None], _segment_simulated_inputs, label_objects,
         _label_objects_reference, _same_labels, _segment_simulated_check),
    Case("label_objects_degenerate",
         _product([(1, 1), (1, 2), (2, 1), (3, 2), (16, 64)], ["none", "all", "all_no_range"]),
         _segment_degenerate_inputs, label_objects, _label_objects_reference, _same_labels,
         _segment_degenerate_check),
    Case("label_objects_full_mask", [None], _segment_full_mask_inputs, label_objects,
         _label_objects_reference, _same_labels, _some_segment),
    Case("label_objects_other_dtypes", [None], _segment_other_dtype_inputs, label_objects,
         _label_objects_reference, _same_labels, _some_segment),
    Case("label_objects_distance_limit", sorted(LINKS), _distance_limit_inputs, label_objects,
         _label_objects_reference, _same_labels, _distance_limit_check),
    Case("label_objects_join_floor", sorted(LINKS), _join_floor_inputs, label_objects,
         _label_objects_reference, _same_labels, _joined_then_not),
    Case("label_objects_range_step", [None], _range_step_inputs, label_objects,
         _label_objects_reference, _same_labels, _joined_then_not),
    Case("register_textures", _product(range(4), [(0, 0), (9, -13), (-3, 5), (14, 15)]),
         _texture_match_inputs, _register, _register_reference, _same_match),
    Case("register_limits_and_starts",
         [{"max_shift_px": 4},  # the true shift lies beyond: pinned at the limit
          {"levels": 1, "initial_shift_rc": (8.0, -12.0)},  # one level, started near the peak
          {"levels": 1},  # one level from zero: a long climb with fresh windows on the way
          {"levels": 2, "max_shift_px": 30}],
         _limit_match_inputs, _register, _register_reference, _same_match),
    Case("register_unequal_and_small", [None], _unequal_match_inputs, _register,
         _register_reference, _same_match),
    Case("register_flat", [None], _flat_match_inputs, _register, _register_reference,
         _same_match, _no_confidence),
    Case("register_edge", [None], _edge_match_inputs, _register, _register_reference,
         _edge_match_compare),
    Case("register_real_frames", [None], _real_frame_inputs, _register, _register_reference,
         _same_match, _real_frame_check),
]  # fmt: skip


def _param_id(param: Any) -> str:
    """A readable test id: tuples joined by "-", dicts as key=value, types by name."""
    if param is None:
        return "-"
    if isinstance(param, tuple):
        return "-".join(_param_id(p) for p in param)
    if isinstance(param, dict):
        return ",".join(f"{k}={v}" for k, v in param.items())
    return getattr(param, "__name__", str(param))


@pytest.mark.parametrize(
    ("case", "param"),
    [
        pytest.param(case, param, id=f"{case.name}[{_param_id(param)}]", marks=case.marks)
        for case in CASES
        for param in case.params
    ],
)
def test_kernel_equals_reference(case: Case, param: Any) -> None:
    calls: list[Call] = []
    for args in case.inputs(param):
        got, want = case.kernel(*args), case.reference(*args)
        case.compare(got, want, args)
        calls.append((args, got, want))
    assert calls, f"{case.name}: no inputs"
    if case.check is not None:
        case.check(param, calls)
