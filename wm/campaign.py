"""A damaged-log and kill campaign: one bad input never breaks a run (the reliability issue).

``python -m wm.campaign --logs N --kills K --out results/``

(a) ``N`` damaged copies of a small simulated log (truncation, bit flips in chunk data,
zeroed byte ranges, duplicated chunks, wrong magic, absurd record lengths; seeded), each
through ``wm log-info --check`` and ``wm run`` (every other one with ``--skip-corrupt``) in a
subprocess with a time limit and a bound on its RSS. Each command's outcome is one of
``OUTCOMES``: a clean error (exit 2, no traceback), a completed run (exit 0), a traceback, a
hang (the time limit), a memory blow-up (the RSS bound, or MemoryError) or ``other``.

(b) ``K`` SIGKILLs of ``wm run`` at random moments on a ~5 s log, each followed by
``wm check KD`` (exit 0: sound) and, 2 s later, a scan of /proc for orphans: children of the
killed run still running, or any process whose command line names its KD. The loss: the run
prints a line at each KD flush (``KD flushed to t_ns=...``, every second of log time); the
killed KD must hold the self state of the last flush it reported (``lost_flushed`` counts the
KDs that do not), and the log time between reported flushes bounds what a kill loses
(``max_flush_gap_s``).

Counts per outcome go to ``--out`` as one JSON file per figure (bench.results.record's
format) and are printed as a table. Linux only (/proc).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import re
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

from mcap.opcode import Opcode

from core.errors import EngineError

REPO = Path(__file__).resolve().parents[1]
OUTCOMES = ("error", "completed", "traceback", "hang", "memory", "other")
DAMAGES = ("truncate", "bitflip", "zero", "duplicate", "magic", "length")


class CampaignError(EngineError):
    """The campaign cannot run as asked (no /proc, a base log that cannot be made)."""


# --- MCAP records by position (shared with tests/test_logs_corrupt.py) ----------------------


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, total length in bytes) of each top-level record of an MCAP file."""
    out, pos = [], 8
    while pos + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        out.append((pos, opcode, 9 + length))
        if opcode == Opcode.FOOTER:
            break
        pos += 9 + length
    return out


def chunks(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, length in bytes, messages) of each chunk: messages from its message indexes."""
    out: list[list[int]] = []
    for offset, opcode, length in records(data):
        if opcode == Opcode.CHUNK:
            out.append([offset, length, 0])
        elif opcode == Opcode.MESSAGE_INDEX and out:
            out[-1][2] += struct.unpack_from("<I", data, offset + 9 + 2)[0] // 16
    return [(o, n, m) for o, n, m in out]


def duplicate_chunk(d: bytearray, k: int, at_end: bool = False) -> tuple[bytearray, int, int]:
    """Chunk ``k`` again, right after it (or after the last chunk): (bytes, offset of the
    copy, messages in it)."""
    offset, length, n = chunks(bytes(d))[k]
    at = offset + length
    if at_end:
        at = next(o for o, op, _ in records(bytes(d)) if op == Opcode.DATA_END)
    d[at:at] = d[offset : offset + length]
    return d, at, n


# --- damage -----------------------------------------------------------------------------------


def damage(data: bytes, kind: str, rng: random.Random) -> tuple[bytes, str]:
    """A damaged copy of an MCAP file's bytes and a description of the damage."""
    d = bytearray(data)
    ch = chunks(data)
    if kind == "truncate":
        cut = rng.randrange(8, len(d))
        return bytes(d[:cut]), f"truncated at byte {cut} of {len(d)}"
    if kind == "bitflip":
        offset, length, _ = rng.choice(ch)
        at = [rng.randrange(offset + 9, offset + length) for _ in range(rng.randint(1, 16))]
        for i in at:
            d[i] ^= 1 << rng.randrange(8)
        return bytes(d), f"{len(at)} bits flipped in the chunk at byte {offset}"
    if kind == "zero":
        start = rng.randrange(8, len(d))
        n = rng.choice([8, 64, 1024, 65536])
        d[start : start + n] = bytes(len(d[start : start + n]))
        return bytes(d), f"{n} bytes zeroed from byte {start}"
    if kind == "duplicate":
        k, at_end = rng.randrange(len(ch)), rng.random() < 0.5
        d, at, _ = duplicate_chunk(d, k, at_end)
        return bytes(d), f"chunk {k} duplicated at byte {at}"
    if kind == "magic":
        at = rng.choice([0, 3, len(d) - 8, len(d) - 1])
        d[at] ^= 0xFF
        return bytes(d), f"magic byte {at} flipped"
    if kind == "length":
        offset, opcode, _ = rng.choice(records(data))
        value = rng.choice([2**31, 2**40, 2**63 - 1, 2**64 - 1, rng.randrange(2**20, 2**34)])
        field_at = offset + 1 if rng.random() < 0.5 or opcode != Opcode.CHUNK else offset + 25
        struct.pack_into("<Q", d, field_at, value)
        what = "record length" if field_at == offset + 1 else "chunk uncompressed size"
        return bytes(d), f"{what} of the record at byte {offset} (opcode {opcode}) set to {value}"
    raise CampaignError(f"unknown damage {kind!r}; one of {', '.join(DAMAGES)}")


# --- running a command and classifying it ----------------------------------------------------


@dataclass
class Outcome:
    """One command of the campaign and what came of it."""

    command: list[str]
    damage: str
    outcome: str
    returncode: int | None
    wall_s: float
    peak_rss_mb: float
    stderr_head: list[str] = field(default_factory=list)


def _tree(pid: int) -> set[int]:
    """``pid`` and every process below it (/proc/PID/task/*/children)."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        out.add(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [
                    int(c) for c in (task / "children").read_text().split() if int(c) not in out
                ]
            except OSError:
                pass
    return out


def _rss_mb(pids: set[int]) -> float:
    """Resident memory of the processes, summed, MiB (VmRSS in /proc/PID/status)."""
    total = 0
    for p in pids:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except (OSError, ValueError):
            pass
    return total / 1024.0


def _kill_tree(pid: int) -> None:
    for p in _tree(pid):
        try:
            os.kill(p, signal.SIGKILL)
        except OSError:
            pass


def classify(returncode: int | None, stderr: str, hung: bool, blew_up: bool) -> str:
    """One of ``OUTCOMES`` for a finished (or stopped) command."""
    if blew_up or "MemoryError" in stderr or "bad_alloc" in stderr:
        return "memory"
    if hung:
        return "hang"
    if "Traceback" in stderr:
        return "traceback"
    if returncode == 0:
        return "completed"
    if returncode == 2:
        return "error"
    return "other"


def run_bounded(cmd: list[str], damage: str, timeout_s: float, max_rss_mb: float) -> Outcome:
    """Run ``cmd`` (from the repository, stdout dropped) with a time limit and an RSS bound
    over its process tree, polled every 0.1 s; either stops it (and its children)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    t0 = time.monotonic()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=err)
        peak, hung, blew_up = 0.0, False, False
        while proc.poll() is None:
            peak = max(peak, _rss_mb(_tree(proc.pid)))
            hung = time.monotonic() - t0 > timeout_s
            blew_up = peak > max_rss_mb
            if hung or blew_up:
                _kill_tree(proc.pid)
                proc.wait()
                break
            time.sleep(0.1)
        err.seek(0)
        stderr = err.read().decode(errors="replace")
    lines = [line for line in stderr.splitlines() if line.strip()]
    head = lines[:3] + (lines[-3:] if "Traceback" in stderr and len(lines) > 3 else [])
    return Outcome(cmd, damage, classify(proc.returncode, stderr, hung, blew_up),
                   proc.returncode, time.monotonic() - t0, peak, head)  # fmt: skip


def _wm(*args: str) -> list[str]:
    return [sys.executable, "-m", "wm.cli", *args]


# --- (a) damaged logs -------------------------------------------------------------------------


def damaged_logs(
    base: Path, n: int, work: Path, seed: int, timeout_s: float, max_rss_mb: float, jobs: int
) -> list[Outcome]:
    """``n`` damaged copies of ``base`` (damages in turn, seeded), each through
    ``wm log-info --check`` and ``wm run`` (``--skip-corrupt`` for every other one)."""
    data = base.read_bytes()
    rng = random.Random(seed)
    cmds: list[tuple[list[str], str]] = []
    for i in range(n):
        kind = DAMAGES[i % len(DAMAGES)]
        bad, what = damage(data, kind, rng)
        path = work / f"damaged_{i:04d}_{kind}.mcap"
        path.write_bytes(bad)
        what = f"{kind}: {what}"
        cmds.append((_wm("log-info", str(path), "--check"), what))
        run = _wm("run", str(path), "--kd", str(work / f"damaged_{i:04d}.kd"), "--no-progress")
        cmds.append((run + (["--skip-corrupt"] if i % 2 == 0 else []), what))
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(lambda c: run_bounded(*c, timeout_s, max_rss_mb), cmds))


# --- (b) kills --------------------------------------------------------------------------------


def _running(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def children(pid: int) -> set[int]:
    """The direct children of ``pid`` (every thread's)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            pass
    return out


def kind_of(pid: int) -> str:
    """A run's child: the decoder (the prefetch interpreter) or odometry (a fork of the run).

    A child read between its fork and its exec still shows the run's command line, so it is
    "odometry" until read again."""
    cmd = _cmdline(pid)
    if not cmd:
        return "gone"
    return "decoder" if "logs.prefetch" in cmd else "odometry" if "wm.cli" in cmd else cmd


def orphans(kd: Path, kids: set[int]) -> list[str]:
    """Processes left by a killed run: its children still running, or any process whose
    command line names its KD."""
    left = {p for p in kids if _running(p)}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and str(kd) in _cmdline(int(entry.name)):
            left.add(int(entry.name))
    return [f"{p}: {_cmdline(p)[:120]}" for p in sorted(left) if p != os.getpid()]


@dataclass
class KillOutcome:
    """One SIGKILL of ``wm run``: when, whether the KD checks sound, what was left running,
    the last flush the run reported and the newest self state its KD holds (ns of log time,
    None: none), the largest log time between two reported flushes (s)."""

    at_s: float
    killed: bool  # False: the run ended before the moment came
    kd: str  # "ok", "defect", "missing"
    orphans: list[str]
    check_stderr: str = ""
    flushed_t_ns: int | None = None
    kd_newest_t_ns: int | None = None
    max_flush_gap_s: float = 0.0

    @property
    def lost_flushed(self) -> bool:
        """The KD lacks what the run had reported flushed."""
        if self.flushed_t_ns is None:
            return False
        return self.kd_newest_t_ns is None or self.kd_newest_t_ns < self.flushed_t_ns


_FLUSHED = re.compile(r"KD flushed to t_ns=(-?\d+)")


def flush_lines(stderr: str) -> list[int]:
    """The log times (ns) of the flushes a ``wm run`` reported on stderr, in order."""
    return [int(m.group(1)) for m in _FLUSHED.finditer(stderr)]


def newest_self_t_ns(kd: Path) -> int | None:
    """The newest self state's time (ns) in the KD file ``kd`` (None: no self state)."""
    import kd_store

    with kd_store.open(kd, read_only=True) as db:
        t = db.sql(
            "SELECT max(s.t_ns) AS t FROM entity_states s JOIN entities e "
            "ON e.id = s.entity_id WHERE e.name = 'self'"
        )["t"][0].as_py()
    return None if t is None else int(t)


def kill_once(
    log: Path, kd: Path, at_s: float, timeout_s: float, after_flush: bool = True
) -> KillOutcome:
    """Start ``wm run``, SIGKILL it ``at_s`` s after its first KD flush (``after_flush``: the
    run is producing) or after its children started (its start-up), then ``wm check`` its KD
    and look for orphans 2 s after the kill."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = _wm("run", str(log), "--kd", str(kd))  # stderr is a file: a line per KD flush
    err_path = kd.with_suffix(".stderr")
    with err_path.open("ab") as err:  # appended by the run, read by path here
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=err)
    kids: set[int] = set()
    t0 = time.monotonic()
    # the moment counts from when the run has started its decoder and odometry (a kill
    # during the interpreter's start-up tests nothing of the run), or from its first flush
    # (on a loaded machine the first sweep can take many seconds after that)
    while proc.poll() is None and len(kids) < 2 and time.monotonic() - t0 < timeout_s:
        kids |= children(proc.pid)
        time.sleep(0.02)
    while (after_flush and proc.poll() is None and time.monotonic() - t0 < timeout_s
           and not flush_lines(err_path.read_text(errors="replace"))):  # fmt: skip
        kids |= children(proc.pid)
        time.sleep(0.02)
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < at_s:
        kids |= children(proc.pid)
        time.sleep(0.02)
    killed = proc.poll() is None
    if killed:
        proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=timeout_s)
    time.sleep(2.0)
    left = orphans(kd, kids)
    for p in left:  # do not leave them for the next kill to find
        _kill_tree(int(p.split(":")[0]))
    flushed = flush_lines(err_path.read_text(errors="replace"))
    gaps = [(b - a) / 1e9 for a, b in itertools.pairwise(flushed)]
    last = flushed[-1] if flushed else None
    if not kd.exists():
        return KillOutcome(at_s, killed, "missing", left, "", last, None, max(gaps, default=0.0))
    check = subprocess.run(_wm("check", str(kd)), cwd=REPO, env=env, capture_output=True,
                           text=True, timeout=timeout_s)  # fmt: skip
    state = "ok" if check.returncode == 0 else "defect"
    newest = newest_self_t_ns(kd) if state == "ok" else None
    return KillOutcome(at_s, killed, state, left, check.stderr[-500:], last, newest,
                       max(gaps, default=0.0))  # fmt: skip


def kills(log: Path, k: int, work: Path, seed: int, run_s: float, timeout_s: float) -> list:
    """``k`` kills, one run at a time (the orphan scan must not see another run's children):
    every fourth in the run's start-up (uniform over 2 s after its children started), the
    others at moments uniform over ``run_s`` seconds after its first KD flush."""
    rng = random.Random(seed + 1)
    return [
        kill_once(log, work / f"killed_{i:03d}.kd", rng.uniform(0.0, 2.0 if i % 4 == 0 else run_s),
                  timeout_s, after_flush=i % 4 != 0)
        for i in range(k)
    ]  # fmt: skip


# --- the campaign -------------------------------------------------------------------------


@dataclass
class CampaignResult:
    """Counts per outcome and every command that did not end cleanly."""

    logs: Counter
    kills: Counter
    bad: list[dict]
    every: list[dict] = field(default_factory=list)  # every command and kill, in order

    def figures(self) -> dict[str, tuple[int, str]]:
        """Figure name -> (value, unit)."""
        out = {f"campaign_damaged_{o}": (self.logs[o], "commands") for o in OUTCOMES}
        for o in ("killed", "kd_ok", "kd_defect", "kd_missing", "orphans", "lost_flushed"):
            out[f"campaign_kill_{o}"] = (self.kills[o], "runs")
        out["campaign_kill_max_flush_gap_s"] = (self.kills["max_flush_gap_ms"] / 1e3, "s")
        return out


def simulate(path: Path, seconds: float, seed: int) -> Path:
    from fixtures.simulate import simulate_to_log

    if not path.exists():
        simulate_to_log("default", path, seconds=seconds, seed=seed, progress=False)
    return path


def campaign(
    n_logs: int,
    n_kills: int,
    work: Path,
    seed: int = 0,
    timeout_s: float = 120.0,
    max_rss_mb: float = 3000.0,
    jobs: int = 2,
    kill_log_s: float = 12.0,
    kill_within_s: float = 5.0,
) -> CampaignResult:
    """Run both parts (module docstring) in ``work``; logs are simulated there once."""
    if not Path("/proc/self/task").exists():
        raise CampaignError("the campaign needs Linux /proc")
    work.mkdir(parents=True, exist_ok=True)
    logs: Counter = Counter()
    bad: list[dict] = []
    every: list[dict] = []
    if n_logs:
        base = simulate(work / "base.mcap", 0.6, seed)
        for o in damaged_logs(base, n_logs, work, seed, timeout_s, max_rss_mb, jobs):
            logs[o.outcome] += 1
            every.append(asdict(o))
            if o.outcome not in ("error", "completed"):
                bad.append(asdict(o))
    kc: Counter = Counter()
    if n_kills:
        log = simulate(work / f"kill_{kill_log_s:g}s.mcap", kill_log_s, seed + 7)
        for ko in kills(log, n_kills, work, seed, kill_within_s, timeout_s):
            kc["killed"] += ko.killed
            kc[f"kd_{ko.kd}"] += 1
            kc["orphans"] += len(ko.orphans)
            kc["lost_flushed"] += ko.lost_flushed
            kc["max_flush_gap_ms"] = max(kc["max_flush_gap_ms"], round(ko.max_flush_gap_s * 1e3))
            every.append(asdict(ko))
            if ko.orphans or ko.kd == "defect" or ko.lost_flushed:
                bad.append(asdict(ko))
    return CampaignResult(logs, kc, bad, every)


def report(result: CampaignResult, out: Path | None, command: str) -> None:
    """Print the table; with ``out``, one JSON file per figure there and the list of bad
    outcomes in ``campaign_bad.json``."""
    print(f"{'figure':<32} {'value':>7}  unit")
    for name, (value, unit) in result.figures().items():
        print(f"{name:<32} {value:>7}  {unit}")
    for b in result.bad:
        print(f"BAD: {json.dumps(b)[:600]}")
    if out is None:
        return
    out.mkdir(parents=True, exist_ok=True)
    bad_kinds = {"traceback", "hang", "memory", "other", "kd_defect", "orphans", "lost_flushed"}
    for name, (value, unit) in result.figures().items():
        target = "0" if any(name.endswith(k) for k in bad_kinds) else None
        if name == "campaign_kill_max_flush_gap_s":  # the flush every 1 s of log, one sweep
            target = "<= 1.1"
        rec = {
            "name": name,
            "value": float(value),
            "unit": unit,
            "baseline": None,
            "baseline_value": None,
            "ratio": None,
            "target": target,
            "command": command,
        }
        (out / f"{name}.json").write_text(json.dumps(rec, indent=2) + "\n")
    (out / "campaign_bad.json").write_text(json.dumps(result.bad, indent=2) + "\n")
    (out / "campaign_all.json").write_text(json.dumps(result.every, indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m wm.campaign", description=__doc__.split("\n")[0])
    p.add_argument("--logs", type=int, default=12, help="damaged logs (each: 2 commands)")
    p.add_argument("--kills", type=int, default=2, help="SIGKILLs of wm run")
    p.add_argument("--out", type=Path, default=None, help="one JSON file per figure here")
    p.add_argument("--work", type=Path, default=None, help="logs and KDs here (default: temp)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=120.0, help="per command, s")
    p.add_argument("--max-rss-mb", type=float, default=3000.0, help="per command tree, MiB")
    p.add_argument("--jobs", type=int, default=2, help="damaged-log commands at once")
    args = p.parse_args(argv)
    command = "python -m wm.campaign " + " ".join(argv if argv is not None else sys.argv[1:])
    with tempfile.TemporaryDirectory(prefix="wm-campaign-") as tmp:
        work = args.work or Path(tmp)
        result = campaign(args.logs, args.kills, work, args.seed, args.timeout,
                          args.max_rss_mb, args.jobs)  # fmt: skip
    report(result, args.out, command)
    clean = not result.bad
    return 0 if clean else 1


if __name__ == "__main__":
    sys.exit(main())
