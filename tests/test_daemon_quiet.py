"""No raw library warnings or errors in a normal run of a real ``mapserver run``: a failed
bundle moved back into the inbox to be tried again, and a stop right after a bundle is archived.
"""

from __future__ import annotations

import os
from pathlib import Path

from daemon_support import Daemon, layout, make_bundle, upload, wait_until
from daemon_support import write_config as write_daemon_config


def test_a_retried_bundle_and_a_stop_right_after_an_archive_log_nothing_raw(
    tmp_path: Path,
) -> None:
    good = make_bundle(tmp_path / "src" / "good", checksums=False)
    broken = make_bundle(tmp_path / "src" / "run-1", seed=1, checksums=False)
    image = (broken / "slam_map.pgm").read_bytes()
    (broken / "slam_map.pgm").write_bytes(b"P5\n100 100\n255\n")  # truncated: fails at load
    config = write_daemon_config(tmp_path, workers=1)
    dirs = layout(tmp_path)
    with Daemon(config) as daemon:
        daemon.wait_ready()
        upload(broken, dirs["inbox"])
        error = dirs["failed"] / "run-1" / "error.yaml"
        wait_until(error.is_file, timeout=30, what="run-1 failed")
        # The README's way to try a failed bundle again, once the cause is fixed.
        (dirs["failed"] / "run-1" / "slam_map.pgm").write_bytes(image)
        error.unlink()
        os.rename(dirs["failed"] / "run-1", dirs["inbox"] / "run-1")
        wait_until((dirs["archive"] / "run-1").is_dir, timeout=30, what="run-1 archived")
        upload(good, dirs["inbox"])
        wait_until((dirs["archive"] / "good").is_dir, timeout=30, what="good archived")
        assert daemon.stop() == 0  # at once: the archive's rename is not 0.5 s old
    log = daemon.log()
    assert (dirs["outbox"] / "run-1" / "result.yaml").is_file()
    raw = [
        line
        for line in log.splitlines()
        if not line.startswith(("INFO mapserver.", "WARNING mapserver.")) or "Warning" in line
    ]
    assert raw == [], log
