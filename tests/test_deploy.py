"""The README's deployment section and the program agree: the upload lines ``mapserver bundle``
prints are the README's rsync commands, and those commands, run through the README's
authorized_keys forced command (rrsync), deliver a bundle a running daemon takes."""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from daemon_support import Daemon, assert_settled, layout, make_bundle, wait_until, write_config

from mapserver.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"
SERVER_INBOX = "/var/lib/mapserver/inbox"


def deploying() -> str:
    """The README's "## Deploying" section."""
    text = README.read_text(encoding="utf-8")
    start = text.index("\n## Deploying\n")
    end = text.index("\n## ", start + 1)
    return text[start:end]


def command_lines(section: str) -> list[str]:
    """Every line of the section's code blocks, continuation lines (``\\``) joined."""
    lines: list[str] = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", section, flags=re.S):
        joined = block.replace("\\\n", " ")
        lines += [" ".join(line.split()) for line in joined.splitlines() if line.strip()]
    return lines


def readme_uploads() -> list[str]:
    """The README's upload: one command line, the two rsync calls joined by ``&&``."""
    found = [line for line in command_lines(deploying()) if line.startswith("rsync ")]
    found = [line for line in found if "mapserver-inbox:" in line]
    assert len(found) == 1 and found[0].count(" && rsync ") == 1, found
    return found


def forced_command() -> str:
    """The ``command="..."`` of the README's authorized_keys line."""
    (line,) = [line for line in command_lines(deploying()) if "command=" in line]
    match = re.search(r'command="([^"]+)",restrict ssh-ed25519 ', line)
    assert match, line
    return match.group(1)


def test_the_upload_lines_mapserver_bundle_prints_are_the_readmes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    maps = make_bundle(tmp_path / "robot" / "maps")
    monkeypatch.chdir(tmp_path)
    args = ["--nav2-map", str(maps / "nav2_map.yaml"), "--nav2-pose=12.30,-4.50,1.5708"]
    args += ["--slam-map", str(maps / "slam_map.yaml"), "--slam-pose=0.80,0.10,0.02"]
    assert main(["bundle", *args, "--robot", "sedia-01", "-o", "run-0042"]) == 0
    out = capsys.readouterr().out.replace("\\\n", " ")
    printed = [" ".join(line.split()) for line in out.splitlines()]
    uploads = [line for line in printed if line.startswith("rsync ")]
    assert uploads == readme_uploads()
    # The README's mapserver bundle line is the one a robot types: it parses.
    (typed,) = [line for line in command_lines(deploying()) if line.startswith("mapserver bundle")]
    assert typed.endswith(" -o run-0042")


@pytest.mark.skipif(shutil.which("rsync") is None, reason="rsync is not installed")
@pytest.mark.skipif(not Path("/usr/bin/rrsync").is_file(), reason="rrsync is not installed")
def test_the_readme_upload_goes_through_the_forced_command_into_a_running_daemon(
    tmp_path: Path,
) -> None:
    dirs = layout(tmp_path)
    inbox = dirs["inbox"]
    (inbox / ".rsync-partial").mkdir(parents=True)  # as the README's install -d makes it
    (inbox / ".rsync-partial").chmod(0o2770)
    # ssh as sshd runs a key's forced command: the client's command in SSH_ORIGINAL_COMMAND.
    forced = forced_command().replace(SERVER_INBOX, str(inbox))
    assert forced != forced_command() and forced.startswith("/usr/bin/rrsync ")
    ssh = tmp_path / "ssh"
    ssh.write_text(
        "#!/bin/sh\n"
        '[ "$1" = mapserver-inbox ] || exit 255\n'
        "shift\n"
        f'SSH_ORIGINAL_COMMAND="$*" exec {forced}\n'
    )
    ssh.chmod(0o755)
    robot = tmp_path / "robot"
    source = make_bundle(robot / "run-0042")
    config = write_config(tmp_path)
    with Daemon(config) as daemon:
        daemon.wait_ready()
        for line in readme_uploads():
            subprocess.run(
                ["sh", "-c", line],
                cwd=robot,
                env={**os.environ, "RSYNC_RSH": str(ssh)},
                check=True,
                capture_output=True,
            )
        wait_until(
            lambda: (dirs["archive"] / "run-0042").is_dir(), timeout=30, what="the bundle taken"
        )
        assert daemon.stop() == 0, daemon.log()
    assert_settled(tmp_path, {"run-0042": source})
    archived = dirs["archive"] / "run-0042"
    assert stat.S_IMODE(archived.stat().st_mode) == 0o2770
    assert {stat.S_IMODE(p.stat().st_mode) for p in archived.iterdir()} == {0o660}
    # Outside the inbox is out of reach: an absolute destination lands inside it, or nowhere.
    escape = subprocess.run(
        ["rsync", "-a", "run-0042/", "mapserver-inbox:/etc/mapserver-test/"],
        cwd=robot,
        env={**os.environ, "RSYNC_RSH": str(ssh)},
        capture_output=True,
    )
    assert not Path("/etc/mapserver-test").exists(), escape


def test_the_readmes_backup_of_a_store_in_use_restores_every_map_and_bundle(
    tmp_path: Path,
) -> None:
    from mapserver.config import UpdateConfig
    from mapserver.fleet.store import FleetStore
    from tests.fleet_support import WALL, Robot, write_building

    (code,) = re.findall(r"python3 -c '([^']+)' SRC DST", deploying())
    hall = write_building(tmp_path / "src")
    robot = Robot("r1")
    live = tmp_path / "maps"
    settings = UpdateConfig(mode="auto", confirm_sessions=1, confirm_span_hours=0)
    with FleetStore(live, settings) as store:
        store.add_map("hall", hall)
        store.apply(robot.observe(0, added=(WALL,), found=(("added", WALL),)))  # version 2
        backup = tmp_path / "backup"
        backup.mkdir()
        # While the store is open (the daemon runs): the database first, then the files.
        subprocess.run(
            [sys.executable, "-c", code, str(live / "store.db"), str(backup / "store.db")],
            check=True,
        )
        shutil.copytree(live / "hall", backup / "hall")
        versions = [(v.version, v.sha256) for v in store.versions("hall")]
        assert [v for v, _ in versions] == [1, 2]
    with FleetStore(backup, UpdateConfig(mode="auto")) as restored:
        restored.sync()
        assert [(v.version, v.sha256) for v in restored.versions("hall")] == versions
        assert restored.map_info("hall").bundles == 1
    assert (backup / "hall" / "current.yaml").read_text().count("v0002.pgm") == 1
