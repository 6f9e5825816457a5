"""One daemon per inbox: the lock in process, and two real ``mapserver run`` on one inbox."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from daemon_support import Daemon, assert_settled, layout, make_bundle, upload, wait_until
from daemon_support import write_config as write_daemon_config

from mapserver.config import Config, parse_config
from mapserver.lock import LOCK_NAME, AlreadyRunning, daemon_lock, daemon_pid


def config_for(root: Path) -> Config:
    return parse_config({}, base_dir=root)


def test_the_lock_is_exclusive_names_its_holder_and_goes_with_it(tmp_path: Path) -> None:
    config = config_for(tmp_path)
    assert daemon_pid(config) is None  # no lock file yet
    with daemon_lock(config) as path:
        assert path == tmp_path / "inbox" / LOCK_NAME
        assert daemon_pid(config) == os.getpid()
        with pytest.raises(AlreadyRunning) as caught, daemon_lock(config):
            pass
        assert caught.value.reason == (
            f"another mapserver (pid {os.getpid()}) is running on {tmp_path / 'inbox'}"
        )
        assert daemon_pid(config) == os.getpid()  # the failed attempt took nothing away
    assert daemon_pid(config) is None
    with daemon_lock(config):  # free again
        pass


def test_a_lock_held_by_a_killed_process_is_free_and_its_stale_pid_means_nothing(
    tmp_path: Path,
) -> None:
    config = config_for(tmp_path)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from mapserver.config import parse_config; "
            "from mapserver.lock import daemon_lock; from pathlib import Path\n"
            f"with daemon_lock(parse_config({{}}, base_dir=Path({str(tmp_path)!r}))):\n"
            "    print('locked', flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "locked\n"
        assert daemon_pid(config) == holder.pid
        holder.kill()
        holder.wait()
    finally:
        holder.kill()
        holder.wait()
        assert holder.stdout is not None
        holder.stdout.close()
    assert (tmp_path / "inbox" / LOCK_NAME).read_text() == f"{holder.pid}\n"
    assert daemon_pid(config) is None
    with daemon_lock(config):
        assert daemon_pid(config) == os.getpid()


def test_a_second_daemon_on_the_same_inbox_exits_1_at_once_and_the_first_serves_on(
    tmp_path: Path,
) -> None:
    source = make_bundle(tmp_path / "src" / "run-1")
    config = write_daemon_config(tmp_path, workers=1)
    with Daemon(config) as first:
        first.wait_ready()
        start = time.monotonic()
        second = subprocess.run(
            [sys.executable, "-m", "mapserver.cli", "run", "--config", str(config)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        took = time.monotonic() - start
        assert second.returncode == 1, second.stdout + second.stderr
        inbox = tmp_path / "inbox"
        assert second.stderr == (
            f"mapserver: error: another mapserver (pid {first.process.pid}) is running on {inbox}\n"
        )
        assert "ready" not in second.stdout and "Warning" not in second.stdout
        assert took < 20, took  # the interpreter's start-up; no waiting on the lock
        # The second one touched nothing: the first takes and finishes the bundle alone.
        upload(source, layout(tmp_path)["inbox"])
        wait_until(
            lambda: (tmp_path / "archive" / "run-1").is_dir(), timeout=30, what="run-1 archived"
        )
        assert first.stop() == 0, first.log()
    assert_settled(tmp_path, {"run-1": source})
    assert "Warning" not in first.log()  # the second one made no probe in the inbox


def test_a_restart_after_kill_9_needs_no_manual_step(tmp_path: Path) -> None:
    config = write_daemon_config(tmp_path, workers=1)
    with Daemon(config) as first:
        first.wait_ready()
        first.kill_group()
    assert (tmp_path / "inbox" / LOCK_NAME).read_text() == f"{first.process.pid}\n"
    source = make_bundle(tmp_path / "src" / "run-1")
    with Daemon(config) as second:
        second.wait_ready()
        assert daemon_pid(config_for(tmp_path)) == second.process.pid
        upload(source, layout(tmp_path)["inbox"])
        wait_until(
            lambda: (tmp_path / "archive" / "run-1").is_dir(), timeout=30, what="run-1 archived"
        )
        assert second.stop() == 0, second.log()
    assert_settled(tmp_path, {"run-1": source})
