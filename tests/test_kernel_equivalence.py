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

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from kernel_reference.computation_reference import ground_below_reference, ground_plane_reference
from kernel_reference.covariance_reference import psd_mask_reference
from kernel_reference.ground_reference import column_walk_reference, refine_reference
from kernel_reference.poses_reference import deskew_to_world_reference
from kernel_reference.sweep_points_reference import sweep_points_reference
from kernel_reference.voxels_reference import first_per_voxel_reference

from core.geometry import interpolate_pose, rotvec_to_matrix, se3, transform_points
from kd_store.covariance import pack_covariance, psd_mask
from logs.types import LadarScan
from sp.computation import ground_below, ground_plane
from sp.egosphere import EgosphereConfig, to_egosphere
from sp.ground import GroundConfig, column_walk, refine
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


def _product(*axes: list[Any]) -> list[tuple[Any, ...]]:
    """Every combination, the first axis varying slowest (as stacked parametrize marks)."""
    import itertools

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
]  # fmt: skip


def _param_id(param: Any) -> str:
    if param is None:
        return "-"
    items = param if isinstance(param, tuple) else (param,)
    return "-".join(getattr(p, "__name__", str(p)) for p in items)


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
