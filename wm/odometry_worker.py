"""LADAR odometry (sp.odometry) in a child process, so that registering sweep k overlaps the
maps, SP and predictions of sweep k-1 (KISS-ICP's registration holds the interpreter lock and
runs on one core; the node's other stages need the other).

Requests go through one queue in the order the node makes them (wheel-odometry frames, then
the sweep they cover), so the child sees exactly what a serial :class:`~sp.odometry.
LadarOdometry` would; replies (:class:`OdometryReply`) come back in sweep order.

One bad request never ends the process: a wheel-odometry frame it cannot use, or a sweep whose
registration fails, comes back as a skip reason with the next reply, and after a failed sweep
the odometry restarts from its last accepted pose (:meth:`~sp.odometry.LadarOdometry.
update_or_skip`). The process never outlives the node's: the kernel kills it when the node's
process dies (:func:`core.process.die_with_parent`, Linux), a thread watching the parent's pid
ends it elsewhere, and the node stops waiting as soon as the process is gone.
"""

from __future__ import annotations

import contextlib
import gc
import multiprocessing as mp
import os
import queue
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from core.errors import EngineError
from core.process import die_with_parent, exit_with_parent
from logs.types import LadarScan, OdometryFrame

if TYPE_CHECKING:
    from sp.odometry import OdometryConfig

RESULT_TIMEOUT_S = 120.0
_POLL_S = 0.2  # how often a node waiting for a reply checks that the process still runs
_NO_INTENSITY = np.zeros(0, dtype=np.float32)  # registration never reads intensities


class OdometryWorkerError(EngineError, RuntimeError):
    """The odometry process failed or stopped answering (names the sweep and the cause)."""


@dataclass
class OdometryReply:
    """The answer to one submitted sweep: its estimate (None when the sweep was skipped), the
    odometry process's CPU seconds on it, and the reasons ("reason: detail", as the node's
    ``stats.skipped`` keys them) of each request skipped since the last reply, the wheel
    frames before this sweep first."""

    estimate: Any | None
    cpu_s: float = 0.0
    skipped: list[str] = field(default_factory=list)


def _serve(
    requests: Any, results: Any, T_body_sensor, T_world_body0, parent: int, config: Any = None
) -> None:
    """The child's loop: feed wheel odometry, register sweeps, answer each sweep in order."""
    die_with_parent(parent)
    exit_with_parent(parent, "wm-odometry-watch")  # where prctl is not there (or not allowed)
    from sp.odometry import LadarOdometry, OdometryConfig

    # one registration thread unless the configuration names a number (0, as many as
    # cores, is one here): this process has the core the node's process leaves, and a
    # second thread would take turns with the node on its own core
    config = config or OdometryConfig()
    if config.max_threads == 0:
        config = replace(config, max_threads=1)
    odo = LadarOdometry(config, T_body_sensor=T_body_sensor, T_world_body0=T_world_body0)
    skipped: list[str] = []
    while True:
        kind, item = requests.get()
        if kind == "stop":
            return
        if kind == "wheel":
            try:
                odo.add_wheel_odometry(item)
            except Exception as e:  # the node screens wheel frames; one that slips by is told
                skipped.append(f"bad odometry pose: t_ns={item.t_ns}: {type(e).__name__}: {e}")
            continue
        cpu = time.process_time()  # KISS-ICP's threads included
        est, why = odo.update_or_skip(item)
        if why:
            skipped.append(why)
        results.put(OdometryReply(est, time.process_time() - cpu, skipped))
        skipped = []


class OdometryWorker:
    """The odometry process: :meth:`add_wheel_odometry`, :meth:`submit` a sweep, then take its
    :meth:`result` (estimates in submission order)."""

    def __init__(
        self,
        T_body_sensor: np.ndarray | None,
        T_world_body0: np.ndarray | None,
        config: OdometryConfig | None = None,
    ):
        # fork: the child needs nothing the parent holds, and a spawned child would re-run
        # the caller's main script (scripts without a __main__ guard would loop)
        ctx = mp.get_context("fork")
        self._requests = ctx.Queue()
        self._results = ctx.Queue()
        self._proc = ctx.Process(
            target=_serve,
            args=(self._requests, self._results, T_body_sensor, T_world_body0, os.getpid(), config),
            daemon=True,
            name="wm-odometry",
        )
        # the child must never finalise the parent's objects (a DuckDB connection, numba or
        # BLAS state whose threads it lacks): what exists now is frozen out of its collector
        gc.collect()
        gc.freeze()
        try:
            self._proc.start()
        finally:
            gc.unfreeze()
        self._waiting: list[int] = []

    def add_wheel_odometry(self, frame: OdometryFrame) -> None:
        self._requests.put(("wheel", frame))

    def submit(self, scan: LadarScan) -> None:
        # only what registration reads (the pickled copy is made in this process): offsets of
        # a sweep's points fit int32 (0 to 2.1 s, differences too), half the bytes to send
        off = np.asarray(scan.t_offset_ns)
        if off.size and off.dtype.itemsize > 4 and 0 <= off.min() and off.max() < 2**31:
            off = off.astype(np.int32)
        slim = LadarScan(scan.t_ns, scan.frame_id, scan.points_xyz, _NO_INTENSITY, off)
        self._requests.put(("scan", slim))
        self._waiting.append(int(scan.t_ns))

    def result(self) -> OdometryReply:
        """The reply for the oldest submitted sweep (waits for it, at most
        ``RESULT_TIMEOUT_S``); raises :class:`OdometryWorkerError` as soon as the process is
        found gone instead of waiting the timeout out."""
        if not self._waiting:
            raise OdometryWorkerError("asked for an odometry result with no sweep submitted")
        t_ns = self._waiting.pop(0)
        deadline = time.monotonic() + RESULT_TIMEOUT_S
        while True:
            try:
                return self._results.get(timeout=_POLL_S)
            except queue.Empty:
                pass
            if not self._proc.is_alive():
                with contextlib.suppress(queue.Empty):  # its last words may be in the pipe
                    return self._results.get(timeout=_POLL_S)
                why = f"the odometry process ended (exit code {self._proc.exitcode})"
            elif time.monotonic() > deadline:
                why = f"none within {RESULT_TIMEOUT_S:g} s (odometry process running)"
            else:
                continue
            raise OdometryWorkerError(f"no odometry for the sweep at t_ns={t_ns}: {why}")

    def close(self) -> None:
        """Stop the process; never blocks on requests it will not read (a process that died
        or is stopped mid-way leaves them queued, and their feeder thread must not be
        waited for at exit)."""
        if self._proc.is_alive():
            self._requests.put(("stop", None))
            self._proc.join(timeout=5)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(timeout=5)
        self._requests.cancel_join_thread()
        self._results.cancel_join_thread()
