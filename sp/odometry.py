"""LADAR odometry: a thin adapter over KISS-ICP giving ``T_world_body`` per sweep, fused with
wheel odometry, with a quality figure and honest loss / recovery of track.

Reference 001, 4.5 and docs/architecture.md, the node cycle (steps 1-2: the pose track, then the
self state into the KD); the fusion follows the estimator form
``x(t|t) = x*(t|t-1) + K (y(t) - y*(t|t-1))``.

Per sweep (one :class:`~logs.types.LadarScan`):

1. predict the sweep's motion: from wheel odometry when it is there, else constant velocity;
2. deskew the sweep with its per-point times and register it to KISS-ICP's local map (KISS-ICP's
   own preprocessing, voxelisation, adaptive threshold and registration, called step by step);
3. judge the result: ``quality`` in 0..1 is the fraction of the registered sweep that lands in
   voxels the previous sweep occupied, scaled down when the result departs from the prediction;
   a sweep with too few points, a jump beyond ``max_step_m`` / ``max_step_rad`` or a quality
   under ``min_quality`` is *rejected*: the map is not touched and the pose follows the
   prediction, with ``status`` saying why (the next good sweep recovers);
4. fuse: the sweep's motion is ``delta = delta_pred + K (delta_icp - delta_pred)`` over the six
   axes (translation, rotation vector), with ``K = P (P + R)^-1``, ``P`` the wheel odometry's
   covariance and ``R`` the registration's: ``R = c H^-1 / quality^2`` with ``H`` the
   point-to-plane information of the registered points (:func:`registration_information`),
   so a direction the scene does not constrain (along a bare slope, around the vertical in
   open country) gets a large variance and follows the wheels, while a well-constrained one
   follows the registration (degeneracy as in Zhang, Kaess and Singh, ICRA 2016); ``R`` is
   then scaled by how far the registrations' innovations against the wheels have exceeded
   what ``P + R`` predicts over the last second (covariance matching,
   :meth:`LadarOdometry._consistency`).

Poses: KISS-ICP deskews a sweep to the end of its per-point times once the motion is known; a
sweep taken as it is (no per-point times, deskew off, or the first sweeps before any motion is
known) stands for its middle. So an estimate is the pose at the sweep's *reference time*, its
end or its middle, which :class:`OdometryEstimate` carries as ``t_ns``.
``T_world_body = T_world_sensor @ inv(T_body_sensor)``; the world is the body frame at the middle
of the first sweep unless ``T_world_body0`` (the body pose at that time) says otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from core.errors import EngineError
from core.geometry import (
    check_pose,
    interpolate_pose,
    rotvec_of,
    rotvec_to_matrix,
    se3_inverse,
    transform_points,
)
from logs.types import LadarScan, OdometryFrame
from sp.voxels import first_per_voxel


class OdometryError(EngineError, ValueError):
    """A configuration or input the odometry cannot use; names the value."""


#: Largest departure of a wheel-odometry rotation from orthonormal (entries of ``R R^T - I``)
#: taken as rounding (a quaternion stored in float32); the rotation is then re-orthonormalised.
#: The node screens messages with the same bound, so what it passes the odometry takes.
WHEEL_POSE_ATOL = 1e-4


class TrackStatus(StrEnum):
    """What happened to a sweep."""

    FIRST = "first"  # the first sweep: it starts the map
    TRACKING = "tracking"  # registered and accepted
    RECOVERED = "recovered"  # accepted after one or more rejected sweeps
    LOST = "lost"  # rejected: the pose follows the prediction (see ``message``)


@dataclass(frozen=True)
class OdometryConfig:
    """LADAR odometry settings (defaults in one place).

    max_range_m, min_range_m: points used (sensor frame).
    voxel_size_m:   KISS-ICP map voxel; None for max_range_m / 100 (KISS-ICP's default).
    deskew:         motion-compensate each sweep with its per-point times.
    min_points:     a sweep with fewer usable points is rejected.
    max_step_m, max_step_rad: largest believable motion between two sweeps.
    min_quality:    registrations judged below this are rejected.
    wheel_sigma_m, wheel_sigma_rad: per-sweep standard deviation of wheel-odometry motion.
                    The rotation's is a gyro's over one 0.1 s sweep (0.03 degrees): in open
                    country a registration pins the heading mostly through the shape of the
                    ground, and there it can be off by 0.1 degree a sweep for seconds on end,
                    a bias the per-sweep blend cannot see; weighted at twice the gyro's
                    error it turned the heading 2.5 degrees in 6 s on one development world.
    icp_sigma_m, icp_sigma_rad: per-sweep standard deviation of a fully trusted registration.
    tilt_sigma_rad: the standard deviation of the roll and pitch a wheel-odometry message reports
                    when its pose covariance gives none (an inertial unit's attitude: about
                    0.5 degrees for a small MEMS unit); a message whose roll and pitch are both
                    exactly zero, or whose covariance gives them more than ``max_tilt_sigma_rad``,
                    carries no attitude (planar odometry) and levels nothing.
    max_tilt_sigma_rad: see ``tilt_sigma_rad``.
    ground_share, ground_z_m: with wheel odometry to fuse, the registration keeps only this
                    share of its points near the body's ground plane (body z below
                    ``ground_z_m``). On flat ground each laser ring returns at the same place
                    in the sensor frame sweep after sweep, and point-to-point registration
                    pulls the motion toward standing still (a parking lot: registration alone
                    short by 6 % of the path); the wheels then carry the motion along the
                    ground while the remaining ground points keep height, roll and pitch.
                    Without wheels the ground stays whole: it is then the only vertical
                    constraint a sparse scene offers.
    wheel_scale_sigma: prior standard deviation of the wheel odometry's speed scale (wheel
                    radius, tyre pressure: about 1 %); the scale is estimated as a bias state
                    from the registrations (:meth:`LadarOdometry._estimate_wheel_scale`) and
                    divided out of the wheels' motion. 0 turns the estimate off.
    wheel_scale_drift: standard deviation of the scale's random walk per sweep.
    wheel_scale_after: registrations before the scale is learned from them (the first ones
                    register to a local map of a few sweeps, which holds them back).
    gate_sigma:     per axis, a registration further than this many standard deviations from
                    the wheel odometry is not used on that axis.
    consistency_sweeps: the registrations' covariance is matched to their innovations against
                    the wheels (:meth:`LadarOdometry._consistency`) over about this many
                    sweeps (the time constant of a running mean of the normalised
                    innovation squared); 0 turns the matching off.
    info_neighbours, info_radius_m: the neighbours (and their farthest distance) that fit the
                    local plane of each registered point for the information matrix, found
                    in the sweep thinned to one point per ``info_voxel_m``, for at most
                    ``info_max_points`` registered points (an even share of them).
    info_well_constrained: the per-point information (eigenvalue of ``H / n``) of a
                    direction that ``icp_sigma_m`` describes; weaker directions get
                    proportionally more variance.
    max_points_per_voxel: points KISS-ICP's local map keeps per voxel (its default is 20).
                    Each source point's nearest neighbour is sought among the 27 voxels
                    around it, so this bounds the registration's cost: on the default
                    scenario (450 m) 5 instead of 20 makes the registration cheaper without
                    adding drift, fused with wheel odometry or by registration alone.
    max_threads:    KISS-ICP's threads (0: as many as cores).
    convergence:    KISS-ICP's registration stops when an iteration's pose update (its se(3)
                    vector: metres and radians) is smaller than this. Its default, 1e-4,
                    polishes a 1 m voxel map to a tenth of a millimetre; 3e-3 stops at 3 mm,
                    which saves iterations while leaving the drift (default scenario) and ATE
                    (7-Scenes) all but unchanged.
    max_iterations: its bound on Gauss-Newton iterations per sweep.
    thin_before_deskew: KISS-ICP deskews every point, then keeps one per half voxel
                    (:mod:`sp.voxels`); thinning first deskews only the points kept (each with
                    its own time, so exactly), the sample differing only in which point of a
                    half voxel stands for it, so the preprocessing of a dense sweep deskews
                    only a fraction of its points.
    source_voxel_ratio: the registered points are the sweep thinned to one per this many map
                    voxels (KISS-ICP's value is 1.5).
    max_source_points: a denser sweep is thinned once more, at the spacing that sampling a
                    surface predicts gives this many (spacing grown by sqrt(n / max)), so the
                    registration's cost stays bounded whatever the sensor (None: no bound).
                    A 32 x 1024 sweep of the default scenario gives 1500-2000 points at 1.5
                    voxels, a 64 x 1024 one 2400-3400; thinning the 32-beam sweeps further
                    (at 2 voxels) made registration alone (no wheel odometry) drift more over
                    the default scenario's 450 m, so the bound leaves them as they are.
    """

    max_range_m: float = 100.0
    min_range_m: float = 1.0
    voxel_size_m: float | None = None
    deskew: bool = True
    min_points: int = 200
    max_step_m: float = 5.0
    max_step_rad: float = 0.6
    min_quality: float = 0.25
    wheel_sigma_m: float = 0.01
    wheel_sigma_rad: float = 0.0005
    icp_sigma_m: float = 0.02
    icp_sigma_rad: float = 0.002
    gate_sigma: float = 3.0
    consistency_sweeps: int = 10
    tilt_sigma_rad: float = 0.01
    max_tilt_sigma_rad: float = 0.1
    ground_share: float = 0.2
    ground_z_m: float = 0.3
    wheel_scale_sigma: float = 0.01
    wheel_scale_drift: float = 1e-4
    wheel_scale_after: int = 20
    max_points_per_voxel: int = 5
    max_threads: int = 0
    convergence: float = 3e-3
    max_iterations: int = 500
    thin_before_deskew: bool = True
    source_voxel_ratio: float = 1.5
    max_source_points: int | None = 2000
    info_neighbours: int = 8
    info_radius_m: float = 3.0
    info_voxel_m: float = 1.0
    info_max_points: int = 500
    info_well_constrained: float = 0.07

    def __post_init__(self) -> None:
        if not 0 <= self.min_range_m < self.max_range_m:
            raise OdometryError(
                f"need 0 <= min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}"
            )
        for name in ("max_step_m", "max_step_rad", "wheel_sigma_m", "wheel_sigma_rad"):
            if not getattr(self, name) > 0:
                raise OdometryError(f"{name} must be positive, got {getattr(self, name)}")
        if self.max_source_points is not None and self.max_source_points < 10:
            raise OdometryError(
                f"max_source_points must be None or >= 10, got {self.max_source_points}"
            )
        if not self.source_voxel_ratio > 0:
            raise OdometryError(
                f"source_voxel_ratio must be positive, got {self.source_voxel_ratio}"
            )
        if self.max_points_per_voxel < 1:
            raise OdometryError(
                f"max_points_per_voxel must be >= 1, got {self.max_points_per_voxel}"
            )
        if self.consistency_sweeps < 0:
            raise OdometryError(
                f"consistency_sweeps must be >= 0 (0: off), got {self.consistency_sweeps}"
            )

    @property
    def voxel_m(self) -> float:
        return self.voxel_size_m if self.voxel_size_m is not None else self.max_range_m / 100.0


@dataclass
class OdometryEstimate:
    """The pose of one sweep: ``T_world_body`` (4x4 float64) at ``t_ns``, its quality (0..1),
    status and, when rejected, why."""

    t_ns: int
    T_world_body: np.ndarray
    quality: float
    status: TrackStatus
    message: str = ""
    n_points: int = 0
    delta_icp: np.ndarray | None = field(default=None, repr=False)  # sensor motion, 4x4


def to_vector(T: np.ndarray) -> np.ndarray:
    """A small motion as (x, y, z, rx, ry, rz): translation and rotation vector."""
    return np.concatenate([T[:3, 3], rotvec_of(T[:3, :3])])


def from_vector(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_vector`."""
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(v[3:])
    T[:3, 3] = v[:3]
    return T


class WheelOdometry:
    """Buffer of wheel-odometry poses ``T_odom_body``; gives the body motion between times."""

    def __init__(self, horizon: int = 2000, max_extrapolate_ns: int = 50_000_000) -> None:
        self.t_ns: list[int] = []
        self.poses: list[np.ndarray] = []
        # per message, the variance (rad^2) of the roll and pitch it reports: 0 when its
        # covariance says nothing, NaN when it carries no attitude (both exactly zero: planar)
        self.tilt_var: list[float] = []
        self.horizon = horizon
        self.max_extrapolate_ns = max_extrapolate_ns

    def add(self, frame: OdometryFrame) -> None:
        """Buffer one message; a pose that is not a finite rigid transform raises
        :class:`OdometryError` and leaves the buffer as it was (its lists stay aligned)."""
        if self.t_ns and frame.t_ns <= self.t_ns[-1]:
            return  # out of order or repeated: the buffer keeps time order
        T = _rigid(frame.T_parent_child, f"wheel odometry T_odom_body at t_ns={frame.t_ns}")
        tilt_var = _reported_tilt_variance(frame)
        self.t_ns.append(int(frame.t_ns))
        self.poses.append(T)
        self.tilt_var.append(tilt_var)
        if len(self.t_ns) > self.horizon:
            del self.t_ns[0], self.poses[0], self.tilt_var[0]

    def pose_at(self, t_ns: int) -> np.ndarray | None:
        """``T_odom_body`` at ``t_ns``: interpolated inside the buffered span, continued at
        constant velocity up to ``max_extrapolate_ns`` past its end, else None."""
        if not self.t_ns or t_ns < self.t_ns[0]:
            return None
        if t_ns > self.t_ns[-1]:
            if len(self.t_ns) < 2 or t_ns - self.t_ns[-1] > self.max_extrapolate_ns:
                return None
            step = se3_inverse(self.poses[-2]) @ self.poses[-1]
            ratio = (t_ns - self.t_ns[-1]) / (self.t_ns[-1] - self.t_ns[-2])
            return self.poses[-1] @ scale_motion(step, ratio)
        i = int(np.searchsorted(self.t_ns, t_ns))
        if self.t_ns[i] == t_ns:
            return self.poses[i]
        t0, t1 = self.t_ns[i - 1], self.t_ns[i]
        return interpolate_pose(self.poses[i - 1], self.poses[i], (t_ns - t0) / (t1 - t0))

    def attitude_at(self, t_ns: int) -> tuple[np.ndarray, float] | None:
        """The body's attitude in the odometry frame at ``t_ns`` (3x3) and the variance of its
        roll and pitch (rad^2, see ``tilt_var``) as the last message at or before then
        reports, or None outside the buffered span."""
        T = self.pose_at(t_ns)
        if T is None:
            return None
        i = max(0, int(np.searchsorted(self.t_ns, t_ns, side="right")) - 1)
        return T[:3, :3], self.tilt_var[i]

    def motion(self, t0_ns: int, t1_ns: int) -> np.ndarray | None:
        """Body motion ``T_body(t0)_body(t1)`` between two times, or None without data."""
        a, b = self.pose_at(t0_ns), self.pose_at(t1_ns)
        if a is None or b is None:
            return None
        return se3_inverse(a) @ b


class LadarOdometry:
    """KISS-ICP driven sweep by sweep (see the module docstring).

    ``T_body_sensor`` is the LADAR mount; ``T_world_body0`` the body pose at the first sweep.
    Feed wheel odometry with :meth:`add_wheel_odometry` as it arrives (before the sweeps it
    covers), and each sweep with :meth:`update`.
    """

    def __init__(
        self,
        config: OdometryConfig | None = None,
        T_body_sensor: np.ndarray | None = None,
        T_world_body0: np.ndarray | None = None,
    ) -> None:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
        from kiss_icp.voxelization import voxel_down_sample

        self._down_sample = voxel_down_sample

        self.config = cfg = config or OdometryConfig()
        kiss = KISSConfig()
        kiss.data.max_range, kiss.data.min_range = cfg.max_range_m, cfg.min_range_m
        kiss.data.deskew = cfg.deskew
        kiss.mapping.voxel_size = cfg.voxel_m
        kiss.mapping.max_points_per_voxel = cfg.max_points_per_voxel
        kiss.registration.max_num_threads = cfg.max_threads
        kiss.registration.convergence_criterion = cfg.convergence
        kiss.registration.max_num_iterations = cfg.max_iterations
        self._kiss_config = kiss
        self.kiss = KissICP(kiss)
        self.T_body_sensor = np.eye(4) if T_body_sensor is None else check_pose(T_body_sensor)
        self.T_sensor_body = se3_inverse(self.T_body_sensor)
        T0 = np.eye(4) if T_world_body0 is None else check_pose(T_world_body0, "T_world_body0")
        self.T_world_map = T0 @ self.T_body_sensor  # KISS-ICP's map frame: first sensor pose
        self.wheel = WheelOdometry()
        self.last_t_ns: int | None = None  # reference time of the last sweep
        self.last_stamp_ns: int | None = None  # its stamp
        self.last_interval_ns = 0  # between the last two reference times
        self.n_lost = 0
        self._previous_voxels: np.ndarray | None = None
        self.last_gain = np.zeros(6)  # per-axis weight of the registration in the last fusion
        self.last_rotation_var = 0.0  # variance (rad^2) of the last fused rotation, per axis
        # variance (rad^2) of the estimated roll and pitch: the world starts level with the
        # first wheel-odometry attitude, so it starts at zero
        self.tilt_P = 0.0
        # the wheels' speed scale (wheel distance / true distance) and its variance, a bias
        # state: the per-sweep fusion treats wheel errors as white, which a scale error is not
        self.wheel_scale = 1.0
        self.wheel_scale_P = cfg.wheel_scale_sigma**2
        self._wheel_body_delta: np.ndarray | None = None  # the last sweep's raw wheel motion
        self._scale_sweeps = 0  # registrations offered to the scale estimate
        # running mean of the registrations' normalised innovation squared against the wheels
        # (6 when their covariance is right; :meth:`_consistency`)
        self.mean_nis = 6.0
        # the last accepted sweep: reference time and T_world_sensor (recover() restarts there)
        self.last_good: tuple[int, np.ndarray] | None = None

    def add_wheel_odometry(self, frame: OdometryFrame) -> None:
        """Buffer a wheel-odometry message; raises :class:`OdometryError` on a pose that is
        not a finite rigid transform, the buffer unchanged."""
        self.wheel.add(frame)

    def update_or_skip(self, scan: LadarScan) -> tuple[OdometryEstimate | None, str]:
        """:meth:`update` that never raises: a sweep it fails on gives ``(None, reason)``,
        the reason ``"odometry failed: ..."`` naming the sweep and the error, and the
        odometry restarts from its last accepted pose (:meth:`recover`), so one bad sweep
        costs that sweep alone. ``(estimate, "")`` otherwise."""
        try:
            return self.update(scan), ""
        except Exception as e:  # any bug or bad value in one sweep must not end the track
            why = f"odometry failed: sweep at t_ns={scan.t_ns}: {type(e).__name__}: {e}"
            self.recover()
            return None, why

    def recover(self) -> None:
        """Start a fresh registration map at the last accepted sweep's pose (the world frame
        stays): the next sweep is placed by the wheels' motion since then (or where that
        sweep was, without wheels) and starts the new map. The wheel buffer is kept."""
        from kiss_icp.kiss_icp import KissICP

        self.kiss = KissICP(self._kiss_config)
        if self.last_good is not None:
            self.last_t_ns, self.T_world_map = self.last_good[0], self.last_good[1].copy()
        else:  # nothing accepted yet: restart where the world started
            self.last_t_ns = None
        self.last_interval_ns = 0
        self._previous_voxels = None
        self.n_lost += 1

    def _T_world_body(self, T_map_sensor: np.ndarray) -> np.ndarray:
        return self.T_world_map @ T_map_sensor @ self.T_sensor_body

    def _predicted_delta(self, t_ns: int) -> tuple[np.ndarray, bool]:
        """Sensor motion since the last sweep: from wheel odometry if it covers the interval,
        else KISS-ICP's constant-velocity model (scaled to the interval)."""
        if self.last_t_ns is None:
            return np.eye(4), False
        body = self.wheel.motion(self.last_t_ns, t_ns)
        self._wheel_body_delta = body
        if body is not None:
            body = body.copy()
            body[:3, 3] /= self.wheel_scale
            return self.T_sensor_body @ body @ self.T_body_sensor, True
        if self.last_interval_ns <= 0:
            return self.kiss.last_delta, False
        return scale_motion(
            self.kiss.last_delta, (t_ns - self.last_t_ns) / self.last_interval_ns
        ), False

    def _voxels(self, points: np.ndarray) -> np.ndarray:
        keys = np.floor(points / self.config.voxel_m).astype(np.int64)
        return np.unique((keys[:, 0] * 1_000_003 + keys[:, 1]) * 1_000_033 + keys[:, 2])

    def update(self, scan: LadarScan) -> OdometryEstimate:
        """Register one sweep; returns its pose, quality and status."""
        cfg, kiss = self.config, self.kiss
        if self.last_stamp_ns is not None and scan.t_ns <= self.last_stamp_ns:
            raise OdometryError(
                f"sweep at t_ns={scan.t_ns} is not after the last one ({self.last_stamp_ns})"
            )
        self.last_stamp_ns = int(scan.t_ns)
        t_mid, t_end = sweep_times_ns(scan)
        pts = np.asarray(scan.points_xyz, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1:] != (3,):
            raise OdometryError(
                f"sweep at t_ns={scan.t_ns}: points_xyz shape {pts.shape}, not (N, 3)"
            )
        finite = np.all(np.isfinite(pts), axis=1)
        range_m = np.linalg.norm(pts, axis=1)
        usable = finite & (range_m >= cfg.min_range_m) & (range_m <= cfg.max_range_m)
        times = _normalised_times(scan.t_offset_ns, usable) if cfg.deskew else np.zeros(0)
        pts = pts[usable]
        # A sweep deskewed with a known motion refers to its end (KISS-ICP's deskew reference);
        # one taken as it is (no times, or no motion known yet) to its middle.
        t_ns = t_end if times.size else t_mid
        delta_pred, from_wheel = self._predicted_delta(t_ns)
        if times.size and np.allclose(delta_pred, np.eye(4), atol=1e-12):
            t_ns = t_mid
        if pts.shape[0] < cfg.min_points:
            return self._reject(
                t_ns, delta_pred, f"{pts.shape[0]} usable points < {cfg.min_points}"
            )

        first = kiss.local_map.empty()
        # KISS-ICP's register_frame, step by step, so a bad result never reaches the map.
        # The deskew takes the motion over the sweep's own span of point times.
        span = sweep_span_ns(scan)
        interval = t_ns - self.last_t_ns if self.last_t_ns is not None else 0
        sweep_motion = scale_motion(delta_pred, span / interval) if interval > 0 else delta_pred
        n_usable = pts.shape[0]
        if cfg.thin_before_deskew:
            keep = first_per_voxel(pts, 0.5 * cfg.voxel_m)
            pts, times = pts[keep], times[keep] if times.size else times
        frame = kiss.preprocessor.preprocess(pts, times, sweep_motion)
        frame_down = self._down_sample(frame, 0.5 * cfg.voxel_m)
        spacing = cfg.source_voxel_ratio * cfg.voxel_m
        source = self._down_sample(frame_down, spacing)
        cap = cfg.max_source_points
        if cap is not None and len(source) > cap:
            source = self._down_sample(frame_down, spacing * math.sqrt(len(source) / cap))
        if from_wheel and cfg.ground_share < 1.0:
            source = _thin_ground(source, self.T_body_sensor, cfg)
        sigma = kiss.adaptive_threshold.get_threshold()
        guess = kiss.last_pose @ delta_pred
        pose = kiss.registration.align_points_to_map(
            points=source,
            voxel_map=kiss.local_map,
            initial_guess=guess,
            max_correspondance_distance=3 * sigma,
            kernel=sigma,
        )
        delta_icp = se3_inverse(kiss.last_pose) @ pose
        quality, why = self._judge(source, pose, delta_icp, delta_pred, sigma, first)
        if why:
            return self._reject(t_ns, delta_pred, why, quality, n_usable)
        if from_wheel:
            stride = max(1, -(-len(source) // cfg.info_max_points))
            cloud = self._down_sample(frame_down, cfg.info_voxel_m)
            info = registration_information(cloud, source[::stride], pose, kiss.last_pose, cfg)
            R = registration_covariance(info, quality, cfg)
            R = R * self._consistency(delta_pred, delta_icp, R)
            self._estimate_wheel_scale(delta_icp, R)
            pose = kiss.last_pose @ self._fuse(delta_pred, delta_icp, R)
            pose = self._level(pose, t_ns)
        kiss.adaptive_threshold.update_model_deviation(se3_inverse(guess) @ pose)
        kiss.local_map.update(frame_down, pose)
        kiss.last_delta = se3_inverse(kiss.last_pose) @ pose
        kiss.last_pose = pose
        self._previous_voxels = self._voxels(transform_points(pose, frame_down))
        status = (
            TrackStatus.FIRST
            if first
            else (TrackStatus.RECOVERED if self.n_lost else TrackStatus.TRACKING)
        )
        self.n_lost = 0
        self.last_interval_ns = t_ns - self.last_t_ns if self.last_t_ns is not None else 0
        self.last_t_ns = t_ns
        self.last_good = (t_ns, self.T_world_map @ pose)
        return OdometryEstimate(
            t_ns, self._T_world_body(pose), quality, status, "", n_usable, delta_icp
        )

    def _judge(
        self,
        source: np.ndarray,
        pose: np.ndarray,
        delta_icp: np.ndarray,
        delta_pred: np.ndarray,
        sigma: float,
        first: bool,
    ) -> tuple[float, str]:
        """Quality of a registration (0..1) and, if it must be rejected, why."""
        cfg = self.config
        if first:
            return 1.0, ""
        step = to_vector(delta_icp)
        if np.linalg.norm(step[:3]) > cfg.max_step_m or np.linalg.norm(step[3:]) > cfg.max_step_rad:
            return 0.0, (
                f"registration jumped {np.linalg.norm(step[:3]):.2f} m / "
                f"{np.linalg.norm(step[3:]):.3f} rad in one sweep (limits {cfg.max_step_m} m, "
                f"{cfg.max_step_rad} rad)"
            )
        overlap = 1.0
        if self._previous_voxels is not None:
            now = self._voxels(transform_points(pose, source))
            overlap = float(np.isin(now, self._previous_voxels, assume_unique=True).mean())
        # Departure from the prediction beyond KISS-ICP's own expected spread lowers trust.
        dev = to_vector(se3_inverse(delta_pred) @ delta_icp)
        spread = 3.0 * max(sigma, cfg.voxel_m)
        agreement = float(np.exp(-0.5 * (np.linalg.norm(dev[:3]) / spread) ** 2))
        quality = float(np.clip(overlap / 0.5, 0.0, 1.0)) * (0.5 + 0.5 * agreement)
        if quality < cfg.min_quality:
            return quality, (
                f"registration quality {quality:.2f} < {cfg.min_quality} (overlap with the "
                f"previous sweep {overlap:.2f})"
            )
        return quality, ""

    def _wheel_covariance(self) -> np.ndarray:
        """Covariance (6, 6) of one sweep's wheel-odometry motion, axes x y z rx ry rz."""
        cfg = self.config
        return np.diag(np.array([cfg.wheel_sigma_m] * 3 + [cfg.wheel_sigma_rad] * 3) ** 2)

    def _consistency(self, delta_pred: np.ndarray, delta_icp: np.ndarray, R: np.ndarray) -> float:
        """The factor (>= 1) the registration's covariance ``R`` (6, 6) is scaled by: the
        running mean of its normalised innovation squared against the wheels,
        ``d = v^T (P + R)^-1 v`` with ``v`` the motions' difference, over the 6 it has when
        ``R`` and ``P`` are right (covariance matching, as in Mehra's adaptive Kalman
        filtering). The point-to-plane information takes each point's error as independent,
        but on smooth ground a registration errs as a whole (the laser rings, the shape of a
        bare slope) and its real spread can be ten times what the information says; never
        below 1: the registration is not trusted beyond its information."""
        n = self.config.consistency_sweeps
        if n == 0:
            return 1.0
        v = to_vector(delta_icp) - to_vector(delta_pred)
        d = float(v @ np.linalg.solve(self._wheel_covariance() + R, v))
        self.mean_nis += (d - self.mean_nis) / n
        return max(1.0, self.mean_nis / 6.0)

    def _fuse(self, delta_pred: np.ndarray, delta_icp: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Kalman blend of the wheels (prediction, covariance P) and the registration
        (measurement, covariance ``R`` (6, 6), :func:`registration_covariance`, sensor frame,
        axes x y z rx ry rz), both sensor motions over one sweep (4x4)."""
        cfg = self.config
        P = self._wheel_covariance()
        x_pred = to_vector(delta_pred)
        innovation = to_vector(delta_icp) - x_pred
        K = P @ np.linalg.inv(P + R)
        # Gate per axis: a registration that disagrees with the wheels far beyond both spreads
        # (a slide the information did not reveal, a wheel slip) is not used on that axis.
        gated = np.abs(innovation) > cfg.gate_sigma * np.sqrt(np.diag(P + R))
        K[gated, :] = 0.0
        K[:, gated] = 0.0
        self.last_gain = np.diag(K).copy()
        self.last_rotation_var = float(np.mean(np.diag((np.eye(6) - K) @ P)[3:5]))
        return from_vector(x_pred + K @ innovation)

    def _estimate_wheel_scale(self, delta_icp: np.ndarray, R: np.ndarray) -> None:
        """Update the wheels' speed scale ``k`` from one registration (a scalar Kalman filter,
        ``x = k``): along the direction ``u`` the wheels moved, they measure ``z = k (u . t)``
        of the registration's translation ``t`` (body frame), with the registration's variance
        along ``u`` (``R``, (6, 6), sensor axes) and the wheels' own white noise. A direction
        the scene does not constrain has a large variance there and teaches the scale little;
        a registration beyond ``gate_sigma`` of the estimate (a slide, a wheel slip) none."""
        cfg, body = self.config, self._wheel_body_delta
        self._scale_sweeps += 1
        if (
            cfg.wheel_scale_sigma <= 0
            or body is None
            or self._scale_sweeps <= cfg.wheel_scale_after
        ):
            return
        moved = float(np.linalg.norm(body[:3, 3]))
        if moved < 10 * cfg.wheel_sigma_m:  # standing or creeping: no scale to see
            return
        u = body[:3, 3] / moved
        icp_body = self.T_body_sensor @ delta_icp @ self.T_sensor_body
        H = float(u @ icp_body[:3, 3])
        R_mount = self.T_body_sensor[:3, :3]
        var_icp = float(u @ (R_mount @ R[:3, :3] @ R_mount.T) @ u)
        self.wheel_scale_P += cfg.wheel_scale_drift**2
        S = H * H * self.wheel_scale_P + self.wheel_scale**2 * var_icp + cfg.wheel_sigma_m**2
        innovation = moved - self.wheel_scale * H
        if abs(innovation) > cfg.gate_sigma * math.sqrt(S):
            return
        K = self.wheel_scale_P * H / S
        bound = 3.0 * cfg.wheel_scale_sigma  # a scale beyond the prior's 3 sd is no tyre's
        self.wheel_scale = float(np.clip(self.wheel_scale + K * innovation, 1 - bound, 1 + bound))
        self.wheel_scale_P *= 1.0 - K * H

    def _level(self, T_map_sensor: np.ndarray, t_ns: int) -> np.ndarray:
        """Correct the roll and pitch of a fused pose toward the attitude the wheel odometry
        reports at ``t_ns``, an absolute measurement of the gravity direction where the
        odometry carries one (an inertial unit): a scalar Kalman update per tilt axis,
        ``P += q`` (the fused rotation's variance), ``K = P / (P + R)``. Chained sweep motions
        alone let a small pitch error per sweep grow into height drift (about 0.5 m per 100 m
        for 5 mrad); the gravity reference bounds it. Yaw is untouched. Returns the corrected
        ``T_map_sensor`` (4x4)."""
        cfg = self.config
        self.tilt_P += self.last_rotation_var
        wheel = self.wheel.attitude_at(t_ns)
        if wheel is None:
            return T_map_sensor
        R_odom_body, R = wheel
        R = cfg.tilt_sigma_rad**2 if R == 0.0 else R
        if not R <= cfg.max_tilt_sigma_rad**2:  # also NaN: planar odometry
            return T_map_sensor
        T_world_body = self._T_world_body(T_map_sensor)
        up_est = T_world_body[2, :3]  # the world's z axis in the body frame
        up_meas = R_odom_body[2, :3]
        K = self.tilt_P / (self.tilt_P + R)
        self.tilt_P *= 1.0 - K
        # the body-frame rotation that turns the estimated up toward the measured one
        delta = np.cross(up_meas, up_est)
        T_world_body[:3, :3] = T_world_body[:3, :3] @ rotvec_to_matrix(K * delta)
        return se3_inverse(self.T_world_map) @ T_world_body @ self.T_body_sensor

    def _reject(
        self,
        t_ns: int,
        delta_pred: np.ndarray,
        why: str,
        quality: float = 0.0,
        n_points: int = 0,
    ) -> OdometryEstimate:
        """Keep the map as it was; carry the pose forward by the prediction."""
        kiss = self.kiss
        if not kiss.local_map.empty():
            kiss.last_pose = kiss.last_pose @ delta_pred
        self.n_lost += 1
        if self.last_t_ns is not None and not kiss.local_map.empty():
            self.last_interval_ns = t_ns - self.last_t_ns
            kiss.last_delta = delta_pred
        self.last_t_ns = t_ns
        message = f"sweep at t_ns={t_ns} rejected: {why}; pose follows the prediction"
        return OdometryEstimate(
            t_ns, self._T_world_body(kiss.last_pose), quality, TrackStatus.LOST, message, n_points
        )


def _rigid(T: np.ndarray, name: str) -> np.ndarray:
    """``T`` (4x4 float64) if it is a finite rigid transform within :data:`WHEEL_POSE_ATOL`,
    a rotation off by rounding replaced by the nearest rotation (SVD); else
    :class:`OdometryError`."""
    try:
        T = check_pose(T, name, atol=WHEEL_POSE_ATOL).copy()
    except ValueError as e:
        raise OdometryError(str(e)) from None
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9):  # exact ones stay bit for bit
        u, _, vt = np.linalg.svd(R)
        T[:3, :3] = u @ vt
    return T


def _reported_tilt_variance(frame: OdometryFrame) -> float:
    """The roll / pitch variance (rad^2) a wheel-odometry message reports (the larger of its
    pose covariance's two), 0 when the covariance is empty or unusable, NaN when its roll and
    pitch are both exactly zero: planar odometry, which carries no attitude."""
    R = np.asarray(frame.T_parent_child)[:3, :3]
    if R[2, 0] == 0.0 and R[2, 1] == 0.0:
        return math.nan
    try:
        cov = np.asarray(frame.pose_covariance, dtype=np.float64)
    except (TypeError, ValueError):  # not numbers at all: as unusable as a wrong shape
        return 0.0
    if cov.shape != (6, 6):
        return 0.0
    var = max(float(cov[3, 3]), float(cov[4, 4]))
    return var if math.isfinite(var) and var > 0 else 0.0


def registration_information(
    cloud_sensor: np.ndarray,
    source_sensor: np.ndarray,
    T_map_sensor: np.ndarray,
    T_map_last: np.ndarray,
    config: OdometryConfig,
) -> np.ndarray:
    """Point-to-plane information ``H / n`` (6, 6) of a registration, in the frame of the last
    sensor pose, axes (x, y, z, rx, ry, rz) as :func:`to_vector` orders a motion.

    Each registered point ``p`` (source_sensor (n, 3), sensor frame) with the normal ``n`` of
    its neighbours in the sweep (cloud_sensor (m, 3)) constrains the motion along
    ``a = (n, p x n)``, weighted by how planar the neighbourhood is; ``H = sum a a^T``. Points and
    normals are expressed in the last pose's frame, where the fused motion is taken. A
    direction with a small eigenvalue is one the scene does not pin down."""
    from scipy.spatial import cKDTree

    n_src = len(source_sensor)
    if n_src == 0 or len(cloud_sensor) < config.info_neighbours:
        return np.zeros((6, 6))
    k = config.info_neighbours
    # built for one query: unbalanced and uncompacted, it builds faster
    tree = cKDTree(cloud_sensor, balanced_tree=False, compact_nodes=False)
    dist, idx = tree.query(source_sensor, k=k, distance_upper_bound=config.info_radius_m)
    ok = np.isfinite(dist).all(axis=1)
    if not ok.any():
        return np.zeros((6, 6))
    nb = cloud_sensor[idx[ok]]  # (n, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred) / k)
    normal = v[:, :, 0]
    planarity = (w[:, 1] - w[:, 0]) / np.maximum(w[:, 2], 1e-12)
    T_last_sensor = se3_inverse(T_map_last) @ T_map_sensor
    R, t = T_last_sensor[:3, :3], T_last_sensor[:3, 3]
    p = source_sensor[ok] @ R.T + t
    normal = normal @ R.T
    a = np.concatenate([normal, np.cross(p, normal)], axis=1) * np.sqrt(planarity)[:, None]
    return a.T @ a / n_src


def _thin_ground(
    source: np.ndarray, T_body_sensor: np.ndarray, config: OdometryConfig
) -> np.ndarray:
    """The registration's points (n, 3, sensor frame) with those near the body's ground plane
    (body z below ``ground_z_m``) kept at ``ground_share`` only."""
    z = source @ T_body_sensor[2, :3] + T_body_sensor[2, 3]
    ground = z < config.ground_z_m
    step = max(1, round(1.0 / max(config.ground_share, 1e-6)))
    keep = ~ground
    keep[np.flatnonzero(ground)[::step]] = True
    return source[keep]


def registration_covariance(info: np.ndarray, quality: float, config: OdometryConfig) -> np.ndarray:
    """Covariance (6, 6) of one registration's motion from its information ``H / n`` (see
    :func:`registration_information`): a direction with ``info_well_constrained`` of
    information per point has the variance ``icp_sigma_m ** 2``, a weaker one proportionally
    more; the quality scales it as before. Regularised so that a direction with no information
    at all has a standard deviation of about 10 m (10 rad), not infinity."""
    c = config.icp_sigma_m**2 * config.info_well_constrained
    H = info / c + np.eye(6) * 1e-2
    return np.linalg.inv(H) / max(quality, 1e-3) ** 2


def scale_motion(T: np.ndarray, factor: float) -> np.ndarray:
    """The motion ``T`` continued at constant velocity for ``factor`` times as long."""
    return from_vector(to_vector(T) * factor)


def sweep_span_ns(scan: LadarScan) -> int:
    """Time from a sweep's first to its last point (0 without per-point times)."""
    t = np.asarray(scan.t_offset_ns)
    return int(t.max() - t.min()) if t.size else 0


def sweep_times_ns(scan: LadarScan) -> tuple[int, int]:
    """Middle and end of a sweep's per-point times (both the stamp when it has none)."""
    t = np.asarray(scan.t_offset_ns)
    if t.size == 0:
        return int(scan.t_ns), int(scan.t_ns)
    lo, hi = int(t.min()), int(t.max())
    return int(scan.t_ns) + (lo + hi) // 2, int(scan.t_ns) + hi


def _normalised_times(t_offset_ns: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Per-point times scaled to 0..1 over the sweep (KISS-ICP's deskew input), or an empty
    array when the sweep carries no per-point times."""
    t = np.asarray(t_offset_ns, dtype=np.float64)
    if t.shape != usable.shape:
        raise OdometryError(f"t_offset_ns has shape {t.shape}, the points {usable.shape}")
    t = t[usable]
    if t.size == 0 or t.max() <= t.min():
        return np.zeros(0)
    return (t - t.min()) / (t.max() - t.min())
