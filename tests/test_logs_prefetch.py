"""Frames decoded ahead in a child process are exactly the frames read directly: same kinds,
times, arrays and order; read statistics come back; errors surface where the frames are
read; leaving early stops the child."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_logs_mcap import assert_same_frame, make_frames

from logs import LogError, McapLogWriter, open_log
from logs.prefetch import FramePrefetcher, PrefetchError


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("prefetch") / "log.mcap"
    with McapLogWriter(path) as w:
        for seed in range(3):  # repeated times go backwards: counted in stats
            for f in make_frames(seed):
                w.write(f)
    return path


@pytest.mark.parametrize("batch_frames", [1, 3, 1000])
def test_prefetched_frames_are_the_frames(log, batch_frames) -> None:
    direct_source = open_log(log)
    direct = list(direct_source.frames())
    source = open_log(log)
    with FramePrefetcher(source, batch_frames) as pf:
        ahead = list(pf)
    assert len(ahead) == len(direct) > 10
    for a, b in zip(direct, ahead, strict=True):
        assert_same_frame(a, b)
    assert source.stats.backwards_timestamps == direct_source.stats.backwards_timestamps > 0
    assert source.stats.messages == direct_source.stats.messages
    assert pf.decode_cpu_s > 0


def test_frame_filters_pass_through(log) -> None:
    from logs import LadarScan

    want = [f.t_ns for f in open_log(log).frames(kinds=LadarScan)]
    with FramePrefetcher(open_log(log), kinds=LadarScan) as pf:
        got = [f for f in pf]
    assert [f.t_ns for f in got] == want and all(isinstance(f, LadarScan) for f in got)


def test_a_corrupt_log_raises_the_readers_error(log, tmp_path) -> None:
    bad = tmp_path / "bad.mcap"
    data = bytearray(log.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = b"\xff" * 64
    bad.write_bytes(bytes(data))
    with pytest.raises(LogError) as direct:
        list(open_log(bad).frames())
    with FramePrefetcher(open_log(bad)) as pf, pytest.raises(LogError) as ahead:
        list(pf)
    assert str(ahead.value) == str(direct.value)


def test_leaving_early_stops_the_child(log) -> None:
    pf = FramePrefetcher(open_log(log), batch_frames=1)
    first = next(iter(pf))
    assert first.t_ns == next(open_log(log).frames()).t_ns
    pf.close()
    assert pf._proc.poll() is not None  # the child has ended


def test_a_child_that_dies_is_noted_and_the_rest_read_here(log) -> None:
    import os
    import signal

    direct = list(open_log(log).frames())
    source = open_log(log)
    with FramePrefetcher(source, batch_frames=1) as pf:
        it = iter(pf)
        got = [next(it)]
        os.kill(pf._proc.pid, signal.SIGKILL)
        got += list(it)
    assert len(got) == len(direct)
    for a, b in zip(direct, got, strict=True):
        assert_same_frame(a, b)
    assert any("decoding process stopped" in m for m in source.stats.messages)


def test_bad_batch_sizes_are_refused(log) -> None:
    with pytest.raises(PrefetchError, match="batch_frames 0"):
        FramePrefetcher(open_log(log), batch_frames=0)
    with pytest.raises(PrefetchError, match="ahead_batches 0"):
        FramePrefetcher(open_log(log), ahead_batches=0)


def test_the_child_runs_ahead_while_nothing_reads(log) -> None:
    """The pipe is drained into the queue, so the child decodes the whole log (far more than a
    pipe holds) and ends while this process reads nothing."""
    import time

    direct = list(open_log(log).frames())
    assert log.stat().st_size > 2 * 65536  # more than a full pipe (64 KiB)
    with FramePrefetcher(open_log(log), batch_frames=1, ahead_batches=len(direct) + 1) as pf:
        deadline = time.monotonic() + 30
        while pf._proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pf._proc.returncode == 0  # finished on its own, nothing read yet
        got = list(pf)
    assert [f.t_ns for f in got] == [f.t_ns for f in direct]
