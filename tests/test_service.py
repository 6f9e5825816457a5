"""The service in process: a real observer on temporary folders, a real worker pool, uploads done
the way rsync does them. (A real ``mapserver run`` subprocess: test_service_daemon.py.)"""

from __future__ import annotations

import os
import random
import shutil
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml
from daemon_support import (
    assert_settled,
    calls,
    layout,
    make_bundle,
    no_leaked_threads,
    scripted_process,
    upload,
    wait_until,
)

from mapserver.config import Config, parse_config
from mapserver.inbox import InboxHandler
from mapserver.service import Service

pytestmark = pytest.mark.usefixtures("no_leaked_threads")
__all__ = ["no_leaked_threads"]


def config_for(root: Path, **overrides: Any) -> Config:
    data: dict[str, Any] = {
        "settle_seconds": 0.2,
        "stale_after_seconds": 30,
        "rescan_seconds": 2,
        "workers": 2,
    }
    data.update(overrides)
    return parse_config(data, base_dir=root)


@contextmanager
def running(config: Config, **kw: Any) -> Iterator[tuple[Service, dict[str, Any]]]:
    """Run the service in a thread; stop it and join it on the way out."""
    service = Service(config, process=scripted_process, **kw)
    outcome: dict[str, Any] = {}

    def target() -> None:
        try:
            outcome["code"] = service.run()
        except BaseException as error:  # reported by the test, not lost in the thread
            outcome["error"] = error

    thread = threading.Thread(target=target, name="service-under-test")
    thread.start()
    try:
        wait_until(
            lambda: service.ready.is_set() or not thread.is_alive(), timeout=30, what="ready"
        )
        yield service, outcome
    finally:
        if not service.stopping:
            service.request_stop()
        thread.join(timeout=60)
        assert not thread.is_alive(), "the service did not stop"
    assert "error" not in outcome, outcome.get("error")


def all_done(root: Path, ids: list[str]) -> bool:
    dirs = layout(root)
    return all(
        ((dirs["outbox"] / i / "result.yaml").is_file() and (dirs["archive"] / i).is_dir())
        or (dirs["failed"] / i / "error.yaml").is_file()
        for i in ids
    )


def upload_in_place(source: Path, inbox: Path) -> None:
    """``cp -r``: the final names from the start, each file written in several pieces."""
    target = inbox / source.name
    target.mkdir()
    for path in sorted(source.iterdir()):
        data = path.read_bytes()
        with (target / path.name).open("wb") as handle:
            for start in range(0, len(data), 4096):
                handle.write(data[start : start + 4096])
                handle.flush()


@pytest.mark.parametrize("observer", ["native", "polling"])
def test_uploads_in_every_order_are_each_processed_exactly_once(
    tmp_path: Path, observer: str
) -> None:
    sources = {
        name: make_bundle(tmp_path / "src" / name, seed=i)
        for i, name in enumerate(
            ["at-start", "manifest-last", "manifest-first", "random", "moved-in", "in-place"]
        )
    }
    dirs = layout(tmp_path)
    dirs["inbox"].mkdir()
    shutil.copytree(sources["at-start"], dirs["inbox"] / "at-start")  # arrived while down
    config = config_for(tmp_path, observer=observer)
    with running(config) as (_, outcome):
        pause = threading.Event().wait  # upload in slow pieces
        jobs = [
            lambda: upload(sources["manifest-last"], dirs["inbox"], pause=lambda: pause(0.05)),
            lambda: upload(sources["manifest-first"], dirs["inbox"], order="manifest-first"),
            lambda: upload(sources["random"], dirs["inbox"], order="random", rng=random.Random(7)),
            lambda: os.rename(
                shutil.copytree(sources["moved-in"], tmp_path / "staging"),
                dirs["inbox"] / "moved-in",
            ),
            lambda: upload_in_place(sources["in-place"], dirs["inbox"]),
        ]
        threads = [threading.Thread(target=job) for job in jobs]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        wait_until(lambda: all_done(tmp_path, list(sources)), timeout=60, what="every result")
    assert outcome["code"] == 0
    assert_settled(tmp_path, sources)
    assert sorted(calls(tmp_path)) == sorted(sources)


def test_a_bundle_whose_events_were_all_lost_is_found_by_the_rescan(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # As after an inotify queue overflow: no event reaches the handler at all.
    monkeypatch.setattr(InboxHandler, "on_any_event", lambda self, event: None)
    source = make_bundle(tmp_path / "src" / "quiet")
    with running(config_for(tmp_path, rescan_seconds=0.5)):
        upload(source, layout(tmp_path)["inbox"])
        wait_until(lambda: all_done(tmp_path, ["quiet"]), timeout=30, what="the rescan")
    assert_settled(tmp_path, {"quiet": source})


def test_a_worker_crash_fails_only_the_bundle_that_caused_it(tmp_path: Path) -> None:
    sources = {
        "good-1": make_bundle(tmp_path / "src" / "good-1", seed=1),
        "crash": make_bundle(tmp_path / "src" / "crash", seed=2, manifest={"robot": "crasher"}),
        "good-2": make_bundle(tmp_path / "src" / "good-2", seed=3),
    }
    dirs = layout(tmp_path)
    with running(config_for(tmp_path)) as (_service, outcome):
        for source in sources.values():
            upload(source, dirs["inbox"])
        wait_until(lambda: all_done(tmp_path, list(sources)), timeout=60, what="every bundle")
        late = make_bundle(tmp_path / "src" / "late", seed=4)  # the pool works after the crash
        upload(late, dirs["inbox"])
        sources["late"] = late
        wait_until(lambda: all_done(tmp_path, ["late"]), timeout=60, what="a bundle after it")
    assert outcome["code"] == 0
    assert_settled(tmp_path, sources, failed={"crash"})
    error = yaml.safe_load((dirs["failed"] / "crash" / "error.yaml").read_text())
    assert error["stage"] == "process" and "died" in error["reason"]
    assert calls(tmp_path).count("crash") == 2


def test_stop_finishes_the_bundle_in_hand_and_leaves_the_queued_ones_for_next_time(
    tmp_path: Path,
) -> None:
    sources = {
        "slow": make_bundle(tmp_path / "src" / "slow", seed=1, manifest={"robot": "slow"}),
        "next": make_bundle(tmp_path / "src" / "next", seed=2),
    }
    dirs = layout(tmp_path)
    taken = dirs["inbox"] / ".taken"
    config = config_for(tmp_path, workers=1)
    with running(config) as (service, outcome):
        upload(sources["slow"], dirs["inbox"])
        wait_until(lambda: calls(tmp_path) == ["slow"], timeout=30, what="slow in a worker")
        upload(sources["next"], dirs["inbox"])
        wait_until(lambda: (taken / "next").is_dir(), timeout=30, what="next taken, queued")
        service.request_stop()
    assert outcome["code"] == 0
    assert (dirs["outbox"] / "slow" / "result.yaml").is_file()  # finished, not abandoned
    assert (dirs["archive"] / "slow").is_dir()
    assert not (dirs["outbox"] / "next").exists() and (taken / "next").is_dir()
    with running(config):
        wait_until(lambda: all_done(tmp_path, ["next"]), timeout=30, what="next at restart")
    assert_settled(tmp_path, sources)
    assert calls(tmp_path) == ["slow", "next"]


def test_systemd_hears_ready_status_watchdog_and_stopping(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    address = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(address))
    sock.settimeout(10)
    monkeypatch.setenv("NOTIFY_SOCKET", str(address))
    monkeypatch.setenv("WATCHDOG_USEC", "300000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    dirs = layout(tmp_path)
    make_bundle(dirs["inbox"] / "waiting")
    messages: list[str] = []

    def receive_until(text: str) -> bool:
        while not any(text in m for m in messages):
            messages.append(sock.recv(4096).decode())
        return True

    try:
        with running(config_for(tmp_path)):
            receive_until("READY=1")
            ready = next(m for m in messages if "READY=1" in m)
            assert "STATUS=1 uploading" in ready  # sent after the start-up scan
            receive_until("1 results")
            count = sum("WATCHDOG=1" in m for m in messages)
            messages.clear()
            receive_until("WATCHDOG=1")
            assert count >= 1
        receive_until("STOPPING=1")
    finally:
        sock.close()


def test_the_service_exits_1_when_it_can_no_longer_watch_the_inbox(tmp_path: Path) -> None:
    dirs = layout(tmp_path)
    with running(config_for(tmp_path)) as (_, outcome):
        shutil.rmtree(dirs["inbox"])
        wait_until(lambda: "code" in outcome, timeout=30, what="the service to give up")
    assert outcome["code"] == 1
