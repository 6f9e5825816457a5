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
WEB_UNIT = UNIT.with_name("mapserver-web.service")
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed")


def settings(unit: Path = UNIT) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in unit.read_text().splitlines():
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
    assert command[1:] == ["run", "--no-web", "--config", "/etc/mapserver/mapserver.yaml"]
    assert s["PrivateNetwork"] == ["yes"]  # the web runs in mapserver-web.service


def test_the_web_unit_may_only_reach_the_loopback_and_write_only_the_store() -> None:
    s = settings(WEB_UNIT)
    assert s["ExecStart"][0].split()[1:] == ["web", "--config", "/etc/mapserver/mapserver.yaml"]
    assert s["ReadWritePaths"] == ["/var/lib/mapserver/maps"]
    assert s["IPAddressDeny"] == ["any"] and s["IPAddressAllow"] == ["localhost"]
    assert "PrivateNetwork" not in s and s["User"] == ["mapserver"]


@needs_analyze
@pytest.mark.parametrize("source", [UNIT, WEB_UNIT], ids=lambda p: p.name)
def test_systemd_analyze_verify_passes(tmp_path: Path, source: Path) -> None:
    # verify checks that ExecStart exists: point it at this checkout's command.
    here = Path(sys.executable).parent / "mapserver"
    unit = tmp_path / source.name
    unit.write_text(source.read_text().replace("/opt/mapserver/.venv/bin/mapserver", str(here)))
    done = subprocess.run(
        [ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    complaints = [line for line in (done.stdout + done.stderr).splitlines() if source.name in line]
    assert done.returncode == 0 and complaints == [], done.stdout + done.stderr


@needs_analyze
@pytest.mark.parametrize("unit", [UNIT, WEB_UNIT], ids=lambda p: p.name)
def test_systemd_analyze_security_rates_it_2_5_or_lower(unit: Path) -> None:
    done = subprocess.run(
        [ANALYZE, "security", "--offline=true", str(unit)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if "--offline" in done.stderr and done.returncode != 0:
        pytest.skip("this systemd-analyze has no --offline")
    name = re.escape(unit.name)
    match = re.search(rf"Overall exposure level for {name}: ([0-9.]+)", done.stdout)
    assert match, done.stdout + done.stderr
    assert float(match.group(1)) <= 2.5, done.stdout
