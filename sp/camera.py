"""Camera model: pinhole with OpenCV (plumb-bob) distortion, and LADAR ranges in camera pixels.

Reference 001, 4.4.6 (Image Field of View): a camera image is a patch of its sensor egosphere
("each pixel can be assigned a range attribute whose value is the estimated distance to the
point from the center of the egosphere"). Frames: the optical frame ``camera`` (z forward,
x right, y down); pixels ``(u, v)`` = (column, row), centre of the top-left pixel at (0, 0).
Numpy core; ``cv2.projectPoints`` / ``cv2.undistortPoints`` only when distortion is non-zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.errors import EngineError
from core.geometry import check_pose, transform_points
from logs.types import CameraFrame


class CameraError(EngineError, ValueError):
    """Impossible intrinsics, a wrong-sized image or unusable points; names the value."""


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics ``K`` (3x3, pixels), distortion ``dist`` (k1, k2, p1, p2, k3) and
    image size. Refuses non-finite or non-positive focal lengths, a skewed or non-upper-
    triangular ``K``, a principal point off the image and an empty image size."""

    K: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)
        if self.width < 1 or self.height < 1:
            raise CameraError(f"camera image size {self.width}x{self.height} is empty")
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraError(f"camera K must be a finite 3x3 matrix, got {K.tolist()}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise CameraError(f"camera focal lengths fx={K[0, 0]}, fy={K[1, 1]} must be > 0")
        if K[0, 1] != 0 or np.any(K[1:, 0] != 0) or K[2, 1] != 0 or K[2, 2] != 1:
            raise CameraError(f"camera K must be [[fx,0,cx],[0,fy,cy],[0,0,1]], got {K.tolist()}")
        cx, cy = K[0, 2], K[1, 2]
        if not (-0.5 <= cx <= self.width - 0.5 and -0.5 <= cy <= self.height - 0.5):
            raise CameraError(
                f"camera principal point ({cx}, {cy}) lies off the {self.width}x{self.height} image"
            )
        if d.size not in (4, 5, 8) or not np.all(np.isfinite(d)):
            raise CameraError(f"camera dist must be 4, 5 or 8 finite values, got {d.tolist()}")

    @classmethod
    def from_frame(cls, frame: CameraFrame) -> PinholeCamera:
        """The camera of a :class:`~logs.types.CameraFrame` (size from its image)."""
        w, h = frame.size_wh
        return cls(K=frame.K, width=w, height=h, dist=frame.dist)

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.dist != 0))

    def check_image(self, image: np.ndarray, name: str = "image") -> np.ndarray:
        """Return ``image`` if it is (height, width[, C]) numeric, else raise naming it."""
        a = np.asarray(image)
        if a.shape[:2] != (self.height, self.width) or a.ndim not in (2, 3):
            raise CameraError(
                f"{name} has shape {a.shape}, the camera is {self.height}x{self.width} (H x W)"
            )
        if a.dtype.kind not in "fiu":
            raise CameraError(f"{name} has dtype {a.dtype}, expected a numeric image")
        return a

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) points in the optical frame -> pixels (N, 2) float64 (u, v) and a bool mask
        (N,) of points in front of the camera (z > 1 mm) that land on the image."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = p[:, 2]
        front = z > 1e-3
        zs = np.where(front, z, 1.0)
        xn, yn = p[:, 0] / zs, p[:, 1] / zs
        if self.distorted:
            xn, yn = self._distort(xn, yn)
        u = self.K[0, 0] * xn + self.K[0, 2]
        v = self.K[1, 1] * yn + self.K[1, 2]
        inside = (u >= -0.5) & (u < self.width - 0.5) & (v >= -0.5) & (v < self.height - 0.5)
        return np.stack([u, v], axis=1), front & inside

    def _distort(self, xn: np.ndarray, yn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV plumb-bob distortion of normalised coordinates."""
        k1, k2, p1, p2 = self.dist[:4]
        k3 = self.dist[4] if self.dist.size > 4 else 0.0
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if self.dist.size == 8:
            k4, k5, k6 = self.dist[5:]
            radial /= 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return xd, yd

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) (u, v) -> rays (N, 3) in the optical frame with z = 1 (undistorted)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.distorted:
            import cv2

            xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2)
        else:
            xy = np.stack(
                [
                    (uv[:, 0] - self.K[0, 2]) / self.K[0, 0],
                    (uv[:, 1] - self.K[1, 2]) / self.K[1, 1],
                ],
                axis=1,
            )
        return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)

    def back_project(self, uv: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) with depth along z (N,) metres -> (N, 3) points in the optical frame."""
        return self.rays(uv) * np.asarray(depth_m, dtype=np.float64).reshape(-1, 1)

    def depth_to_points(self, depth_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A depth image (H, W) metres (NaN or <= 0 unknown) -> points (M, 3) float32 in the
        optical frame and their pixel (row, col) indices (M, 2)."""
        depth = self.check_image(depth_m, "depth image").astype(np.float64)
        rows, cols = np.nonzero(np.isfinite(depth) & (depth > 0))
        uv = np.stack([cols, rows], axis=1).astype(np.float64)
        pts = self.back_project(uv, depth[rows, cols]).astype(np.float32)
        return pts, np.stack([rows, cols], axis=1)


@dataclass
class CameraRange:
    """LADAR ranges in camera pixels (nearest point per pixel wins).

    range_m: (H, W) float32 distance from the camera centre, NaN where no point landed.
    depth_m: (H, W) float32 depth along the optical axis, NaN where no point landed.
    point_index: (H, W) int64 index of the point in the input array, -1 where none.
    """

    range_m: np.ndarray
    depth_m: np.ndarray
    point_index: np.ndarray


def ladar_range_in_camera(
    camera: PinholeCamera, points_sensor: np.ndarray, T_camera_sensor: np.ndarray
) -> CameraRange:
    """Project LADAR points (N, 3), sensor frame, into the camera so its pixels carry range
    (4.4.6: "each pixel can be assigned a range attribute")."""
    T = check_pose(T_camera_sensor, "T_camera_sensor")
    pts = np.asarray(points_sensor, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CameraError(f"points_sensor must be (N, 3), got shape {pts.shape}")
    p_cam = transform_points(T, pts)
    uv, ok = camera.project(p_cam)
    idx = np.flatnonzero(ok)
    rows = np.rint(uv[idx, 1]).astype(np.int64)
    cols = np.rint(uv[idx, 0]).astype(np.int64)
    point_range_m = np.linalg.norm(p_cam[idx], axis=1)
    flat = rows * camera.width + cols
    n = camera.width * camera.height
    nearest = np.full(n, np.inf)
    np.minimum.at(nearest, flat, point_range_m)
    wins = point_range_m == nearest[flat]  # the nearest point of each pixel (ties: one of them)
    index = np.full(n, -1, dtype=np.int64)
    index[flat[wins]] = idx[wins]
    hit = index >= 0
    range_m = np.full(n, np.nan, dtype=np.float32)
    depth_m = np.full(n, np.nan, dtype=np.float32)
    range_m[hit] = np.linalg.norm(p_cam[index[hit]], axis=1)
    depth_m[hit] = p_cam[index[hit], 2]
    shape = (camera.height, camera.width)
    return CameraRange(range_m.reshape(shape), depth_m.reshape(shape), index.reshape(shape))
