"""ROS 1 ``.bag`` files and ROS 2 bag folders, read through ``rosbags`` (AnyReader).

Messages come in log-time order across topics and become frames through the same
:class:`~logs.ros_decode.FrameAssembler` as MCAP logs (ROS 1 messages are decoded by
rosbags into the same field layout). The bag formats have no attachments or metadata
records, so those are empty.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from logs.ros_decode import FrameAssembler
from logs.ros_types import frame_topic, frame_topics_of, role_of
from logs.source import LogSource, TopicInfo, topic_info
from logs.types import LogError, LogMessage


class RosbagLogSource(LogSource):
    """A ROS 1 bag file or a ROS 2 bag folder."""

    format_name = "ROS bag (rosbags)"

    @classmethod
    def accepts(cls, path: Path) -> bool:
        if path.is_file():
            return path.suffix == ".bag"
        return (path / "metadata.yaml").is_file()

    def __init__(self, path: str | Path, *, skip_corrupt: bool = False) -> None:
        super().__init__(path, skip_corrupt=skip_corrupt)
        self.format_name = "ROS 1 bag" if self.path.is_file() else "ROS 2 bag folder"
        with self._reader() as reader:  # fail early on a bag that cannot be opened
            self._connections = [(c.topic, c.msgtype, c.msgcount) for c in reader.connections]

    def _reader(self) -> Any:
        from rosbags.highlevel import AnyReader

        try:
            return _Opened(AnyReader([self.path]), self.path)
        except Exception as exc:  # rosbags raises its own error per format
            raise LogError(f"{self.path}: cannot open as a ROS bag: {exc}") from exc

    def _frames(
        self, kinds: tuple[type, ...] | None, topics: frozenset[str] | None
    ) -> Iterator[LogMessage]:
        assembler = FrameAssembler(self.stats, kinds, on_error=self.fail)
        with self._reader() as reader:
            wanted = {}
            for c in reader.connections:
                role = role_of(c.topic, c.msgtype)
                if assembler.wants(role) and (
                    topics is None or frame_topic(c.topic, role) in topics
                ):
                    wanted[c.id] = (c, role)
            if not wanted:
                return
            conns = [c for c, _ in wanted.values()]
            messages = reader.messages(connections=conns)
            while True:
                try:
                    item = next(messages)
                except StopIteration:
                    break
                except Exception as exc:
                    self.fail(f"cannot read past a damaged record: {exc}")
                    return
                conn, t_ns, raw = item
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except Exception as exc:
                    self.fail(
                        f"{conn.topic} message at {t_ns} ns is undecodable: {exc}",
                        reason="undecodable message",
                        lost=1,
                    )
                    continue
                yield from assembler.push(conn.topic, wanted[conn.id][1], msg, t_ns)
        yield from assembler.flush()

    def frame_topics(self) -> set[str]:
        return frame_topics_of((t.name, t.msgtype) for t in self.info().topics)

    def _topics(self) -> list[TopicInfo]:
        times: dict[tuple[str, str], list[int]] = {(t, m): [] for t, m, _ in self._connections}
        with self._reader() as reader:
            try:
                for conn, t_ns, _ in reader.messages():
                    times[(conn.topic, conn.msgtype)].append(t_ns)
            except Exception as exc:  # info() runs once: its problems count in stats
                self.fail(f"cannot read past a damaged record: {exc}")
        return [topic_info(topic, msgtype, t) for (topic, msgtype), t in times.items()]


class _Opened:
    """Context manager that opens an AnyReader and turns its failures into LogError."""

    def __init__(self, reader: Any, path: Path) -> None:
        self.reader = reader
        self.path = path

    def __enter__(self) -> Any:
        try:
            self.reader.open()
        except Exception as exc:
            raise LogError(f"{self.path}: cannot open as a ROS bag: {exc}") from exc
        return self.reader

    def __exit__(self, *exc: object) -> None:
        self.reader.close()
