"""Prompt, precise rejections on a real ``mapserver run``: a complete bundle whose checksum does
not match, and a folder of bundles uploaded as one, go to failed/ within seconds (not after
``stale_after_seconds``), each with its own one-line reason."""

from __future__ import annotations

import hashlib
import shutil
import time
from pathlib import Path

import yaml
from daemon_support import Daemon, layout, make_bundle, upload, wait_until
from daemon_support import write_config as write_daemon_config


def test_a_checksum_mismatch_and_a_folder_of_bundles_are_failed_within_seconds(
    tmp_path: Path,
) -> None:
    corrupt = make_bundle(tmp_path / "src" / "corrupt")
    data = bytearray((corrupt / "slam_map.pgm").read_bytes())
    data[-1] ^= 0xFF  # one flipped byte: what a broken transfer leaves
    (corrupt / "slam_map.pgm").write_bytes(bytes(data))
    expected = yaml.safe_load((corrupt / "bundle.yaml").read_text())["checksums"]["slam_map.pgm"]
    actual = hashlib.sha256(bytes(data)).hexdigest()
    folder = tmp_path / "src" / "runs"
    make_bundle(folder / "run-1", seed=1)
    make_bundle(folder / "run-2", seed=2)
    config = write_daemon_config(tmp_path, stale_after_seconds=600)  # settle_seconds 0.2
    dirs = layout(tmp_path)
    with Daemon(config) as daemon:
        daemon.wait_ready()
        start = time.monotonic()
        upload(corrupt, dirs["inbox"])
        shutil.copytree(folder, dirs["inbox"] / "runs")
        wait_until(
            lambda: all((dirs["failed"] / i / "error.yaml").is_file() for i in ("corrupt", "runs")),
            timeout=30,
            what="both failed",
        )
        took = time.monotonic() - start
        assert daemon.stop() == 0, daemon.log()
    assert took < 15, took  # 10 x settle_seconds for the mismatch; stale_after_seconds is 600
    # The folders did not exist: the daemon made them, and said so (a misspelt path shows).
    made = ", ".join(
        f"{name} {tmp_path / name}" for name in ("inbox", "outbox", "archive", "failed")
    )
    assert f"WARNING mapserver.service: created {made}: not there before" in daemon.log()
    error = yaml.safe_load((dirs["failed"] / "corrupt" / "error.yaml").read_text())
    assert error["stage"] == "upload", error
    assert error["reason"].startswith(
        f"slam_map.pgm: sha256 of 'slam_map.pgm' does not match the manifest: "
        f"expected {expected}, actual {actual} (every file there, nothing changed for "
    ), error
    error = yaml.safe_load((dirs["failed"] / "runs" / "error.yaml").read_text())
    assert error["stage"] == "bundle", error
    assert error["reason"] == (
        "runs: not a bundle: no bundle.yaml in it; it holds 2 bundle folders (run-1, run-2); "
        "upload each bundle folder directly into the inbox"
    )
    assert (dirs["failed"] / "runs" / "run-1" / "bundle.yaml").is_file()  # kept as it came


def test_the_daemon_names_the_map_store_folder_it_created(tmp_path: Path) -> None:
    config = write_daemon_config(tmp_path, maps="maps")
    with Daemon(config) as daemon:
        daemon.wait_ready()
        assert daemon.stop() == 0, daemon.log()
    made = ", ".join(
        f"{name} {tmp_path / name}" for name in ("inbox", "outbox", "archive", "failed", "maps")
    )
    assert f"WARNING mapserver.service: created {made}: not there before" in daemon.log()
    assert (tmp_path / "maps").is_dir()
