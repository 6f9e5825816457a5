"""The daemon's inotify watches stay bounded: watchdog keeps the watch of every bundle moved out
of the inbox, so the daemon sets its watches up afresh every so many bundles
($MAPSERVER_TEST_REARM_AFTER here), without missing an upload."""

from __future__ import annotations

import glob
from pathlib import Path

from tests.daemon_support import Daemon, layout, make_bundle, upload, wait_until, write_config


def watches(pid: int) -> int:
    n = 0
    for path in glob.glob(f"/proc/{pid}/fdinfo/*"):
        try:
            with open(path) as f:
                n += sum(1 for line in f if line.startswith("inotify wd:"))
        except OSError:
            continue
    return n


def test_watches_stay_bounded_and_every_upload_is_still_seen(tmp_path: Path) -> None:
    config = write_config(tmp_path, workers=2, observer="native")
    inbox = layout(tmp_path)["inbox"]
    with Daemon(config, env={"MAPSERVER_TEST_REARM_AFTER": "5"}) as daemon:
        daemon.wait_ready()
        first = watches(daemon.process.pid)
        for i in range(16):
            upload(make_bundle(tmp_path / "src" / f"b{i:02d}", seed=i), inbox)
            if i % 4 == 3:  # uploads keep coming while the watches are set up again
                wait_until(
                    lambda n=i + 1: len(list((tmp_path / "archive").iterdir())) == n,
                    timeout=60,
                    what=f"{i + 1} archived",
                )
        wait_until(lambda: len(list((tmp_path / "archive").iterdir())) == 16, timeout=60, what="16")
        wait_until(
            lambda: watches(daemon.process.pid) <= first + 6,
            timeout=10,
            what="the watches of archived bundles dropped",
        )
        assert "watches set up afresh" in daemon.log()
        assert "ERROR" not in daemon.log() and "Traceback" not in daemon.log()
        assert daemon.stop() == 0, daemon.log()
