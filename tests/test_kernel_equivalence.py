"""Compiled kernels against their numpy oracles: one parametrised harness.

Each :class:`Case` names a kernel, the inputs it is called on (a generator of argument
tuples, seeded per parameter), the kernel call, the reference call (the oracles in
``tests/kernel_reference``, or a plain definition beside its case) and the comparison:
``np.testing.assert_array_equal`` where the kernel is the reference bit for bit, a tolerance
where it is the reference to rounding. A
case's ``check`` holds the assertions about what the inputs exercised (both answers occur,
something was found), given every call's results. Argument checks of the kernels, and inputs
a reference cannot take, are in test_kernel_arguments.py; tests of their behaviour beyond the
reference are in the modules' own test files.
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
from kernel_reference.ground_prior_reference import (
    above_prior_reference,
    on_known_ground_reference,
)
from kernel_reference.ground_reference import (
    column_walk_reference,
    ground_mask_reference,
    refine_reference,
)
from kernel_reference.level3_surfaces_reference import foot_rise_deg_reference
from kernel_reference.lists_reference import list_slots_reference, list_sums_reference
from kernel_reference.poses_reference import deskew_to_world_reference
from kernel_reference.pyramid_reference import register_reference
from kernel_reference.sweep_points_reference import sweep_points_reference
from kernel_reference.voxels_reference import first_per_voxel_reference
from kernel_reference.windowing_reference import window_mask_reference
from kernel_scenes import (
    ListSweep,
    attribute_scene,
    box_t,
    crops,
    ground_rays,
    ground_sweep,
    list_sweep,
    non_ground,
    plane_t,
    random_scan,
    scan_of,
    segment_scene,
    small_list_sweep,
    texture,
)

from core.geometry import interpolate_pose, rotvec_to_matrix, se3, transform_points
from kd_store.covariance import pack_covariance, psd_mask
from logs.types import LadarScan
from maps.fusion import FusionConfig, cast_rays, fuse_points
from maps.level import LevelConfig, MapLevel
from maps.pyramid import TABLE_MAX_PX, Match, _window_sums, register
from maps.stack import MapStack, StackConfig
from sp.computation import SegmentAttributes, ground_below, ground_plane, segment_attributes
from sp.egosphere import EgosphereConfig, to_egosphere
from sp.ground import (
    GroundConfig,
    _height_from_lowest,
    _median_height,
    _prepare_kernel,
    column_walk,
    estimate_sensor_height,
    ground_mask,
    refine,
)
from sp.ground_prior import (
    ABOVE,
    OBJECT,
    GroundPrior,
    GroundPriorConfig,
    above_prior,
    on_known_ground,
)
from sp.level3_surfaces import foot_rise_deg
from sp.lists import (
    brightness_edges,
    list_slots,
    list_slots_and_sums,
    list_sums,
    range_jump_edges,
    range_jump_edges_reference,
)
from sp.segments import SegmentConfig, label_objects, label_objects_reference, range_edges
from sp.sweep_points import sweep_points
from sp.voxels import first_per_voxel
from sp.windowing import WindowConfig, window_mask
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


def _product(*axes: list[Any]) -> list[tuple[Any, ...]]:
    """Every combination, the first axis varying slowest (as stacked parametrize marks)."""
    return list(itertools.product(*axes))


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
    x, y, z, valid = _ground_scene(seed, p_invalid=p_invalid)
    yield from _with_grounds(seed, x, y, z, valid)


def _with_grounds(
    seed: int, x: np.ndarray, y: np.ndarray, z: np.ndarray, valid: np.ndarray
) -> Iterator[tuple[np.ndarray, ...]]:
    """x, y, z, valid, ground, r of one scene under four ground masks: the walk's (last
    height), a random one, none and every valid pixel."""
    r = np.hypot(x, y)
    walk = column_walk(r, z, valid, WALK_HEIGHTS_M[-1], GroundConfig())
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


# --- sp.ground_prior: far ground against the map's (the same pixels) ----------------------


def _prior_inputs(param: tuple[int, float]) -> Iterator[Args]:
    """A toroidal height grid, 40 % unknown, and far and near returns over and beyond its
    window (its edges, where the pruning's square wraps, included)."""
    seed, res = param
    rng = np.random.default_rng(seed)
    n, origin = 40, (int(rng.integers(-60, 60)), int(rng.integers(-60, 60)))
    z = rng.normal(0.0, 0.6, (n, n)).astype(np.float32)
    z[rng.random((n, n)) < 0.4] = np.nan
    prior = GroundPrior(z, origin, res)
    xyz = np.zeros((50, 60, 3))
    for a in range(2):
        xyz[..., a] = (origin[a] + rng.uniform(-6, n + 6, (50, 60))) * res
    xyz[..., 2] = rng.normal(0.5, 1.0, (50, 60))
    range_m = rng.uniform(0.0, 40.0, (50, 60)).astype(np.float32)
    ground = rng.random((50, 60)) < 0.8
    yield xyz, range_m, ground, prior, GroundPriorConfig()


def _prior_check(param: tuple[int, float], calls: list[Call]) -> None:
    for args, got, _ in calls:
        # objects flagged, some high enough to stand as objects, most ground kept
        assert 20 < int((got == OBJECT).sum()) < int((got != 0).sum()) < int(args[2].sum())
        assert (got == ABOVE).sum() > 20


def _known_check(param: tuple[int, float], calls: list[Call]) -> None:
    for args, got, _ in calls:
        # some returns on the known ground; fewer than lie within on_ground_m of their cell,
        # the cells standing above their neighbourhood refused
        xyz, rng, valid, prior, cfg = args
        n = prior.z_m.shape[0]
        c = np.floor(xyz[..., :2] / prior.resolution_m).astype(np.int64)
        z = prior.z_m[c[..., 1] % n, c[..., 0] % n]
        with np.errstate(invalid="ignore"):
            near = np.abs(xyz[..., 2] - z) <= cfg.on_ground_m
        close = valid & (rng >= cfg.on_ground_min_range_m) & near
        assert 3 < int(got.sum()) < int(close.sum())


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
def _pipeline_calls() -> dict[str, list[Args]]:
    """The arguments of every segment_attributes call (before and after the merge of
    collinear pieces) and every foot_rise_deg call of the pipeline on a few simulated
    sweeps."""
    import kd_store
    import sp.level4_objects
    from fixtures.simulate import simulate
    from logs.types import GroundTruthPose, TransformFrame
    from wm.entities import KDSensoryProcessor

    calls: dict[str, list[Args]] = {"segment_attributes": [], "foot_rise_deg": []}

    def recording(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def record(*args: Any, **kwargs: Any) -> Any:
            assert not kwargs  # the harness passes arguments by position
            calls[name].append(args)
            return fn(*args)

        return record

    mp = pytest.MonkeyPatch()
    for name in calls:
        mp.setattr(sp.level4_objects, name, recording(name, getattr(sp.level4_objects, name)))
    try:
        proc = KDSensoryProcessor(kd_store.open(":memory:"))
        T_body_ladar = T_world_body = None
        for f in simulate("village", seconds=0.35):
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
    yield from _pipeline_calls()["segment_attributes"]


def _pipeline_attribute_check(_: None, calls: list[Call]) -> None:
    assert len(calls) >= 3
    for _, _, want in calls:
        assert len(want) >= 5 and (want.n_pixels > 0).all()


# --- sp.level3_surfaces: the walks up the columns from the feet of segments ------------------


def _foot_inputs(param: tuple[int, int]) -> Iterator[Args]:
    """A ray-cast sweep, its ground (``ground_mask``) and its other returns cut into blocks of
    ``cols`` columns (and of 5 rows when ``rows_cut``: walks that leave their segment), some
    returns dropped (walks across gaps); each walk limit on and off."""
    seed, cols = param
    xyz, valid = ground_sweep(seed, fill="zero")
    ground, _ = ground_mask(xyz, valid, GroundConfig())
    i, j = np.indices(valid.shape)
    for rows_cut in (False, True):
        labels = np.where(valid & ~ground, j // cols + (i // 5) * 1024 * rows_cut, -1)
        labels = np.unique(labels, return_inverse=True)[1].reshape(labels.shape) - 1
        K = int(labels.max()) + 1
        for gap, chord_m, rise_m, max_rows in [
            (2, 0.25, 0.4, 8), (0, 0.25, 0.4, 8), (2, 2.0, 0.1, 8), (2, 0.25, 0.4, 1),
            (2, 0.25, 0.4, 0), (5, 1.0, 1.5, 8),
        ]:  # fmt: skip
            yield labels, xyz, valid, ground, K, gap, chord_m, rise_m, max_rows


def _foot_check(_: Any, calls: list[Call]) -> None:
    """Segments with and without counting columns, and limits that change the answer."""
    counts = [want[1].sum() for _, _, want in calls]
    assert max(counts) > 50 and min(counts) == 0  # max_rows 0 counts nothing
    assert len(set(counts)) > 3


def _foot_pipeline_inputs(_: None) -> Iterator[Args]:
    yield from _pipeline_calls()["foot_rise_deg"]


def _foot_pipeline_check(_: None, calls: list[Call]) -> None:
    assert len(calls) >= 3 and sum(want[1].sum() for _, _, want in calls) > 20


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


# --- sp.ground: the ground mask and its sensor height on ray-cast sweeps ----------------------

# the numpy references cast NaN ranges, azimuths and window sizes of empty pixels or
# degenerate windows to int64 (values they then never use); numpy's median of inf and -inf
# is NaN
REFERENCE_CAST = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")


def _same_ground(got: Any, want: Any, args: Args) -> None:
    """The same mask and the same sensor height (bit for bit, not approximately); no ground
    where there is no return."""
    (mask, h), (want_mask, want_h) = got, want
    valid = args[1]
    assert mask.dtype == np.bool_ and mask.shape == valid.shape
    np.testing.assert_array_equal(mask, want_mask)
    assert h == want_h
    assert not (mask & ~valid).any()


def _ground_sweep_inputs(param: tuple[int, str]) -> Iterator[Args]:
    seed, fill = param
    yield *ground_sweep(seed, fill=fill), GroundConfig()


def _mostly_ground(_: Any, calls: list[Call]) -> None:
    """A real scene: most of the valid returns are ground, the boxes and vegetation are not."""
    (_, valid, _), (mask, _), _ = calls[-1]
    n = np.count_nonzero(valid)
    assert 0.3 * n < np.count_nonzero(mask) < n


def _tied_range_inputs(seed: int) -> Iterator[Args]:
    """Coordinates on a 5 cm grid: the faces of the boxes give runs of equal ranges in a
    column (the walk's ``dr > 0`` and gap tests at their edges)."""
    xyz, valid = ground_sweep(seed, quantum_m=0.05)
    yield xyz, valid, GroundConfig()
    yield xyz, valid, GroundConfig(step_m=0.0, resume_gap_m=0.0, cell_m=0.05)


def _ties_there_are(_: int, calls: list[Call]) -> None:
    xyz, valid, _ = calls[0][0]
    x, y = xyz[..., 0][valid], xyz[..., 1][valid]
    assert np.unique(np.hypot(x, y)).size < 0.9 * x.size


def _cell_boundary_scene(param: tuple[float, int]):
    """Returns right on ring and sector boundaries (ranges ``k * cell_m``, azimuths
    ``-pi + s * 2 pi / n_sectors``, and their neighbouring floats), where the cell of a
    return rests on the last bit of the division and of numpy's arctan2: x, y, z, valid
    (H, W), two ground masks and the configuration."""
    cfg = GroundConfig(cell_m=param[0], n_sectors=param[1])
    rng = np.random.default_rng(int(cfg.cell_m * 10) + cfg.n_sectors)
    H, W = 48, 512
    k = rng.integers(1, 40, (H, W))
    s = rng.integers(0, cfg.n_sectors + 1, (H, W))
    r = k * cfg.cell_m
    az = -np.pi + s * (2 * np.pi / cfg.n_sectors)
    nudge = rng.integers(-1, 2, (H, W))  # the float below, the boundary, the float above
    r = np.where(nudge < 0, np.nextafter(r, 0), np.where(nudge > 0, np.nextafter(r, 1e9), r))
    x, y = r * np.cos(az), r * np.sin(az)
    z = rng.uniform(-1.9, -1.3, (H, W))
    valid = rng.random((H, W)) < 0.9
    grounds = [rng.random((H, W)) < 0.5, rng.random((H, W)) < 0.1]
    return x, y, z, valid, grounds, cfg


CELL_BOUNDARY_GRIDS = [(GroundConfig().cell_m, GroundConfig().n_sectors), (0.3, 7), (1.1, 360)]


def _cell_boundary_refine_inputs(param: tuple[float, int]) -> Iterator[Args]:
    x, y, z, valid, grounds, cfg = _cell_boundary_scene(param)
    for ground in grounds:
        yield x, y, z, valid, ground, cfg


def _some_but_not_all_valid_ground(_: Any, calls: list[Call]) -> None:
    for args, got, _ in calls:
        assert got.any() and not got[args[3]].all()


def _cell_boundary_mask_inputs(param: tuple[float, int]) -> Iterator[Args]:
    x, y, z, valid, _, cfg = _cell_boundary_scene(param)
    yield np.stack([x, y, z], axis=-1), valid, cfg


# (x, y) m of returns whose sector of the default grid (180) is one by numpy's float64
# arctan2 on AVX-512 (its SIMD routine) and the next one by libm's atan2 (what a compiled
# math.atan2 calls): within a few ulps of a sector boundary, found by search on such a CPU
ATAN2_SPLIT_XY = [
    (-43.626014971585, -10.877187184872),
    (42.646391332732, 30.984416969189),
    (-31.071585857064, 30.005481677621),
    (-13.682519858391, 21.896608973673),
    (-47.149043440653, 20.992106624637),
    (-45.774893693434, 35.763266497553),
    (-27.513987166547, -23.086976483666),
    (-16.697015343033, 31.402518647936),
    (-36.43447481801, -40.464583704111),
    (-38.8986109044, 11.153997189264),
    (-16.150393130108, -7.190618300534),
    (-20.613720730879, -42.264390803764),
]


def _atan2_split_scene(xy: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A return a few ulps from a sector boundary, and a much lower ground return in the
    sector across that boundary: in its own sector (numpy's) the return is its cell's lowest
    ground and stays ground; put across (another atan2's last bit) it is 0.75 m above that
    cell's lowest and is not. On any CPU the mask is the reference's. xyz (1, 2, 3), valid."""
    cfg = GroundConfig()
    x, y = xy
    a = float(np.arctan2(y, x))
    t = (a + np.pi) * (cfg.n_sectors / (2 * np.pi))
    s_other = int(t) - 1 if t - int(t) < 0.5 else int(t) + 1
    az_other = -np.pi + (s_other + 0.5) * (2 * np.pi / cfg.n_sectors)
    r = float(np.hypot(x, y))
    xyz = np.array([[[x, y, -1.75], [r * np.cos(az_other), r * np.sin(az_other), -2.5]]])
    return xyz, np.ones((1, 2), dtype=bool)


def _atan2_split_mask_inputs(xy: tuple[float, float]) -> Iterator[Args]:
    yield *_atan2_split_scene(xy), GroundConfig()


def _all_ground(_: Any, calls: list[Call]) -> None:
    assert calls[-1][1][0].all()


def _atan2_split_refine_inputs(xy: tuple[float, float]) -> Iterator[Args]:
    xyz, valid = _atan2_split_scene(xy)
    yield xyz[..., 0], xyz[..., 1], xyz[..., 2], valid, valid, GroundConfig()


def _both_stay_ground(_: Any, calls: list[Call]) -> None:
    np.testing.assert_array_equal(calls[-1][1], [[True, True]])


def _clipped_height_inputs(height: float) -> Iterator[Args]:
    """A sensor far below or above the prior: the height clips to the search range."""
    yield *ground_sweep(11, height=height), GroundConfig()


def _clipped_height_check(_: float, calls: list[Call]) -> None:
    (xyz, valid, cfg), (_, h), _ = calls[-1]
    assert h == estimate_sensor_height(np.where(valid, xyz[..., 2], 0.0), valid, cfg)
    assert cfg.sensor_height_m - cfg.height_search_m <= h <= cfg.sensor_height_m + 1.0


def _ground_config_inputs(changes: dict[str, Any]) -> Iterator[Args]:
    yield *ground_sweep(21, h=32, w=512), GroundConfig(**changes)


def _some_ground(_: Any, calls: list[Call]) -> None:
    assert calls[-1][1][0].any()


def _ground_dtype_inputs(_: None) -> Iterator[Args]:
    """float32 points; then an (H, W, 3) view of a bigger array (not C-contiguous), with
    valid as a Fortran-ordered array."""
    xyz, valid = ground_sweep(5, h=32, w=256, fill="zero")
    yield xyz.astype(np.float32), valid
    big = np.zeros((32, 256, 5))
    big[..., 1:4] = xyz
    yield big[..., 1:4], np.asfortranarray(valid)


def _ground_mask_of_copies(xyz: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, float]:
    """The reference on C-contiguous copies of the arguments."""
    return ground_mask_reference(np.ascontiguousarray(xyz), np.ascontiguousarray(valid))


def _strided_check(_: None, calls: list[Call]) -> None:
    assert not calls[1][0][0].flags.c_contiguous


SMALL_GROUND_SHAPES = [(1, 1), (1, 7), (9, 1), (3, 5), (16, 64)]


def _small_ground_inputs(param: tuple[tuple[int, int], float]) -> Iterator[Args]:
    """Valid pixels at random, with ray-cast or made-up points (a valid pixel needs a
    value), NaN where invalid; the default and a one-sector grid."""
    shape, p_valid = param
    rng = np.random.default_rng(shape[0] * 100 + shape[1])
    xyz, _ = ground_sweep(3, h=shape[0], w=shape[1], fill="zero")
    xyz = np.where(np.isfinite(xyz), xyz, rng.normal(0, 5, xyz.shape))
    valid = rng.random(shape) < p_valid
    xyz[~valid] = np.nan
    for cfg in (GroundConfig(), GroundConfig(n_sectors=1, cell_m=0.5)):
        yield xyz, valid, cfg


def _no_returns_no_ground(param: tuple[tuple[int, int], float], calls: list[Call]) -> None:
    if param[1] == 0.0:
        for (_, _, cfg), (mask, h), _ in calls:
            assert not mask.any() and h == cfg.sensor_height_m


def _all_invalid_and_all_valid_inputs(_: None) -> Iterator[Args]:
    """No valid pixel; then every pixel a return: a flat floor all round (a garage)."""
    xyz, valid = ground_sweep(9)
    yield np.full_like(xyz, np.nan), np.zeros_like(valid), GroundConfig()
    d = ground_rays(64, 1024, np.random.default_rng(9))
    t = np.minimum(plane_t(d, 1.8, 0.0, 0.0), box_t(d, np.full(3, -30.0), np.full(3, 30.0)))
    yield t[..., None] * d, np.ones(valid.shape, dtype=bool), GroundConfig()


def _all_invalid_and_all_valid_check(_: None, calls: list[Call]) -> None:
    (_, (none, h), _), ((xyz_all, _, _), (garage, _), _) = calls
    assert not none.any() and h == GroundConfig().sensor_height_m
    assert np.isfinite(xyz_all).all()
    assert garage[-10:].all()  # the floor under the sensor
    assert not garage[:5].any()  # the ceiling


def _prepare_reference(xyz: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, ...]:
    """numpy's valid coordinates, ranges (hypot) and each column's lowest return."""
    lowest = valid.shape[0] - 1 - np.argmax(valid[::-1], axis=0)
    cols = np.flatnonzero(valid.any(axis=0))
    coords = tuple(xyz[..., k][valid] for k in range(3))
    r = np.hypot(xyz[..., 0], xyz[..., 1])[valid]
    return (*coords, r, xyz[lowest[cols], cols, 2])


def _same_arrays(got: Any, want: Any, args: Args) -> None:
    assert len(got) == len(want)
    for k, (g, w) in enumerate(zip(got, want, strict=True)):
        np.testing.assert_array_equal(g, w, err_msg=f"item {k}")


def _prepare_inputs(seed: int) -> Iterator[Args]:
    yield ground_sweep(seed)


def _prepare_check(_: int, calls: list[Call]) -> None:
    (_, valid), (_, _, _, r_v, z_low), _ = calls[-1]
    assert z_low.size == valid.any(axis=0).sum() and r_v.size == valid.sum()


def _awkward_hypot_inputs(_: None) -> Iterator[Args]:
    """Ranges over many magnitudes, signed zeros, subnormals and infinities."""
    rng = np.random.default_rng(0)
    vals = np.concatenate(
        [
            rng.normal(0, 1, 4000) * 10.0 ** rng.uniform(-300, 300, 4000),
            [0.0, -0.0, 5e-324, -5e-324, 1e308, -1e308, np.inf, -np.inf, 3.0, 4.0],
        ]
    )
    xyz = np.stack([vals, rng.permutation(vals), np.zeros_like(vals)], axis=-1)[None]
    yield np.ascontiguousarray(xyz), np.ones(xyz.shape[:2], dtype=bool)


def _median_height_inputs(_: None) -> Iterator[Args]:
    """Odd and even counts, ties, signed zeros (numpy's median of -0.0 is +0.0; its clip
    keeps the value on a tie with a bound), subnormals, infinities, and bounds that cross."""
    rng = np.random.default_rng(0)
    special = [-0.0, 0.0, 1.0, -1.0, 5e-324, -5e-324, 0.5, -2.0, np.inf, -np.inf]
    samples = [np.array(v) for v in ([-0.0], [-0.0, -0.0], [0.0, -0.0], [np.inf, -np.inf])]
    samples += [rng.choice(special, rng.integers(1, 12)) for _ in range(400)]
    samples += [rng.normal(-1.8, 0.3, n) for n in (1, 2, 999, 1000)]
    configs = [
        GroundConfig(sensor_height_m=s, height_search_m=d)
        for s, d in ((1.8, 1.0), (0.0, 0.0), (1.0, 1.0), (-1.0, 1.0), (0.0, -1.0))
    ]
    for z_low in samples:
        for cfg in configs:
            yield z_low, cfg
    yield np.zeros(0), GroundConfig()  # no column with a return: the prior


def _median_height_of(z_low: np.ndarray, cfg: GroundConfig) -> float:
    """The compiled height with ``cfg``'s prior and search bounds."""
    s, d = float(cfg.sensor_height_m), float(cfg.height_search_m)
    return _median_height(z_low, s, s - d, s + d)


def _same_height(got: Any, want: Any, args: Args) -> None:
    """The same float to the bit, the sign of a zero too (NaN where NaN)."""
    if np.isnan(want):
        assert np.isnan(got)
        return
    assert got == want and np.signbit(got) == np.signbit(want), args


def _median_height_check(_: None, calls: list[Call]) -> None:
    assert any(w == 0 and np.signbit(w) for _, _, w in calls)  # a zero's sign both ways
    (z_low, cfg), got, _ = calls[-1]
    assert z_low.size == 0 and got == cfg.sensor_height_m


WALK_SWEEPS = _product(range(3), ["nan", "zero"])


def _walk_sweep_inputs(param: tuple[int, str]) -> Iterator[Args]:
    """The public wrapper of the walk on image-sized arrays, NaN or zero where empty."""
    seed, fill = param
    xyz, valid = ground_sweep(seed, fill=fill)
    r = np.hypot(xyz[..., 0], xyz[..., 1])
    for h in WALK_HEIGHTS_M:
        yield r, xyz[..., 2], valid, h, GroundConfig()


def _column_walk_zero_filled(
    r: np.ndarray, z: np.ndarray, valid: np.ndarray, h: float, cfg: GroundConfig
) -> np.ndarray:
    """The reference on zero-filled arrays (a NaN would carry through its row arithmetic)."""
    return column_walk_reference(np.where(valid, r, 0.0), np.where(valid, z, 0.0), valid, h, cfg)


def _some_ground_walked(_: Any, calls: list[Call]) -> None:
    assert calls[-1][1].any()


def _sweep_grounds(param: tuple[int, str]) -> Iterator[tuple[np.ndarray, ...]]:
    """x, y, z, valid, ground, r: a sweep with the walk's mask (last height), a random mask,
    none and every valid pixel as ground."""
    seed, fill = param
    xyz, valid = ground_sweep(seed, fill=fill)
    yield from _with_grounds(seed, xyz[..., 0], xyz[..., 1], xyz[..., 2], valid)


def _refine_sweep_inputs(param: tuple[int, str]) -> Iterator[Args]:
    for x, y, z, valid, ground, _ in _sweep_grounds(param):
        yield x, y, z, valid, ground, GroundConfig()


def _no_ground_outside_valid(_: Any, calls: list[Call]) -> None:
    for args, got, _ in calls:
        assert not (got & ~args[3]).any()


# --- sp.windowing: the attention mask of the tracks' windows ----------------------------------


def _windows(seed: int, n: int, H: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n window centres (sensor frame, m) around the sensor, sigmas, and the rows' elevations
    (a few rows NaN, as rows without returns)."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(-np.pi, np.pi, n)
    # some right on the azimuth seam, where the window wraps
    az[: n // 5] = rng.choice([-np.pi, np.pi], n // 5) + rng.normal(0, 0.01, n // 5)
    rg = rng.uniform(0.5, 80.0, n)
    c = np.stack([rg * np.cos(az), rg * np.sin(az), rng.uniform(-3.0, 2.0, n)], axis=1)
    sigma = rng.exponential(0.5, n)
    sigma[: n // 7] = 50.0  # clamped to max_half_m; near ones span the whole row
    row_el = np.linspace(0.3, -0.4, H)
    row_el[rng.random(H) < 0.1] = np.nan
    return c, sigma, row_el


def _same_mask(got: Any, want: Any, args: Args) -> None:
    assert got.dtype == np.bool_ and got.shape == args[0]
    np.testing.assert_array_equal(got, want)


def _window_inputs(param: tuple[int, int]) -> Iterator[Args]:
    seed, n = param
    c, sigma, row_el = _windows(seed, n)
    for shape, cfg in (((64, 1024), None), ((64, 360), WindowConfig(1.0, 1.0, 3.0))):
        yield shape, c, sigma, row_el, cfg


def _windows_within_rows(_: Any, calls: list[Call]) -> None:
    for (_, _, _, row_el, _), got, _ in calls:
        assert got.any() and not got.all()
        assert not got[~np.isfinite(row_el)].any()


def _wrap_inputs(_: None) -> Iterator[Args]:
    """A window straddling azimuth pi."""
    yield (64, 1024), np.array([[-20.0, 0.0, -1.8]]), np.array([0.5]), np.linspace(0.3, -0.4, 64)


def _wraps(_: None, calls: list[Call]) -> None:
    """It covers both ends of its rows, not the middle."""
    got = calls[-1][1]
    rows = np.flatnonzero(got.any(axis=1))
    assert rows.size > 0
    assert got[rows, 0].all() and got[rows, -1].all() and not got[rows, 512].any()


def _degenerate_window_inputs(_: None) -> Iterator[Args]:
    """No windows, no rows with returns, windows at the sensor or missing every row, negative
    and NaN sigmas (empty or reversed intervals), one column; then windows of negative width
    (sigma below -base/k): reversed intervals, some starting at column 0 (so ending at -1,
    which both index from the end), still within their rows."""
    row_el = np.linspace(0.3, -0.4, 16)
    rng = np.random.default_rng(3)
    c = rng.normal(0, 10, (40, 3))
    c[0] = 0.0  # at the sensor
    c[1] = [5.0, 0.0, 500.0]  # straight up: above every row
    sigma = rng.normal(0, 2.0, 40)  # some negative: windows narrower than one column
    sigma[2] = np.nan
    yield (16, 90), np.zeros((0, 3)), np.zeros(0), row_el
    yield (16, 90), c, sigma, np.full(16, np.nan)
    yield (16, 90), c, sigma, row_el
    yield (16, 90), c, np.full(40, -1.0), row_el
    yield (16, 1), c, sigma, row_el
    yield (1, 90), c, sigma, row_el[:1]
    row_el64 = np.linspace(0.3, -0.4, 64)
    az = np.pi - (np.arange(0, 1024, 37) + 0.5) * 2 * np.pi / 1024
    az[0] = -np.pi + 1e-9  # the last column: its reversed interval starts at 0, ends at -1
    el = row_el64[np.arange(az.size) % 64]
    c_rev = 10.0 * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    s_rev = np.full(az.size, (-0.08 - 1.0) / 3.0)  # half-width -0.08 m at 10 m: -1.3 columns
    s_rev[1::2] = 0.5
    yield (64, 1024), c_rev, s_rev, row_el64


def _degenerate_window_check(_: None, calls: list[Call]) -> None:
    assert not calls[1][1].any()  # no row has a return
    assert calls[2][1].any()
    assert calls[-1][1].any()  # the reversed intervals


# --- sp.lists: range edges, list slots and sums (level 2) -------------------------------------


def _same_bytes(got: Any, want: Any, args: Args) -> None:
    """Equal dtype, shape and bytes (bit for bit, NaN included)."""
    assert got.dtype == want.dtype and got.shape == want.shape
    assert got.tobytes() == want.tobytes(), f"{np.count_nonzero(got != want)} elements differ"


LIST_SWEEPS = _product(range(5), [np.float32, np.float64])
SMALL_LIST_IMAGES = _product(range(3), [(1, 1), (1, 7), (6, 1), (2, 2), (3, 5), (7, 33)])


def _edge_sweep_inputs(param: tuple[int, type]) -> Iterator[Args]:
    seed, dtype = param
    s = list_sweep(seed)
    rng = s.range_m.astype(dtype)
    for jump_m, frac in ((0.5, 0.05), (0.2, 0.01), (0.0, 0.0), (2.0, 0.2)):
        yield rng, s.valid, jump_m, frac


def _some_edges(_: Any, calls: list[Call]) -> None:
    for _, _, want in calls:
        assert want.any() and not want.all()


def _range_edges_inputs(param: tuple[int, type]) -> Iterator[Args]:
    """``sp.segments.range_edges`` (the pipeline's call) with the default thresholds."""
    seed, dtype = param
    s = list_sweep(seed)
    yield s.range_m.astype(dtype), s.valid, SegmentConfig()


def _range_edges_reference(rng: np.ndarray, valid: np.ndarray, cfg: SegmentConfig) -> np.ndarray:
    return range_jump_edges_reference(rng, valid, cfg.edge_jump_m, cfg.edge_jump_frac)


def _no_edge_outside_valid(_: Any, calls: list[Call]) -> None:
    (_, valid, _), got, _ = calls[-1]
    assert not got[~valid].any()


def _small_edge_inputs(param: tuple[int, tuple[int, int]]) -> Iterator[Args]:
    seed, (H, W) = param
    s = small_list_sweep(seed, H, W)
    for dtype, (jump_m, frac) in itertools.product(
        (np.float32, np.float64),
        # a negative threshold makes pixels jump against themselves at the bottom row and
        # in a one-column image: the reference's pairing of a pixel with itself, kept
        ((0.5, 0.05), (0.0, 0.0), (-1.0, 0.0), (0.1, -0.1)),
    ):
        rng = s.range_m.astype(dtype)
        odd = np.random.default_rng(seed).random((H, W))
        rng[s.valid & (odd < 0.1)] = -3.0
        rng[s.valid & (odd > 0.95)] = -np.inf
        yield rng, s.valid, jump_m, frac


def _degenerate_edge_inputs(_: None) -> Iterator[Args]:
    """No valid pixel and every pixel valid on a flat image; valid NaN, +inf and -inf ranges;
    a step along the rows and one down the columns; one hole."""
    H, W = 8, 16
    flat = np.full((H, W), 10.0, np.float32)
    none = np.zeros((H, W), bool)
    yield flat, none, 0.5, 0.05
    yield flat, ~none, 0.5, 0.05
    odd = flat.copy()
    odd[2, 3], odd[5, 9], odd[1, 12] = np.nan, np.inf, -np.inf
    yield odd, ~none, 0.5, 0.05
    step = flat.copy()
    step[:, W // 2 :] = 20.0
    yield step, ~none, 0.5, 0.05
    down = flat.copy()
    down[H // 2 :, :] = 30.0
    yield down, ~none, 0.5, 0.05
    hole = ~none
    hole[3, 4] = False
    yield flat, hole, 0.5, 0.05


def _degenerate_edge_check(_: None, calls: list[Call]) -> None:
    no_valid, all_valid, odd, step, down, hole = (got for _, got, _ in calls)
    W = no_valid.shape[1]
    assert not no_valid.any() and not all_valid.any()
    # a valid NaN range makes no edge, nor does -inf (no finite nearer side); a valid +inf
    # is the far side of a jump for its four neighbours
    assert odd[5, 8] and odd[4, 9] and odd[5, 10] and odd[6, 9] and odd.sum() == 4
    # a step: the nearer side, along the row (wrapping round) and down the column
    assert set(np.flatnonzero(step.any(axis=0)).tolist()) == {W // 2 - 1, 0}
    assert np.flatnonzero(down.any(axis=1)).tolist() == [down.shape[0] // 2 - 1]
    # an empty pixel counts as infinitely far: the returns round it are the nearer side
    assert np.argwhere(hole).tolist() == [[2, 4], [3, 3], [3, 5], [4, 4]]


def _widening_inputs(_: None) -> Iterator[Args]:
    """Where numpy would widen: a float32 image with a numpy float64 threshold (numpy
    computes the threshold in float64), an integer image, a valid mask of another dtype.
    The kernel falls back to the reference."""
    s = list_sweep(9, 16, 128)
    yield s.range_m, s.valid, np.float64(0.5), 0.05
    yield np.nan_to_num(s.range_m, posinf=99).astype(np.int32), s.valid, 0.5, 0.05
    yield s.range_m, s.valid.astype(np.uint8), 0.5, 0.05


def _first_has_edges(_: None, calls: list[Call]) -> None:
    assert calls[0][1].any()


def _list_args(s: ListSweep, seed: int) -> tuple:
    """The arguments of list_slots_and_sums as sp.level2_lists.ListLevel.group builds them
    (without the range and intensity): range and brightness edges of the sweep, free-surface
    patches, and a table of the existing lists with some (owner, kind) keys still missing
    and one too large for it."""
    g = np.random.default_rng(seed)
    r_edge = range_edges(s.range_m, s.valid)
    b_edge = brightness_edges(s.intensity, s.valid) & ~r_edge
    H, W = s.owner.shape
    blocks = g.random((-(-H // 4), -(-W // 16))) < 0.3
    patch = np.kron(blocks, np.ones((4, 16), bool))[:H, :W] & s.valid
    n_keys = 4 * (int(s.owner.max(initial=0)) + 1)
    lut = np.full(n_keys - 3, -1, np.int64)
    have = g.permutation(lut.size)[: (3 * lut.size) // 4]
    lut[have] = np.arange(have.size)
    list_ids = 7 * np.arange(have.size, dtype=np.int64) + 1000
    return s.owner, r_edge, b_edge, patch, lut, list_ids


def _lists_reference(*args: Any) -> tuple[np.ndarray, ...]:
    """The numpy slots, ids, branches and missing keys, and the per-pixel sums kernel on
    them (it adds the same float64 values in the same order as the fused pass: the sums are
    compared bit for bit)."""
    *tables, range_m, intensity = args
    slots, ids, branches, missing = list_slots_reference(*tables)
    edge = tables[1] | tables[2]
    sums = list_sums(slots, range_m, intensity, edge, branches, tables[5].size)
    return slots, ids, branches, missing, sums


def _same_lists(got: Any, want: Any, args: Args) -> None:
    """The fused pass (and the slots pass alone) against the numpy slots, exactly; its sums
    against the per-pixel kernel's, bit for bit."""
    for g, w in zip(got[:4], want[:4], strict=True):
        np.testing.assert_array_equal(g, w)
    assert got[2].dtype == np.int8 and got[3].dtype == np.int64
    for g, w in zip(list_slots(*args[:6]), want[:4], strict=True):
        np.testing.assert_array_equal(g, w)
    _same_bytes(got[4], want[4], args)


def _list_sweep_inputs(seed: int) -> Iterator[Args]:
    s = list_sweep(seed)
    yield *_list_args(s, seed), s.range_m, s.intensity


def _list_sweep_check(_: int, calls: list[Call]) -> None:
    """Every kind and every case was there: vertices, lists to sum, keys still missing."""
    slots, _, branches, missing, sums = calls[-1][1]
    assert ((branches == 1) | (branches >= 3)).any() and (branches == 2).any()
    assert sums[:, 0].sum() > 1000 and missing.size > 0 and (slots <= -2).any()


def _list_sweep_float64_inputs(seed: int) -> Iterator[Args]:
    s = list_sweep(seed)
    yield *_list_args(s, seed), s.range_m.astype(np.float64), s.intensity.astype(np.float64)


def _fused_sums(*args: Any) -> np.ndarray:
    return list_slots_and_sums(*args)[4]


def _numpy_sums(*args: Any) -> np.ndarray:
    """The numpy sums (bincounts: another summation order) on the numpy slots."""
    *tables, range_m, intensity = args
    slots, _, branches, _ = list_slots_reference(*tables)
    edge = tables[1] | tables[2]
    return list_sums_reference(slots, range_m, intensity, edge, branches, tables[5].size)


def _to_rounding(got: Any, want: Any, args: Args) -> None:
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0.0)


def _small_list_inputs(param: tuple[int, tuple[int, int]]) -> Iterator[Args]:
    """Random edges and patches; owners on the empty pixels too (their infinite and NaN
    ranges and intensities summed), in float32 and float64."""
    seed, (H, W) = param
    s = small_list_sweep(seed, H, W)
    g = np.random.default_rng(seed)
    r_edge = g.random((H, W)) < 0.4
    b_edge = (g.random((H, W)) < 0.4) & ~r_edge
    patch = g.random((H, W)) < 0.5
    lut = np.array([0, -1, 1, 2, -1, 3, 4, 5, -1, 6], np.int64)  # owner 3's keys: missing
    list_ids = np.arange(7, dtype=np.int64) + 50
    owner = g.integers(-1, 4, (H, W))
    for tables in (
        (s.owner, r_edge, b_edge, patch, lut, list_ids),
        (owner, r_edge, b_edge, patch, lut, list_ids),
    ):
        yield *tables, s.range_m, s.intensity
        yield *tables, s.range_m.astype(np.float64), s.intensity.astype(np.float64)


def _degenerate_list_inputs(_: None) -> Iterator[Args]:
    """No edges and no patches; every pixel an edge; no owners; no lists at all (empty
    tables); a table of one list for everything; one pixel; an all-NaN intensity."""
    s = list_sweep(3, 16, 64)
    H, W = s.owner.shape
    args = _list_args(s, 3)
    owner, r_edge, b_edge, patch, lut, list_ids = args
    none = np.zeros((H, W), bool)
    every = ~none
    empty = np.zeros(0, np.int64)
    one = np.zeros(4 * (int(owner.max()) + 1), np.int64)
    yield owner, none, none, none, lut, list_ids, s.range_m, s.intensity
    yield owner, every, none, none, lut, list_ids, s.range_m, s.intensity
    yield np.full((H, W), -1), r_edge, b_edge, patch, lut, list_ids, s.range_m, s.intensity
    yield owner, r_edge, b_edge, patch, empty, empty, s.range_m, s.intensity
    yield owner, r_edge, b_edge, patch, one, np.array([9], np.int64), s.range_m, s.intensity
    yield (np.zeros((1, 1), np.int64), every[:1, :1], none[:1, :1], none[:1, :1], one, one[:1],
           s.range_m[:1, :1], s.intensity[:1, :1])  # fmt: skip
    yield *args, s.range_m, np.full((H, W), np.nan, np.float32)


def _degenerate_list_check(_: None, calls: list[Call]) -> None:
    nothing, every, _, no_lists, one, _, _ = calls
    slots, _, branches, missing, sums = nothing[1]
    assert (slots == -1).all() and not branches.any() and missing.size == 0 and not sums.any()
    # every pixel an edge: none inside has a branch (its whole ring is on), the top row one
    branches = every[1][2]
    assert (branches[1:-1, 1:-1] == 0).all() and (branches[0, 1:-1] == 1).all()
    _, _, _, missing, sums = no_lists[1]
    assert sums.shape == (0, 12) and missing.size > 0
    (owner, r_edge, b_edge, patch, *_), (_, _, _, missing, sums), _ = one
    assert missing.size == 0
    assert sums[0, 0] == np.count_nonzero((owner >= 0) & (r_edge | b_edge | patch))


# --- maps.fusion: the compiled fusion and ray casting -------------------------------------------

FUSION_KERNEL = FusionConfig()
FUSION_NUMPY = FusionConfig(compiled=False)
EXACT_LAYERS = {
    "count", "obstacle_count", "last_seen_ns", "occupancy", "elevation_min", "elevation_max",
}  # fmt: skip


def _same_layers(a: MapLevel, b: MapLevel) -> None:
    """Discrete layers and min / max equal; estimates equal up to the rounding of the sums'
    centring height (the kernel's sequential mean against numpy's pairwise one)."""
    for name in a.layer_names:
        x, y = a.storage(name), b.storage(name)
        if name in EXACT_LAYERS:
            np.testing.assert_array_equal(x, y, err_msg=name)
        elif x.dtype == np.float32:
            np.testing.assert_allclose(x, y, rtol=2e-6, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9, err_msg=name)


def _fusion_points(rng: np.random.Generator, n: int, bad: float = 0.05) -> np.ndarray:
    """Points over an 8 x 8 m patch (partly outside a 16 x 0.5 m window), a slope, obstacle
    points, a table top, and a share ``bad`` of NaN/inf coordinates."""
    xy = rng.uniform([-3.0, -6.0], [7.0, 4.0], size=(n, 2))
    z = 0.3 * xy[:, 0] + rng.normal(0, 0.05, n)
    z[rng.random(n) < 0.1] += rng.uniform(0.5, 2.0)
    top = (xy[:, 0] >= 2.5) & (xy[:, 1] >= -0.5) & (xy[:, 1] < 1.0)
    z[top & (rng.random(n) < 0.5)] += 1.0
    pts = np.column_stack([xy, z])
    hit = rng.random(n) < bad
    pts[hit, rng.integers(0, 3, int(hit.sum()))] = rng.choice([np.nan, np.inf, -np.inf])
    return pts


def _fused(config: FusionConfig) -> Callable[..., tuple[MapLevel, list]]:
    """A level of ``size`` cells of 0.5 m (moved to ``origin`` unless None) fused with each
    batch (t_ns, points, variances) in turn with ``config``; the level and the stats."""

    def fuse(batches: list, size: int, origin: np.ndarray | None) -> tuple[MapLevel, list]:
        level = MapLevel(LevelConfig("t", 0.5, size))
        if origin is not None:
            level.move_to(origin)
        stats = [fuse_points(level, p, v, t_ns=t, config=config) for t, p, v in batches]
        return level, stats

    return fuse


def _same_fusion(got: Any, want: Any, args: Args) -> None:
    assert got[1] == want[1]  # the stats of every batch
    _same_layers(got[0], want[0])


def _fusion_inputs(param: tuple[int, int, float]) -> Iterator[Args]:
    """Batches of random sweeps, variances per point, then scalar, then some refused."""
    seed, n_batches, bad = param
    rng = np.random.default_rng(seed)
    batches = []
    for b in range(n_batches):
        n = int(rng.integers(1, 400))
        pts = _fusion_points(rng, n, bad)
        var = rng.uniform(1e-4, 1e-2, n) if b % 2 == 0 else 3e-3  # per point, then scalar
        if b == 2:
            var[rng.random(n) < 0.1] = rng.choice([0.0, -1.0, np.nan])  # refused variances
        batches.append((100 + b, pts, var))
    yield batches, 16, np.array([2.0, -1.0])


def _fusion_edge_inputs(param: tuple[int, int]) -> Iterator[Args]:
    """Empty, single-point, all outside, all NaN/inf, points on cell edges, a non-power-of-two
    window (12), and float32 / Fortran-ordered input (the ``draw``-th sweep of seed 5)."""
    size, draw = param
    rng = np.random.default_rng(5)
    for _ in range(draw + 1):
        sweep = _fusion_points(rng, 500)
    edges = np.column_stack([np.arange(-4, 4) * 0.5, np.arange(-4, 4) * -0.5, np.zeros(8)])
    batches = [
        (1, np.zeros((0, 3)), 1e-3),
        (2, np.array([[0.3, -0.2, 1.0]]), 1e-3),
        (3, np.array([[0.3, -0.2, 0.0]]), np.array([1e-3])),
        (4, np.array([[500.0, 0.0, 0.0], [0.0, -1e300, 0.0]]), 1e-3),
        (5, np.full((5, 3), np.nan), 1e-3),
        (6, edges, 1e-3),
        (7, np.asfortranarray(sweep).astype(np.float32), 2e-3),
    ]
    yield batches, size, None


def _something_counted(_: Any, calls: list[Call]) -> None:
    assert calls[-1][1][0].window("count").sum() > 0


def _stack_frames() -> list[tuple[int, np.ndarray, np.ndarray, dict[str, Any]]]:
    """(t, centre, points, fuse keywords) of four sweeps round moving centres: variances per
    point, then the sensor's position, then a ray origin (free space cast)."""
    rng = np.random.default_rng(21)
    sensor = np.array([0.0, 0.0, 2.0])
    frames = []
    for t, centre in enumerate(([0.3, 0.2], [1.7, -0.9], [4.0, 2.2], [4.1, 2.2])):
        xy = np.array(centre) + rng.normal(0, 12.0, size=(20000 if t < 3 else 1500, 2))
        z = 0.05 * xy[:, 0] + rng.normal(0, 0.02, len(xy))
        z[rng.random(len(xy)) < 0.05] += 1.5
        pts = np.column_stack([xy, z])
        pts[rng.random(len(xy)) < 0.01, 2] = np.nan
        kw = {"variance_m2": rng.uniform(1e-4, 4e-4, len(xy))} if t < 2 else {"sensor_xyz": sensor}
        if t == 3:
            kw["ray_origin_xyz"] = sensor + np.array([*centre, 0.0])
        frames.append((t, np.array(centre), pts, kw))
    return frames


def _stack_inputs(_: None) -> Iterator[Args]:
    yield (_stack_frames(),)


def _stack_run(config: FusionConfig) -> Callable[[list], tuple[MapStack, list, list]]:
    """A three-level stack (rays cast on two, free space below 3 m) fused with each frame
    in turn: the stack, each fuse's stats, and each frame's points inside each level's
    window then."""
    levels = (
        LevelConfig("a", 0.1, 32, keep_tiles=False),
        LevelConfig("b", 0.5, 32, keep_tiles=False),
        LevelConfig("c", 2.5, 32, keep_tiles=False),
    )
    fusion = dataclasses.replace(config, ray_free_height_m=3.0)

    def run(frames: list) -> tuple[MapStack, list, list]:
        stack = MapStack(StackConfig(levels, fusion, raycast_levels=("b", "c")))
        stats, inside = [], []
        for t, centre, pts, kw in frames:
            stack.move_to(centre)
            stats.append(stack.fuse(pts, t_ns=t, **kw))
            finite = np.isfinite(pts).all(axis=1)
            inside.append(
                {lvl.name: int((lvl.contains(pts) & finite).sum()) for lvl in stack.levels}
            )
        return stack, stats, inside

    return run


def _same_stacks(got: Any, want: Any, args: Args) -> None:
    assert got[1] == want[1]  # the stats of every sweep
    for mine, ref in zip(got[0].levels, want[0].levels, strict=True):
        _same_layers(mine, ref)


def _each_point_once_per_level(_: None, calls: list[Call]) -> None:
    """Every level counts each point of its window once; the ray origin frees cells."""
    _, stats, inside = calls[-1][1]
    for t, (s, n) in enumerate(zip(stats, inside, strict=True)):
        assert t < 3 or s.cells_freed["b"] > 20
        for name, count in n.items():
            assert s.ground[name] + s.obstacle[name] == count


def _segment_cells(p: np.ndarray, s: np.ndarray, res: float):
    """Cells (ix, iy) whose square the 2-D segment from ``s`` to ``p`` (metres) crosses, with
    the parameter interval (from ``s``) of the crossing (Liang-Barsky clipping per cell)."""
    lo = np.floor(np.minimum(p, s) / res).astype(int)
    hi = np.floor(np.maximum(p, s) / res).astype(int)
    d = p - s
    for ix in range(lo[0], hi[0] + 1):
        for iy in range(lo[1], hi[1] + 1):
            u0, u1 = 0.0, 1.0
            for k, (a, b) in enumerate(((ix * res, (ix + 1) * res), (iy * res, (iy + 1) * res))):
                if d[k] == 0:
                    if not a <= s[k] < b:
                        u0, u1 = 1.0, 0.0
                    continue
                ua, ub = sorted(((a - s[k]) / d[k], (b - s[k]) / d[k]))
                u0, u1 = max(u0, ua), min(u1, ub)
            if u1 > u0:
                yield ix, iy, u0, u1


def _reference_rays(level, pts, origin, cfg: FusionConfig) -> set:
    """Cells lowered by the rule of :func:`maps.kernels.cast_rays`, by plain geometry: the
    lowest beam per start cell, each cell it crosses (not its end cell, nor one a point fell
    in) lowered where the beam passes within ``ray_free_height_m`` of the ground and not over
    a top seen there."""
    touched = {tuple(k) for k in level.world_to_cell(pts)}
    res = level.resolution_m
    horiz = np.linalg.norm(pts[:, :2] - origin[:2], axis=1)
    t_lim = np.minimum(1.0, cfg.ray_max_range_m / horiz)
    start = origin + t_lim[:, None] * (pts - origin)
    keys = [tuple(k) for k in np.floor(start[:, :2] / res).astype(int)]
    chosen: dict = {}
    for i, key in enumerate(keys):  # the lowest beam per start cell
        if key not in chosen or pts[i, 2] < pts[chosen[key], 2]:
            chosen[key] = i
    elev = {}
    lowered: set = set()
    for i in chosen.values():
        end = tuple(np.floor(pts[i, :2] / res).astype(int))
        for ix, iy, u0, u1 in _segment_cells(origin[:2], start[i, :2], res):
            if (ix, iy) == end or (ix, iy) in touched or (ix, iy) in lowered:
                continue
            if not level.contains(np.array([[ix + 0.5, iy + 0.5]]) * res)[0]:
                continue
            z = origin[2] + (pts[i, 2] - origin[2]) * t_lim[i] * (1 - 0.5 * (u0 + u1))
            if (ix, iy) not in elev:
                centre = np.array([[ix + 0.5, iy + 0.5]]) * res
                elev[ix, iy] = [level.read(n, centre)[0] for n in ("elevation", "elevation_max")]
            ground, top = elev[ix, iy]
            ground = pts[i, 2] if np.isnan(ground) else ground
            if z - ground <= cfg.ray_free_height_m and not z > top:
                lowered.add((ix, iy))
    return lowered


def _ray_inputs(_: None) -> Iterator[Args]:
    """A level whose cells partly know their ground, and 400 beams round a raised origin,
    their points already fused (without a ray origin: nothing cast yet)."""
    rng = np.random.default_rng(3)
    cfg = FusionConfig(ray_max_range_m=6.0, ray_free_height_m=0.8, ray_stop_after_cells=0)
    level = MapLevel(LevelConfig("t", 0.5, 32))
    origin = np.array([0.3, -0.2, 1.2])
    ground = np.column_stack([rng.uniform(-7, 7, (300, 2)), rng.normal(0.0, 0.02, 300)])
    fuse_points(level, ground, 1e-4, t_ns=0, config=cfg)  # some cells know their ground
    az = rng.uniform(-np.pi, np.pi, 400)
    r = rng.uniform(0.5, 10.0, 400)
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), rng.uniform(-0.2, 2.5, 400)])
    pts += origin * [1, 1, 0]
    fuse_points(level, pts, 1e-3, t_ns=1, config=cfg)
    yield level, pts, origin, cfg


def _cast(level: MapLevel, pts: np.ndarray, origin: np.ndarray, cfg: FusionConfig):
    """The cells the compiled cast lowered (read from the occupancy it changed, as world
    cells), and how many it says it lowered."""
    before = level.storage("occupancy").copy()
    lowered = cast_rays(level, pts, origin, cfg)
    srow, scol = np.nonzero(level.storage("occupancy") != before)
    ox, oy, size = *level.origin_cell, level.size
    ix, iy = (ox + (scol - ox) % size).tolist(), (oy + (srow - oy) % size).tolist()
    return lowered, set(zip(ix, iy, strict=True))


def _same_cells(got: Any, want: Any, args: Args) -> None:
    lowered, cells = got
    assert lowered == len(cells) > 20
    assert cells == want


# --- maps.pyramid: window sums and the correlation surface against their definitions --------


def _direct_window_sums(region: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    h, w = shape
    k = region.shape[0] - h + 1
    r = region.astype(np.float64)
    s = np.array([[r[a : a + h, b : b + w].sum() for b in range(k)] for a in range(k)])
    ss = np.array([[(r[a : a + h, b : b + w] ** 2).sum() for b in range(k)] for a in range(k)])
    return s, ss


WINDOW_SUM_REGIONS = [((10, 12), 5), ((5, 6), 5), ((3, 3), 3), ((7, 9), 1), ((140, 130), 3),
                      ((300, 280), 5)]  # fmt: skip


def _window_sum_inputs(param: tuple[tuple[int, int], int]) -> Iterator[Args]:
    """A region far from zero; windows ``k - 1`` smaller each way."""
    region_shape, k = param
    rng = np.random.default_rng(k + region_shape[0])
    region = (50.0 + rng.random(region_shape)).astype(np.float32)
    yield region, (region_shape[0] - k + 1, region_shape[1] - k + 1)


def _same_sums(got: Any, want: Any, args: Args) -> None:
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13)


def _both_window_sum_paths(_: Any, calls: list[Call]) -> None:
    """The regions span both paths: summed-area tables (small) and row/column reductions."""
    assert 10 * 12 <= TABLE_MAX_PX < 300 * 280


def _ncc_texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)


def _direct_ncc(ref: np.ndarray, mov: np.ndarray, center: tuple[int, int], d: tuple[int, int]):
    """Normalised correlation (float64) of ``mov`` against ``ref`` moved by ``center + d``,
    over the window the search builds at ``center``: the pixels of ``mov`` whose partners in
    ``ref`` exist for every offset within 2 px of ``center``."""
    (cr, cc), reach = center, 2
    h, w = mov.shape
    r0, r1 = max(0, cr + reach), min(h, ref.shape[0] + cr - reach)
    c0, c1 = max(0, cc + reach), min(w, ref.shape[1] + cc - reach)
    dr, dc = cr + d[0], cc + d[1]
    a = mov[r0:r1, c0:c1].astype(np.float64)
    b = ref[r0 - dr : r1 - dr, c0 - dc : c1 - dc].astype(np.float64)
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def _surface_inputs(size: int) -> Iterator[Args]:
    """A texture and the same moved by (6, -4); one level started at the true offset."""
    big = _ncc_texture((size + 60, size + 60), size)
    shift = (6, -4)
    ref = big[30 : 30 + size, 30 : 30 + size]
    mov = big[30 - shift[0] : 30 + size - shift[0], 30 - shift[1] : 30 + size - shift[1]]
    yield ref, mov, shift


def _one_level_search(ref: np.ndarray, mov: np.ndarray, shift: tuple[int, int]) -> Match:
    return register(ref, mov, levels=1, initial_shift_rc=shift)


def _ncc_around(ref: np.ndarray, mov: np.ndarray, shift: tuple[int, int]) -> list[list[float]]:
    """The normalised correlations at the 9 offsets around ``shift``."""
    return [[_direct_ncc(ref, mov, shift, (i, j)) for j in (-1, 0, 1)] for i in (-1, 0, 1)]


def _surface_is_ncc(got: Any, want: Any, args: Args) -> None:
    np.testing.assert_allclose(got.surface, want, atol=1e-5)


def _peak_at_the_shift(_: int, calls: list[Call]) -> None:
    (_, _, shift), got, _ = calls[-1]
    assert np.abs(got.shift_rc - shift).max() < 0.02  # the parabola through the peak


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
    Case("above_prior", _product(range(3), [0.4, 1.0]), _prior_inputs, above_prior,
         above_prior_reference, _equal, _prior_check),
    Case("on_known_ground", _product(range(3), [0.4, 1.0]), _prior_inputs, on_known_ground,
         on_known_ground_reference, _equal, _known_check),
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
    Case("foot_rise_deg", _product(range(3), [16, 200]), _foot_inputs, foot_rise_deg,
         foot_rise_deg_reference, _equal, _foot_check),
    Case("foot_rise_deg_simulated", [None], _foot_pipeline_inputs, foot_rise_deg,
         foot_rise_deg_reference, _equal, _foot_pipeline_check),
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
    Case("ground_mask_sweeps", _product(range(5), ["nan", "zero", "junk"]),
         _ground_sweep_inputs, ground_mask, ground_mask_reference, _same_ground, _mostly_ground,
         marks=[REFERENCE_CAST]),
    Case("ground_mask_tied_ranges", [0, 1, 2], _tied_range_inputs, ground_mask,
         ground_mask_reference, _same_ground, _ties_there_are, marks=[REFERENCE_CAST]),
    Case("refine_cell_boundaries", CELL_BOUNDARY_GRIDS, _cell_boundary_refine_inputs, refine,
         refine_reference, _equal, _some_but_not_all_valid_ground, marks=[REFERENCE_CAST]),
    Case("ground_mask_cell_boundaries", CELL_BOUNDARY_GRIDS, _cell_boundary_mask_inputs,
         ground_mask, ground_mask_reference, _same_ground, marks=[REFERENCE_CAST]),
    Case("ground_mask_atan2_split", ATAN2_SPLIT_XY, _atan2_split_mask_inputs, ground_mask,
         ground_mask_reference, _same_ground, _all_ground, marks=[REFERENCE_CAST]),
    Case("refine_atan2_split", ATAN2_SPLIT_XY, _atan2_split_refine_inputs, refine,
         refine_reference, _equal, _both_stay_ground, marks=[REFERENCE_CAST]),
    Case("ground_mask_clipped_height", [0.4, 1.8, 3.5], _clipped_height_inputs, ground_mask,
         ground_mask_reference, _same_ground, _clipped_height_check, marks=[REFERENCE_CAST]),
    Case("ground_mask_configs",
         [{"refine": False}, {"n_sectors": 1, "cell_m": 0.5}, {"n_sectors": 2, "cell_m": 7.0},
          {"n_sectors": 720, "cell_m": 0.25, "max_slope_deg": 10.0, "step_m": 0.2},
          {"resume_gap_m": 0.1, "resume_gap_per_m": 0.0, "refine_within_m": 0.5}],
         _ground_config_inputs, ground_mask, ground_mask_reference, _same_ground, _some_ground,
         marks=[REFERENCE_CAST]),
    Case("ground_mask_dtypes_strides", [None], _ground_dtype_inputs, ground_mask,
         _ground_mask_of_copies, _same_ground, _strided_check, marks=[REFERENCE_CAST]),
    Case("ground_mask_small_images", _product(SMALL_GROUND_SHAPES, [0.0, 0.3, 1.0]),
         _small_ground_inputs, ground_mask, ground_mask_reference, _same_ground,
         _no_returns_no_ground, marks=[REFERENCE_CAST]),
    Case("ground_mask_all_invalid_and_all_valid", [None], _all_invalid_and_all_valid_inputs,
         ground_mask, ground_mask_reference, _same_ground, _all_invalid_and_all_valid_check,
         marks=[REFERENCE_CAST]),
    Case("ground_prepare", [0, 1], _prepare_inputs, _prepare_kernel, _prepare_reference,
         _same_arrays, _prepare_check, marks=[REFERENCE_CAST]),
    Case("ground_prepare_hypot", [None], _awkward_hypot_inputs,
         lambda xyz, valid: _prepare_kernel(xyz, valid)[3],
         lambda xyz, valid: np.hypot(xyz[..., 0], xyz[..., 1])[valid], _equal,
         marks=[REFERENCE_CAST]),
    Case("ground_median_height", [None], _median_height_inputs, _median_height_of,
         _height_from_lowest, _same_height, _median_height_check, marks=[REFERENCE_CAST]),
    Case("column_walk_sweeps", WALK_SWEEPS, _walk_sweep_inputs, column_walk,
         _column_walk_zero_filled, _equal, _some_ground_walked, marks=[REFERENCE_CAST]),
    Case("refine_sweeps", WALK_SWEEPS, _refine_sweep_inputs, refine, refine_reference, _equal,
         _no_ground_outside_valid, marks=[REFERENCE_CAST]),
    Case("refine_given_ranges_sweeps", WALK_SWEEPS, _sweep_grounds,
         lambda x, y, z, v, g, r: refine(x, y, z, v, g, GroundConfig(), r_m=r),
         lambda x, y, z, v, g, r: refine(x, y, z, v, g, GroundConfig()), _equal,
         marks=[REFERENCE_CAST]),
    Case("window_mask", _product(range(3), [1, 11, 265, 2000]), _window_inputs, window_mask,
         window_mask_reference, _same_mask, _windows_within_rows, marks=[REFERENCE_CAST]),
    Case("window_mask_wrap", [None], _wrap_inputs, window_mask, window_mask_reference,
         _same_mask, _wraps, marks=[REFERENCE_CAST]),
    Case("window_mask_degenerate", [None], _degenerate_window_inputs, window_mask,
         window_mask_reference, _same_mask, _degenerate_window_check, marks=[REFERENCE_CAST]),
    Case("range_jump_edges_sweeps", LIST_SWEEPS, _edge_sweep_inputs, range_jump_edges,
         range_jump_edges_reference, _same_bytes, _some_edges),
    Case("range_edges_sweeps", LIST_SWEEPS, _range_edges_inputs, range_edges,
         _range_edges_reference, _same_bytes, _no_edge_outside_valid),
    Case("range_jump_edges_small", SMALL_LIST_IMAGES, _small_edge_inputs, range_jump_edges,
         range_jump_edges_reference, _same_bytes),
    Case("range_jump_edges_degenerate", [None], _degenerate_edge_inputs, range_jump_edges,
         range_jump_edges_reference, _same_bytes, _degenerate_edge_check),
    Case("range_jump_edges_widening", [None], _widening_inputs, range_jump_edges,
         range_jump_edges_reference, _same_bytes, _first_has_edges),
    Case("list_slots_and_sums_sweeps", list(range(5)), _list_sweep_inputs, list_slots_and_sums,
         _lists_reference, _same_lists, _list_sweep_check),
    Case("list_sums_numpy", list(range(5)), _list_sweep_float64_inputs, _fused_sums,
         _numpy_sums, _to_rounding),
    Case("list_slots_and_sums_small", SMALL_LIST_IMAGES, _small_list_inputs,
         list_slots_and_sums, _lists_reference, _same_lists),
    Case("list_slots_and_sums_degenerate", [None], _degenerate_list_inputs, list_slots_and_sums,
         _lists_reference, _same_lists, _degenerate_list_check),
    Case("fuse_points", _product(range(4), [1, 2, 3, 4], [0.0, 0.3]), _fusion_inputs,
         _fused(FUSION_KERNEL), _fused(FUSION_NUMPY), _same_fusion),
    Case("fuse_points_edge_cases", [(16, 0), (12, 1)], _fusion_edge_inputs,
         _fused(FUSION_KERNEL), _fused(FUSION_NUMPY), _same_fusion, _something_counted,
         marks=[pytest.mark.filterwarnings("ignore:invalid value encountered in cast")]),
    Case("stack_fuse", [None], _stack_inputs, _stack_run(FUSION_KERNEL),
         _stack_run(FUSION_NUMPY), _same_stacks, _each_point_once_per_level),
    Case("cast_rays", [None], _ray_inputs, _cast, _reference_rays, _same_cells),
    Case("window_sums", WINDOW_SUM_REGIONS, _window_sum_inputs, _window_sums,
         _direct_window_sums, _same_sums, _both_window_sum_paths),
    Case("register_surface", [48, 128, 256], _surface_inputs, _one_level_search, _ncc_around,
         _surface_is_ncc, _peak_at_the_shift),
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
