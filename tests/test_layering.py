"""The house's rules that a reader cannot see at a glance: no clock in the algorithms or the session,
no module that grows past what a reader can hold, and the import contracts themselves."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("proto", "server", "client", "bench", "walkstream")
CLOCKS = {("time", n) for n in ("time", "perf_counter", "monotonic", "process_time", "time_ns", "perf_counter_ns",
                                "monotonic_ns", "thread_time")} | {("datetime", "now"), ("datetime", "utcnow"),
                                                                   ("date", "today")}


def _modules(*under: str) -> list[Path]:
    return sorted(p for u in under for p in (ROOT / u).rglob("*.py"))


def _clock_reads(path: Path) -> list[str]:
    """Calls of a clock in ``path``: ``time.perf_counter()``, ``from time import monotonic``, ``datetime.now()``."""
    tree = ast.parse(path.read_text(), str(path))
    name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) \
                and (node.value.id, node.attr) in CLOCKS:
            found.append(f"{name}:{node.lineno} {node.value.id}.{node.attr}")
        elif isinstance(node, ast.ImportFrom) and node.module in ("time", "datetime"):
            for alias in node.names:
                if (node.module, alias.name) in CLOCKS:
                    found.append(f"{name}:{node.lineno} from {node.module} import {alias.name}")
    return found


def test_nothing_under_the_session_or_the_algorithms_reads_a_clock():
    found = [hit for p in _modules("server/session", "server/select") for hit in _clock_reads(p)]
    assert found == []


def test_the_clock_check_finds_a_clock(tmp_path):
    bad = tmp_path / "probe.py"
    bad.write_text("import time\nfrom time import monotonic\n\ndef f():\n    return time.perf_counter()\n")
    assert len(_clock_reads(bad)) == 2


def test_no_module_outside_tests_is_longer_than_600_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules(*PACKAGES)
            if (n := len(p.read_text().splitlines())) > 600}
    assert long == {}


def test_the_import_contracts_hold():
    lint = Path(sys.executable).with_name("lint-imports")
    if not lint.exists():
        pytest.fail("lint-imports is not installed (pip install -e '.[dev]')")
    done = subprocess.run([str(lint)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:]
