"""KITTI Velodyne folders: ``NNNNNN.bin`` scans (N x 4 float32: x, y, z, reflectance).

The path may be the folder of ``.bin`` files, a sequence folder holding ``velodyne/``, or the
dataset's root holding ``sequences/NN/velodyne/`` for exactly one sequence (with several, the
error names them: pass the one to read).
KITTI scans carry no times: when the sequence folder has ``times.txt`` (seconds, one line
per scan) those are used, otherwise times are synthesised at 10 Hz (the HDL-64's spin rate,
scan k at k * 100 ms) and :meth:`LogSource.info` says so. Points have no per-point times
(``t_offset_ns`` zero) and no rings. SemanticKITTI ``NNNNNN.label`` files (uint32 per point:
low 16 bits class, high 16 bits instance), beside the scans or in ``../labels/``, are ground
truth: :meth:`KittiLogSource.labels` returns them aligned with the yielded points.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.geometry import LADAR, NS_PER_S
from logs.source import LogSource, TopicInfo
from logs.types import LadarScan, LogError, LogMessage

SCAN_PERIOD_NS = 100_000_000  # 10 Hz
TOPIC = "/ladar/points"
_SCAN_NAME = re.compile(r"^\d{6}\.bin$")


def _scan_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.glob("*.bin") if _SCAN_NAME.match(p.name))


def _sequences(root: Path) -> list[Path]:
    """Sequence folders under a dataset root (``sequences/NN`` with scans in ``velodyne/``)."""
    return sorted(q for q in root.glob("sequences/*") if _scan_files(q / "velodyne"))


def scan_folder(path: Path) -> Path | None:
    """The folder holding the scans of ``path`` (see the module docstring), or None."""
    for folder in (path, path / "velodyne"):
        if _scan_files(folder):
            return folder
    seqs = _sequences(path)
    return seqs[0] / "velodyne" if len(seqs) == 1 else None


class KittiLogSource(LogSource):
    """A folder of KITTI Velodyne scans (yields :class:`LadarScan` on ``/ladar/points``)."""

    format_name = "KITTI Velodyne .bin folder"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        if not path.is_dir():
            return False
        return scan_folder(path) is not None or len(_sequences(path)) > 1

    def __init__(self, path: str | Path, *, skip_corrupt: bool = False) -> None:
        super().__init__(path, skip_corrupt=skip_corrupt)
        folder = scan_folder(self.path)
        if folder is None:
            names = ", ".join(q.name for q in _sequences(self.path)) or "none"
            raise LogError(
                f"{self.path}: a KITTI root with several sequences ({names}); pass one of "
                f"them, e.g. {self.path / 'sequences' / names.split(', ')[0]}"
            )
        self.scan_files = _scan_files(folder)
        if not self.scan_files:
            raise LogError(f"{self.path}: no NNNNNN.bin scans")
        self.numbers = [int(p.stem) for p in self.scan_files]
        self.times_ns, self._synthesised = self._times(folder.parent / "times.txt")

    def _times(self, times_txt: Path) -> tuple[np.ndarray, bool]:
        numbers = np.array(self.numbers, dtype=np.int64)
        if times_txt.is_file():
            seconds = np.loadtxt(times_txt, dtype=np.float64, ndmin=1)
            if seconds.size > numbers.max():
                return np.round(seconds[numbers] * NS_PER_S).astype(np.int64), False
        return numbers * SCAN_PERIOD_NS, True

    def _notes(self) -> list[str]:
        if self._synthesised:
            return ["times synthesised at 10 Hz (scan number x 100 ms): no times.txt"]
        return []

    def _topics(self) -> list[TopicInfo]:
        t = self.times_ns
        return [TopicInfo(TOPIC, "LadarScan", len(t), int(t.min()), int(t.max()))]

    def _load(self, i: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(N, 4) float32 scan i and its finite-point mask, or None when skipped as corrupt."""
        path = self.scan_files[i]
        size = path.stat().st_size
        if size % 16:
            self.fail(
                f"{path.name}: {size} bytes is not a whole number of 16-byte points",
                reason="corrupt scan",
                lost=1,
            )
            return None
        xyzi = np.fromfile(path, dtype="<f4").reshape(-1, 4)
        return xyzi, np.isfinite(xyzi[:, :3]).all(axis=1)

    def _frames(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> Iterator[LogMessage]:
        if (kinds is not None and LadarScan not in kinds) or (
            topics is not None and TOPIC not in topics
        ):
            return
        for i in np.argsort(self.times_ns, kind="stable"):
            loaded = self._load(int(i))
            if loaded is None:
                continue
            xyzi, finite = loaded
            n_bad = int(finite.size - finite.sum())
            if n_bad:
                self.stats.dropped_nonfinite_points += n_bad
                xyzi = xyzi[finite]
            yield LadarScan(
                t_ns=int(self.times_ns[i]),
                frame_id=LADAR,
                points_xyz=np.ascontiguousarray(xyzi[:, :3]),
                intensity=np.ascontiguousarray(xyzi[:, 3]),
                t_offset_ns=np.zeros(xyzi.shape[0], dtype=np.int64),
                ring=None,
                topic=TOPIC,
            )

    def labels(self, index: int) -> np.ndarray | None:
        """SemanticKITTI labels (M,) uint32 of scan ``index`` aligned with its yielded points.

        None when the scan has no ``.label`` file. Low 16 bits: class; high 16 bits: instance.
        """
        scan = self.scan_files[index]
        beside, in_labels = scan.with_suffix(".label"), scan.parents[1] / "labels" / scan.name
        for path in (beside, in_labels.with_suffix(".label")):
            if path.is_file():
                labels = np.fromfile(path, dtype="<u4")
                loaded = self._load(index)
                if loaded is None or labels.size != loaded[0].shape[0]:
                    n = None if loaded is None else loaded[0].shape[0]
                    raise LogError(f"{path}: {labels.size} labels for a scan of {n} points")
                return labels[loaded[1]]
        return None
