"""The kiosk's systemd unit: what systemd itself makes of it (``systemd-analyze verify``), and the keys that
keep a kiosk running unattended, checked against the kiosk code they must agree with."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from client.kiosk.hours import RESTART_STATUS
from client.kiosk.watchdog import Watchdog

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "deploy" / "walkstream-kiosk.service"
INSTALLED = "/usr/local/bin/walkstream"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """A unit file's sections → key → values, in order (keys such as Environment= may repeat)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current = None
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None and "=" in line, f"line {n} is neither a section nor a key: {raw!r}"
        key, value = (s.strip() for s in line.split("=", 1))
        current.setdefault(key, []).append(value)
    return sections


def _seconds(value: str) -> float:
    units = {"s": 1, "min": 60, "ms": 1e-3}
    for suffix, factor in sorted(units.items(), key=lambda kv: -len(kv[0])):
        if value.endswith(suffix):
            return float(value[: -len(suffix)]) * factor
    return float(value)


def _bytes(value: str) -> int:
    """systemd's sizes: a number of bytes, or with K, M, G, T (powers of 1024)."""
    powers = {"K": 1, "M": 2, "G": 3, "T": 4}
    suffix = value[-1].upper()
    return int(float(value[:-1]) * 1024 ** powers[suffix]) if suffix in powers else int(value)


@pytest.fixture(scope="module")
def unit() -> dict[str, dict[str, list[str]]]:
    return parse_unit(UNIT.read_text())


def _one(unit, section: str, key: str) -> str:
    values = unit.get(section, {}).get(key)
    assert values, f"[{section}] {key}= is missing"
    return values[-1]


def test_systemd_accepts_the_unit_without_a_warning(tmp_path: Path) -> None:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.fail("systemd-analyze is missing: apt-get install systemd")
    # verify checks that ExecStart's program exists: point it at this environment's walkstream.
    here = Path(sys.executable).with_name("walkstream")
    assert here.exists(), f"{here} is missing: pip install -e ."
    text = UNIT.read_text()
    assert INSTALLED in text
    copy = tmp_path / UNIT.name
    copy.write_text(text.replace(INSTALLED, str(here)))
    out = subprocess.run([exe, "verify", str(copy)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr.strip() == "" and out.stdout.strip() == "", out.stderr


def test_a_typo_in_a_unit_would_be_caught(tmp_path: Path) -> None:
    """The check above is not vacuous: systemd-analyze names a key it does not know."""
    exe = shutil.which("systemd-analyze") or pytest.fail("systemd-analyze is missing: apt-get install systemd")
    copy = tmp_path / "typo.service"
    copy.write_text(f"[Service]\nType=notify\nExecStart={sys.executable}\nWatchdogSecs=30\n")
    out = subprocess.run([exe, "verify", str(copy)], capture_output=True, text=True, timeout=60)
    assert "Unknown key" in out.stderr and "WatchdogSecs" in out.stderr


def test_it_runs_the_kiosk_as_a_notify_service_restarted_always(unit) -> None:
    svc = unit["Service"]
    assert _one(unit, "Service", "ExecStart").split()[1:] == ["kiosk", "/etc/walkstream/kiosk.toml"]
    assert _one(unit, "Service", "Type") == "notify" and _one(unit, "Service", "NotifyAccess") == "main"
    assert _one(unit, "Service", "Restart") == "always"
    assert 1 <= _seconds(_one(unit, "Service", "RestartSec")) <= 30
    # The nightly restart's exit status is the one the schedule exits with.
    assert str(RESTART_STATUS) in _one(unit, "Service", "RestartForceExitStatus").split()
    assert str(RESTART_STATUS) not in " ".join(svc.get("RestartPreventExitStatus", []))
    # A wrong config (EX_CONFIG) waits for a person; an unexpected failure (1) is restarted.
    from walkstream.cli import EX_CONFIG

    prevent = " ".join(svc.get("RestartPreventExitStatus", [])).split()
    assert str(EX_CONFIG) in prevent and "1" not in prevent
    assert {"DISPLAY", "XAUTHORITY"} <= {v.split("=", 1)[0] for v in svc["Environment"]}
    assert unit["Install"]["WantedBy"] == ["graphical.target"]


def test_the_watchdog_and_the_kiosks_pings_agree(unit) -> None:
    watchdog_s = _seconds(_one(unit, "Service", "WatchdogSec"))
    assert 5 <= watchdog_s <= 120
    # What systemd hands the process for this WatchdogSec: the kiosk pings twice per period.
    dog = Watchdog.from_environ({"NOTIFY_SOCKET": "/nonexistent", "WATCHDOG_USEC": str(int(watchdog_s * 1e6))})
    assert dog.interval == watchdog_s / 2


def test_failed_starts_escalate_to_a_reboot(unit) -> None:
    interval = _seconds(_one(unit, "Unit", "StartLimitIntervalSec"))
    burst = int(_one(unit, "Unit", "StartLimitBurst"))
    restart = _seconds(_one(unit, "Service", "RestartSec"))
    assert _one(unit, "Unit", "StartLimitAction") == "reboot"
    assert 2 <= burst <= 10
    assert burst * restart < interval  # a kiosk that keeps failing at once does reach the limit
    assert "StartLimitIntervalSec" not in unit["Service"]  # systemd reads the start limits in [Unit] only


def test_memory_is_capped_above_the_kiosks_own_budget(unit) -> None:
    high, top = _bytes(_one(unit, "Service", "MemoryHigh")), _bytes(_one(unit, "Service", "MemoryMax"))
    assert 0 < high < top
    assert top >= 4 * 256 * 10**6  # room for the default cache budget (cache_mb = 256) several times over
