"""RGB-D folders in the Microsoft 7-Scenes layout.

``frame-XXXXXX.color.jpg`` (or ``.color.png``), ``frame-XXXXXX.depth.png`` (16-bit
millimetres; 0 and 65535 mean no reading), ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world,
i.e. ``T_world_camera``) and ``camera-intrinsics.txt`` (3x3 K; 7-Scenes' published
fx = fy = 585, cx = 320, cy = 240 when absent). Each frame yields a :class:`CameraFrame` on
``/camera`` (RGB image, depth in metres with NaN where unknown) and a
:class:`GroundTruthPose` (``world`` -> ``camera``) on ``/ground_truth/pose``.

The folders carry no times: frame k is stamped k / 30 s (the Kinect's 30 Hz) and
:meth:`LogSource.info` says so. The depth image is used as registered to the colour image,
as 7-Scenes' users usually do (the two sensors are a few centimetres apart).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.geometry import CAMERA, NS_PER_S, WORLD
from logs.source import LogSource, TopicInfo
from logs.types import CameraFrame, GroundTruthPose, LogError, LogMessage

FRAME_RATE_HZ = 30
CAMERA_TOPIC = "/camera"
POSE_TOPIC = "/ground_truth/pose"
K_7SCENES = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
_COLOR = re.compile(r"^frame-(\d{6})\.color\.(jpg|png)$")


def _color_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("frame-*.color.*") if _COLOR.match(p.name))


class RgbdLogSource(LogSource):
    """A 7-Scenes style RGB-D folder."""

    format_name = "RGB-D folder (7-Scenes layout)"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        return path.is_dir() and bool(_color_files(path))

    def __init__(self, path: str | Path, *, skip_corrupt: bool = False) -> None:
        super().__init__(path, skip_corrupt=skip_corrupt)
        self.color_files = _color_files(self.path)
        if not self.color_files:
            raise LogError(f"{self.path}: no frame-XXXXXX.color.jpg images")
        numbers = np.array([int(_COLOR.match(p.name)[1]) for p in self.color_files])
        self.times_ns = np.round(numbers * (NS_PER_S / FRAME_RATE_HZ)).astype(np.int64)
        self.K = self._intrinsics()

    def _intrinsics(self) -> np.ndarray:
        path = self.path / "camera-intrinsics.txt"
        if not path.is_file():
            return K_7SCENES.copy()
        try:
            K = np.loadtxt(path, dtype=np.float64).reshape(3, 3)
        except ValueError as exc:
            raise LogError(f"{path}: not a 3x3 matrix: {exc}") from exc
        return K

    def _notes(self) -> list[str]:
        notes = [f"times synthesised at {FRAME_RATE_HZ} Hz (frame number / {FRAME_RATE_HZ} s)"]
        if not (self.path / "camera-intrinsics.txt").is_file():
            notes.append("no camera-intrinsics.txt: 7-Scenes K (585, 585, 320, 240) assumed")
        return notes

    def _topics(self) -> list[TopicInfo]:
        t0, t1, n = int(self.times_ns.min()), int(self.times_ns.max()), len(self.times_ns)
        n_pose = sum(self._pose_path(p).is_file() for p in self.color_files)
        return [
            TopicInfo(CAMERA_TOPIC, "CameraFrame", n, t0, t1),
            TopicInfo(POSE_TOPIC, "GroundTruthPose", n_pose, t0, t1),
        ]

    @staticmethod
    def _pose_path(color: Path) -> Path:
        return color.with_name(color.name.split(".")[0] + ".pose.txt")

    def _camera(self, color: Path, t_ns: int) -> CameraFrame | None:
        import cv2

        bgr = cv2.imread(str(color), cv2.IMREAD_COLOR)
        if bgr is None:
            self.fail(f"{color.name}: unreadable image", reason="corrupt image", lost=1)
            return None
        depth = None
        depth_path = color.with_name(color.name.split(".")[0] + ".depth.png")
        if depth_path.is_file():
            mm = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED)
            if mm is None or mm.dtype != np.uint16:
                self.fail(f"{depth_path.name}: not a 16-bit depth image")
            else:
                depth = mm.astype(np.float32) / 1000.0
                depth[(mm == 0) | (mm == 65535)] = np.nan
        return CameraFrame(
            t_ns=t_ns,
            frame_id=CAMERA,
            image=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB),
            K=self.K.copy(),
            depth=depth,
            topic=CAMERA_TOPIC,
        )

    def _pose(self, color: Path, t_ns: int) -> GroundTruthPose | None:
        path = self._pose_path(color)
        if not path.is_file():
            return None
        try:
            T = np.loadtxt(path, dtype=np.float64).reshape(4, 4)
        except ValueError as exc:
            self.fail(f"{path.name}: not a 4x4 pose: {exc}", reason="corrupt pose", lost=1)
            return None
        if not np.isfinite(T).all():
            self.stats.note(f"{path.name}: pose not finite (tracking lost); left out")
            return None
        return GroundTruthPose(t_ns, WORLD, CAMERA, T, topic=POSE_TOPIC)

    def _frames(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> Iterator[LogMessage]:
        def wanted(kind: type, topic: str) -> bool:
            return (kinds is None or kind in kinds) and (topics is None or topic in topics)

        want_cam, want_pose = wanted(CameraFrame, CAMERA_TOPIC), wanted(GroundTruthPose, POSE_TOPIC)
        for i in np.argsort(self.times_ns, kind="stable"):
            color, t_ns = self.color_files[i], int(self.times_ns[i])
            if want_cam and (cam := self._camera(color, t_ns)) is not None:
                yield cam
            if want_pose and (pose := self._pose(color, t_ns)) is not None:
                yield pose
