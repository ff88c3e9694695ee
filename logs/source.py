"""Log sources: one interface over every recorded-log format the engine reads.

``open_log(path)`` looks at what ``path`` is and returns the matching :class:`LogSource`:

* an ``.mcap`` file (ours or any ROS 2 MCAP with ``cdr`` messages): :mod:`logs.mcap_log`;
* a ROS 1 ``.bag`` file or a ROS 2 bag folder (``metadata.yaml``): :mod:`logs.rosbag_log`;
* a KITTI Velodyne folder of ``NNNNNN.bin``: :mod:`logs.kitti_log`;
* an RGB-D folder in the 7-Scenes layout: :mod:`logs.rgbd_log`;
* an Argoverse 2 sensor log folder: :mod:`logs.av2_log`.

Every source yields the frames of :mod:`logs.types` in time order, reports what it had to
skip in ``stats`` (:class:`~logs.types.ReadStats`) and raises
:class:`~logs.types.LogError` (naming the file and the problem) for input it cannot read.
In the 4D/RCS reference model (reference 001), "the level 1 SP typically receives data from
the physical sensors" (section 4.5): a log source stands in for those sensors, and each frame
it yields is one sample of a sensor's signal, which section 4.4.10 counts as an event at the
input of the servo level. Hence every frame carries its own time (``t_ns``), and sources
report times that run backwards rather than reorder them silently.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.geometry import NS_PER_S
from logs.types import LogError, LogMessage, ReadStats, TransformFrame

SUPPORTED_FORMATS = (
    "MCAP file with ROS 2 messages (*.mcap)",
    "ROS 1 bag (*.bag)",
    "ROS 2 bag folder (metadata.yaml with .db3 or .mcap files)",
    "KITTI Velodyne folder (NNNNNN.bin, N x 4 float32; optional .label)",
    "RGB-D folder in the 7-Scenes layout (frame-XXXXXX.color.jpg/.depth.png/.pose.txt)",
    "Argoverse 2 sensor log folder (sensors/lidar/<t_ns>.feather)",
)


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """One topic of a log: its message type, message count, first/last time (ns) and rate (Hz)."""

    name: str
    msgtype: str
    count: int
    first_t_ns: int
    last_t_ns: int

    @property
    def rate_hz(self) -> float:
        """Mean message rate, (count - 1) / duration; 0 for fewer than two messages."""
        span = self.last_t_ns - self.first_t_ns
        return (self.count - 1) * NS_PER_S / span if self.count > 1 and span > 0 else 0.0


@dataclass(frozen=True, slots=True)
class LogInfo:
    """What a log holds: format, topics, and its time span (ns)."""

    path: Path
    format_name: str
    topics: tuple[TopicInfo, ...]
    notes: tuple[str, ...] = ()

    @property
    def first_t_ns(self) -> int:
        return min((t.first_t_ns for t in self.topics if t.count), default=0)

    @property
    def last_t_ns(self) -> int:
        return max((t.last_t_ns for t in self.topics if t.count), default=0)

    @property
    def duration_s(self) -> float:
        return (self.last_t_ns - self.first_t_ns) / NS_PER_S

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self.topics)

    def topic(self, name: str) -> TopicInfo:
        """The topic called ``name``; LogError naming the topics there are."""
        for t in self.topics:
            if t.name == name:
                return t
        raise LogError(f"{self.path}: no topic {name!r} (topics: {[t.name for t in self.topics]})")


def topic_info(name: str, msgtype: str, times_ns: Iterable[int]) -> TopicInfo:
    """A :class:`TopicInfo` from the message times (ns) of one topic."""
    t = np.fromiter(times_ns, dtype=np.int64)
    if t.size == 0:
        return TopicInfo(name, msgtype, 0, 0, 0)
    return TopicInfo(name, msgtype, int(t.size), int(t.min()), int(t.max()))


def format_log_info(info: LogInfo) -> str:
    """A human-readable table of ``info`` (what ``wm log-info`` prints)."""
    lines = [
        f"log:       {info.path}",
        f"format:    {info.format_name}",
        f"messages:  {info.message_count} on {len(info.topics)} topics",
        f"time:      {info.first_t_ns} .. {info.last_t_ns} ns ({info.duration_s:.3f} s)",
    ]
    lines += [f"note:      {n}" for n in info.notes]
    width = max((len(t.name) for t in info.topics), default=5)
    tw = max((len(t.msgtype) for t in info.topics), default=4)
    lines.append(f"{'topic':<{width}}  {'type':<{tw}}  {'count':>7}  {'rate Hz':>8}")
    for t in info.topics:
        lines.append(f"{t.name:<{width}}  {t.msgtype:<{tw}}  {t.count:>7}  {t.rate_hz:>8.2f}")
    return "\n".join(lines)


class LogSource(ABC):
    """A recorded log, read as time-ordered sensor frames.

    Subclasses implement :meth:`_frames` (frames in time order, filtered as asked) and
    :meth:`_topics`; everything else is shared.
    """

    format_name: str = "log"

    def __init__(self, path: str | Path, *, skip_corrupt: bool = False) -> None:
        self.path = Path(path)
        self.skip_corrupt = skip_corrupt
        self.stats = ReadStats()
        self._info: LogInfo | None = None
        self._static: dict[tuple[str, str], np.ndarray] | None = None
        self._failed: set[str] = set()  # corrupt records counted (each problem names its place)
        #: the defects skipped (skip_corrupt=True), each once, in the order met
        self.defects: list[str] = []

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    # ------------------------------------------------------------------ for subclasses
    @classmethod
    def accepts(cls, path: Path) -> bool:
        """Whether ``path`` looks like a log of this format (cheap: names and magic bytes)."""
        return False

    @abstractmethod
    def _frames(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> Iterator[LogMessage]:
        """Frames in time order, of the given kinds and frame topics (None: all)."""

    @abstractmethod
    def _topics(self) -> list[TopicInfo]:
        """The log's topics as stored (for ROS logs: the message topics, not frame topics)."""

    def _notes(self) -> list[str]:
        return []

    def fail(self, problem: str, *, reason: str = "corrupt record", lost: int = 0) -> None:
        """A corrupt record: raise LogError, or count and note it once when skipping corrupt
        input: one more in ``stats.skipped_records`` and ``lost`` more messages left out under
        ``stats.lost[reason]``."""
        if not self.skip_corrupt:
            raise LogError(f"{self.path}: {problem} (open with skip_corrupt=True to skip it)")
        if problem in self._failed:  # met again on a later pass (info() and frames() both read)
            return
        self._failed.add(problem)
        self.defects.append(problem)
        self.stats.skipped_records += 1
        self.stats.lost[reason] = self.stats.lost.get(reason, 0) + lost
        self.stats.note(f"{self.path.name}: skipped: {problem}")

    # ------------------------------------------------------------------ the interface
    def frames(
        self,
        kinds: Iterable[type] | type | None = None,
        topics: Iterable[str] | str | None = None,
    ) -> Iterator[LogMessage]:
        """Time-ordered frames, optionally only of some kinds (frame classes) and topics.

        Times that go backwards on a topic (per child frame for transforms) are counted in
        ``stats.backwards_timestamps`` and noted; the frames are still yielded.
        """
        if isinstance(kinds, type):
            kinds = (kinds,)
        if isinstance(topics, str):
            topics = (topics,)
        kinds_t = tuple(kinds) if kinds is not None else None
        topics_f = frozenset(topics) if topics is not None else None
        last_t: dict[tuple[str, str], int] = {}
        for frame in self._frames(kinds_t, topics_f):
            key = (frame.topic, getattr(frame, "child_frame_id", ""))
            prev = last_t.get(key)
            if prev is not None and frame.t_ns < prev:
                self.stats.backwards_timestamps += 1
                self.stats.note(
                    f"{self.path.name}: {frame.topic} {key[1]} time went back "
                    f"{prev - frame.t_ns} ns (from {prev} to {frame.t_ns})"
                )
            last_t[key] = frame.t_ns
            yield frame

    def info(self) -> LogInfo:
        """Format, topics (type, count, first/last t_ns, rate) and notes; computed once.

        Counts are of stored messages (for ROS logs, by log time). Reading the index counts
        corrupt records in ``stats`` like reading frames does (each pass adds its own)."""
        if self._info is None:
            topics = tuple(sorted(self._topics(), key=lambda t: t.name))
            self._info = LogInfo(self.path, self.format_name, topics, tuple(self._notes()))
        return self._info

    @property
    def static_transforms(self) -> dict[tuple[str, str], np.ndarray]:
        """``{(parent, child): T_parent_child}`` from the static transforms (latest wins)."""
        if self._static is None:
            self._static = {
                (f.parent_frame_id, f.child_frame_id): f.T_parent_child
                for f in self._frames((TransformFrame,), None)
                if isinstance(f, TransformFrame) and f.static
            }
        return self._static

    def attachments(self) -> dict[str, bytes]:
        """Attached files by name (empty where the format has none)."""
        return {}

    def metadata(self) -> dict[str, dict[str, str]]:
        """Metadata records by name (empty where the format has none)."""
        return {}

    def damaged_extras(self) -> dict[str, str]:
        """Attachments and metadata left out of :meth:`attachments` and :meth:`metadata` as
        damaged (what -> why); never fatal, since they only serve scoring."""
        return {}

    def frame_topics(self) -> set[str]:
        """The topics of the frames this log yields (a camera's ROS topics share one)."""
        return {t.name for t in self.info().topics}

    def require_topics(self, names: Iterable[str]) -> None:
        """Raise LogError naming every topic of ``names`` the log lacks (stored or frame topics)."""
        have = {t.name for t in self.info().topics} | self.frame_topics()
        missing = [n for n in names if n not in have]
        if missing:
            raise LogError(f"{self.path}: missing topics {missing} (topics there: {sorted(have)})")


def open_log(path: str | Path, *, skip_corrupt: bool = False) -> LogSource:
    """The :class:`LogSource` for ``path``, chosen by what the path is.

    Raises LogError when the path does not exist or is no supported log, listing the formats.
    """
    p = Path(path)
    if not p.exists():
        raise LogError(f"{p}: no such file or folder")
    source_type = _source_type(p)
    if source_type is None:
        formats = "\n  ".join(SUPPORTED_FORMATS)
        raise LogError(f"{p}: not a supported log. Supported formats:\n  {formats}")
    return source_type(p, skip_corrupt=skip_corrupt)


def _source_type(p: Path) -> type[LogSource] | None:
    from logs.av2_log import Av2LogSource
    from logs.kitti_log import KittiLogSource
    from logs.mcap_log import McapLogSource
    from logs.rgbd_log import RgbdLogSource
    from logs.rosbag_log import RosbagLogSource

    for source_type in (
        McapLogSource,
        RosbagLogSource,
        KittiLogSource,
        RgbdLogSource,
        Av2LogSource,
    ):
        if source_type.accepts(p):
            return source_type
    return None
