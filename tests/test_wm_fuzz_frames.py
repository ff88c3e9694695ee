"""Property-based fuzz of every sensor message the node takes: a frame spoiled at random
(shapes, dtypes, NaN/inf, huge and negative values, rotations that are none, odd times) fed
among good ones. ``feed`` never raises (only FrameTypeError, for what is no frame), and the
good sweeps after it still run their cycles with finite poses.

Times shifted within ``NodeConfig.max_time_jump_ns`` are left out on purpose: a good frame a
few minutes ahead of the log is, by the node's design, taken (the log may have paused), and
the sweeps behind it are then out of order."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from logs import open_log
from logs.types import (
    CameraFrame,
    GroundTruthPose,
    ImuFrame,
    LadarScan,
    ObjectBoxes,
    OdometryFrame,
    TransformFrame,
)
from wm.config import NodeConfig, PoseSource

# the arrays of each frame type a spoiler may replace
ARRAYS: dict[type, tuple[str, ...]] = {
    LadarScan: ("points_xyz", "intensity", "t_offset_ns", "ring"),
    CameraFrame: ("image", "K", "depth", "dist"),
    OdometryFrame: ("T_parent_child", "twist_linear", "twist_angular", "pose_covariance"),
    ImuFrame: ("angular_velocity", "linear_acceleration", "orientation_xyzw"),
    TransformFrame: ("T_parent_child",),
    ObjectBoxes: ("ids", "centers", "sizes", "yaws", "velocities"),
    GroundTruthPose: ("T_parent_child",),
}
POSES = {OdometryFrame, TransformFrame, GroundTruthPose}
SPECIAL = [np.nan, np.inf, -np.inf, 1e30, -1e30, 1e9, -1.0, 0.0]
DTYPES = [np.float32, np.float64, np.int64, np.int32, np.uint8, np.uint16, np.bool_]
#: cheap nodes: truth poses with SP on (camera and boxes reach SP), odometry in the node's
#: process with SP off (wheel odometry and sweeps reach the registration)
CONFIGS = {
    "truth+sp": NodeConfig(pose_source=PoseSource.TRUTH),
    "odometry": NodeConfig(use_sp=False, odometry_process=False),
}
WARMUP_SWEEPS = 3  # good sweeps fed before the bad frame
AFTER_SWEEPS = 2  # good cycles that must follow it


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> list:
    from fixtures.simulate import simulate_to_log

    path = tmp_path_factory.mktemp("fuzz") / "short.mcap"
    log = simulate_to_log("default", path, seconds=1.6, seed=44, progress=False)
    return list(open_log(log).frames())


def _imu(t_ns: int) -> ImuFrame:
    return ImuFrame(t_ns, "body", np.zeros(3), np.array([0.0, 0.0, 9.81]), np.r_[0.0, 0, 0, 1])


@st.composite
def weird_time(draw, t_ns: int) -> object:
    """A time that is no int64-like integer, or one far beyond the node's jump bound."""
    far = 10**12  # 1000 s, over NodeConfig.max_time_jump_ns (600 s)
    return draw(
        st.one_of(
            st.none(),
            st.booleans(),
            st.floats(allow_nan=True, allow_infinity=True),
            st.text(max_size=3),
            st.integers(-(2**70), 2**70),
            st.integers(far, 2**62).map(lambda d: t_ns + d),
            st.integers(far, 2**62).map(lambda d: np.int64(t_ns - d)),
            st.just(np.float64(t_ns)),
        )
    )


@st.composite
def weird_array(draw, like: np.ndarray | None) -> object:
    """A random small array of any dtype, the template with special values put in, the
    template cast to another dtype, or something that is no array."""
    dtype = draw(st.sampled_from(DTYPES))
    shape = hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5)
    fresh = hnp.arrays(dtype, shape)
    options = [fresh, st.none(), st.just([1.0, 2.0, 3.0]), st.just("x")]
    if like is not None and like.size:
        options.append(st.just(_cast(like, dtype)))
        spots = st.lists(st.integers(0, like.size - 1), min_size=1, max_size=4)
        options.append(st.tuples(spots, st.sampled_from(SPECIAL)).map(lambda sv: _put(like, *sv)))
    return draw(st.one_of(options))


def _cast(like: np.ndarray, dtype: type) -> np.ndarray:
    with np.errstate(invalid="ignore", over="ignore"):  # NaN to int: whatever numpy makes
        return like.astype(dtype, copy=True)


def _put(like: np.ndarray, spots: list[int], value: float) -> np.ndarray:
    a = np.array(like, dtype=np.float64 if like.dtype.kind != "f" else like.dtype)
    with np.errstate(over="ignore"):
        a.reshape(-1)[spots] = value
    return a


@st.composite
def bad_rotation(draw, T: np.ndarray) -> np.ndarray:
    T = np.array(T, dtype=np.float64)
    R = draw(hnp.arrays(np.float64, (3, 3), elements=st.floats(-2, 2)))
    T[:3, :3] = R if draw(st.booleans()) else T[:3, :3] * draw(st.sampled_from([0.0, -1.0, 1.5]))
    return T


@st.composite
def spoiled(draw, template) -> object:
    """The template frame with one thing spoiled (time, an array, a rotation or a name)."""
    kind = type(template)
    what = draw(st.sampled_from(["time", "array", "array", "rotation", "name"]))
    if what == "time":
        return dataclasses.replace(template, t_ns=draw(weird_time(int(template.t_ns))))
    if what == "rotation" and kind in POSES:
        T = draw(bad_rotation(template.T_parent_child))
        return dataclasses.replace(template, T_parent_child=T)
    if what == "name":
        field = draw(st.sampled_from([f for f in ("frame_id", "child_frame_id", "parent_frame_id")
                                      if hasattr(template, f)]))  # fmt: skip
        return dataclasses.replace(template, **{field: draw(st.sampled_from([None, 3, b"x"]))})
    field = draw(st.sampled_from(ARRAYS[kind]))
    return dataclasses.replace(template, **{field: draw(weird_array(getattr(template, field)))})


def _split(frames: list) -> tuple[list, list]:
    """The log up to its ``WARMUP_SWEEPS``-th sweep, and the rest."""
    k = [i for i, f in enumerate(frames) if isinstance(f, LadarScan)][WARMUP_SWEEPS]
    return frames[:k], frames[k:]


def _template(frames: list, kind: type, t_ns: int):
    """The last ``kind`` frame of ``frames`` (a made-up IMU frame: the log has none), 1 ns
    after the log's latest so that an unspoiled one would be in time."""
    if kind is ImuFrame:
        return _imu(t_ns + 1)
    last = next(f for f in reversed(frames) if isinstance(f, kind))
    return dataclasses.replace(last, t_ns=t_ns + 1)


def _check(frames: list, config: NodeConfig, kind: type, data) -> None:
    """The property, for one spoiled frame of ``kind`` drawn from ``data``."""
    import kd_store
    from wm.node import WorldModelNode

    before, after = _split(frames)
    bad = data.draw(spoiled(_template(before, kind, before[-1].t_ns)), label="bad frame")
    kd = kd_store.open(":memory:")
    try:
        with WorldModelNode(kd, config) as node:
            for f in before:
                node.feed(f)
            cycles = node.feed(bad)  # never raises for a frame, however spoiled
            n_bad = len(cycles)
            for f in after:  # until the good sweeps after it have run: enough, and cheap
                cycles += node.feed(f)
                if len(cycles) - n_bad >= AFTER_SWEEPS:
                    break
            cycles += node.finish()
        assert len(cycles) - n_bad >= AFTER_SWEEPS, (node.stats.skipped, node.stats.notes)
        for c in cycles:
            assert np.all(np.isfinite(c.T_world_body)), c.t_ns
    finally:
        kd.close()


def _property(frames, config_name: str, examples: int) -> None:
    @settings(
        max_examples=examples,
        deadline=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )
    @given(kind=st.sampled_from(list(ARRAYS)), data=st.data())
    def run(kind, data) -> None:
        _check(frames, CONFIGS[config_name], kind, data)

    run()


@pytest.mark.parametrize("config_name", list(CONFIGS))
def test_no_spoiled_frame_breaks_the_run(frames, config_name) -> None:
    _property(frames, config_name, examples=12)


@pytest.mark.eval
@pytest.mark.parametrize("config_name", list(CONFIGS))
def test_no_spoiled_frame_breaks_the_run_many(frames, config_name) -> None:
    _property(frames, config_name, examples=400)


@pytest.mark.parametrize("thing", [None, 3, "frame", {"t_ns": 0}, np.zeros((4, 4)), [1, 2]])
def test_only_what_is_no_frame_raises_and_only_frame_type_error(frames, thing) -> None:
    import kd_store
    from wm.node import FrameTypeError, WorldModelNode

    kd = kd_store.open(":memory:")
    with WorldModelNode(kd, CONFIGS["odometry"]) as node:
        with pytest.raises(FrameTypeError):
            node.feed(thing)
    kd.close()
