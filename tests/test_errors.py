"""One exception base: every error type the engine defines derives from EngineError, so a
caller (and the command line) catches one type for "the engine refused this input"."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

from core.errors import EngineError

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "kd_store", "maps", "sp", "wm", "fixtures")


def engine_modules():
    for name in PACKAGES:
        pkg = importlib.import_module(name)
        yield pkg
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{name}."):
            if info.name.endswith("__main__"):
                continue
            yield importlib.import_module(info.name)


def test_every_engine_error_derives_from_engine_error():
    found = {}
    for mod in engine_modules():
        for cname, cls in inspect.getmembers(mod, inspect.isclass):
            if cls.__module__ == mod.__name__ and issubclass(cls, BaseException):
                found[f"{mod.__name__}.{cname}"] = cls
    assert len(found) >= 40  # every module's own type, kd_store's family included
    strays = sorted(n for n, c in found.items() if not issubclass(c, EngineError))
    assert strays == []


@pytest.mark.parametrize(
    "argv, words",
    [
        (["simulate", "nowhere-scenario", "--out", "x.mcap"], "nowhere-scenario"),
        (["query", "missing.duckdb", "SELECT 1"], "missing.duckdb"),
    ],
)
def test_cli_prints_one_line_for_an_engine_error(tmp_path, argv, words):
    r = subprocess.run(
        [sys.executable, "-m", "wm.cli", *argv], cwd=tmp_path, capture_output=True, text=True,
        env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], r.stderr
    assert "Traceback" not in r.stderr
