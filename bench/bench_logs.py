"""Log writing: McapLogWriter against writing the same number of bytes to a plain file.

A realistic log: 50 LADAR sweeps of 32 x 1024 points (x, y, z, intensity, t, ring) at 10 Hz,
50 RGB images of 640 x 480 with their camera info, and 100 Hz odometry (~110 MB of messages).
The baseline writes the very bytes of the serialised messages to a plain file, one write per
message, so the ratio is the whole cost of the log format (ROS 2 encoding, CDR
serialisation, chunking, CRCs, compression, indexes) over raw file output. Both sides end
with fsync, as McapLogWriter does by default (``durable``) so that its atomic rename survives
a crash. Target: ratio <= 2 (logging at no less than half the plain-file speed) for the
default (uncompressed) writer; LZ4 and zstd are reported. A second figure leaves out fsync on
both sides: the CPU cost of encoding and chunk CRCs against one memory copy into the page
cache. Previous files are removed outside the timed region.

Run: ``python -m bench logs``.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.results import median_times_interleaved, record
from core.geometry import rot_z, se3
from logs import (
    CameraFrame,
    Compression,
    LadarScan,
    McapLogWriter,
    McapWriterConfig,
    OdometryFrame,
    open_log,
)
from logs.ros_encode import encode_frame, serialize

N_SWEEPS = 50
RINGS, COLUMNS = 32, 1024
COMMAND = "python -m bench logs"
DEFAULT = McapWriterConfig().compression


def realistic_frames(seed: int = 0) -> list:
    """50 sweeps, 50 images and 500 odometry frames over 5 s, in time order."""
    rng = np.random.default_rng(seed)
    n = RINGS * COLUMNS
    az = np.tile(np.linspace(-np.pi, np.pi, COLUMNS, endpoint=False), RINGS)
    el = np.repeat(np.linspace(-0.3, 0.3, RINGS), COLUMNS)
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    frames = []
    for k in range(N_SWEEPS):
        t_ns = k * 100_000_000
        r = rng.uniform(2, 60, n)
        xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)])
        frames.append(
            LadarScan(
                t_ns=t_ns,
                frame_id="ladar",
                points_xyz=xyz.T.astype(np.float32),
                intensity=rng.random(n).astype(np.float32),
                t_offset_ns=np.tile(np.arange(COLUMNS) * 97_656, RINGS),
                ring=np.repeat(np.arange(RINGS, dtype=np.uint16), COLUMNS),
            )
        )
        frames.append(
            CameraFrame(t_ns, "camera", rng.integers(0, 256, (480, 640, 3), dtype=np.uint8), K)
        )
        for j in range(10):
            T = se3(rot_z(0.01 * (10 * k + j)), [0.1 * (10 * k + j), 0, 0])
            frames.append(OdometryFrame(t_ns + j * 10_000_000, "odom", "base_link", T))
    frames.sort(key=lambda f: f.t_ns)
    return frames


def serialised_payloads(frames: list) -> list[bytes]:
    return [bytes(serialize(enc)) for f in frames for enc in encode_frame(f)]


def interleaved_write_times(
    writers: dict[str, Callable[[Path], None]], folder: Path, repeat: int = 5
) -> dict[str, float]:
    """Median seconds of each writer making a new file, run interleaved; removing the
    previous file (freeing its pages) happens outside the timed region for every writer."""
    samples: dict[str, list[float]] = {name: [] for name in writers}
    for r in range(repeat + 1):  # the first round warms up
        for name, write in writers.items():
            path = folder / f"{name}.out"
            path.unlink(missing_ok=True)
            t0 = time.perf_counter()
            write(path)
            if r:
                samples[name].append(time.perf_counter() - t0)
    return {name: statistics.median(v) for name, v in samples.items()}


def main() -> None:
    frames = realistic_frames()
    payloads = serialised_payloads(frames)
    total_mb = sum(len(p) for p in payloads) / 1e6

    def plain_file(durable: bool) -> Callable[[Path], None]:
        def write(path: Path) -> None:
            with open(path, "wb") as f:
                for p in payloads:
                    f.write(p)
                if durable:
                    f.flush()
                    os.fsync(f.fileno())

        return write

    def mcap(compression: Compression, durable: bool) -> Callable[[Path], None]:
        config = McapWriterConfig(compression=compression, durable=durable)

        def write(path: Path) -> None:
            with McapLogWriter(path, config) as w:
                for frame in frames:
                    w.write(frame)

        return write

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        writers = {"plain": plain_file(True)} | {c.value: mcap(c, True) for c in Compression}
        writers |= {"plain_cached": plain_file(False), "none_cached": mcap(Compression.NONE, False)}
        times = interleaved_write_times(writers, folder)
        sizes = {c.value: (folder / f"{c.value}.out").stat().st_size / 1e6 for c in Compression}
        log = folder / f"{DEFAULT.value}.out"
        n_read = sum(1 for _ in open_log(log).frames())
        assert n_read == len(frames), (n_read, len(frames))
        read_s = median_times_interleaved(
            {"read": lambda: sum(1 for _ in open_log(log).frames())}, repeat=3
        )["read"]
    print(f"payload {total_mb:.1f} MB in {len(payloads)} messages; file sizes MB: {sizes}")
    for c in Compression:
        record(
            f"logs_write_mcap_{c.value}_s",
            times[c.value],
            "s",
            baseline="the same serialised bytes written to a plain file, fsynced",
            baseline_value=times["plain"],
            target="ratio <= 2" if c is DEFAULT else f"reported (default is {DEFAULT.value})",
            command=COMMAND,
        )
    record(
        "logs_write_mcap_none_page_cache_s",
        times["none_cached"],
        "s",
        baseline="the same bytes to a plain file, neither fsynced (memory copies only)",
        baseline_value=times["plain_cached"],
        target="reported: encoding + chunk CRC against one memory copy",
        command=COMMAND,
    )
    record(
        f"logs_read_mcap_{DEFAULT.value}_MBps",
        total_mb / read_s,
        "MB/s",
        target="reported",
        command=COMMAND,
    )


if __name__ == "__main__":
    main()
