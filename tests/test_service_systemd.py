"""deploy/systemd/mapserver.service: it verifies, it is hardened (exposure 2.5 or lower), and it
says what the daemon relies on."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[1] / "deploy" / "systemd" / "mapserver.service"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed")


def settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


def test_the_unit_says_what_the_daemon_relies_on() -> None:
    s = settings()
    assert s["Type"] == ["notify"] and s["NotifyAccess"] == ["main"]
    assert s["Restart"] == ["on-failure"]
    assert int(s["WatchdogSec"][0]) >= 10  # the daemon pings about once a second
    assert s["User"] == ["mapserver"]
    assert s["KillMode"] == ["mixed"]  # SIGTERM to the daemon; the workers finish their bundle
    assert len(s["ReadWritePaths"]) == 1 and " " not in s["ReadWritePaths"][0]  # no EXDEV
    # Bounded: the workers' default worker_memory_mb is a share of MemoryMax, and the kernel
    # killing one worker at MemoryMax must not stop the service.
    assert s["MemoryMax"] == ["80%"] and s["OOMPolicy"] == ["continue"]
    assert 100 <= int(s["TasksMax"][0]) <= 4096
    command = s["ExecStart"][0].split()
    assert command[1:] == ["run", "--config", "/etc/mapserver/mapserver.yaml"]


@needs_analyze
def test_systemd_analyze_verify_passes(tmp_path: Path) -> None:
    # verify checks that ExecStart exists: point it at this checkout's command.
    here = Path(sys.executable).parent / "mapserver"
    unit = tmp_path / "mapserver.service"
    unit.write_text(UNIT.read_text().replace("/opt/mapserver/.venv/bin/mapserver", str(here)))
    done = subprocess.run(
        [ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    complaints = [
        line for line in (done.stdout + done.stderr).splitlines() if "mapserver.service" in line
    ]
    assert done.returncode == 0 and complaints == [], done.stdout + done.stderr


@needs_analyze
def test_systemd_analyze_security_rates_it_2_5_or_lower() -> None:
    done = subprocess.run(
        [ANALYZE, "security", "--offline=true", str(UNIT)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if "--offline" in done.stderr and done.returncode != 0:
        pytest.skip("this systemd-analyze has no --offline")
    match = re.search(r"Overall exposure level for mapserver\.service: ([0-9.]+)", done.stdout)
    assert match, done.stdout + done.stderr
    assert float(match.group(1)) <= 2.5, done.stdout
