"""The ``mapserver`` command: a thin layer over the library. The only place that configures logging.

Each subcommand's help (``mapserver <command> --help``) is written for the operator who runs it
and ends with an example.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import math
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from mapserver.bundle import UPLOAD_TO
from mapserver.config import (
    CONFIG_HELP,
    DEMO_MARKER,
    ENV_VAR,
    Config,
    check_paths,
    dump_config,
    load_config,
)
from mapserver.errors import ConfigError, MapFileError, MapserverError, describe_validation
from mapserver.fleet.cli import open_store
from mapserver.fleet.cli import register as register_fleet_commands
from mapserver.lock import AlreadyRunning, daemon_pid, store_lock
from mapserver.trust import trust_notice

log = logging.getLogger("mapserver")


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level),
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stdout,
    )


def _cmd_check_config(args: argparse.Namespace) -> int:
    from mapserver.outbox import check_one_filesystem

    config = load_config(args.config)
    check_paths(config)
    # What run refuses too (session 58's review: these passed here, and the unit that
    # systemctl started then stopped at once, again and again).
    check_one_filesystem(config.inbox, config.outbox, config.archive, config.failed)
    if config.web is not None:
        from mapserver.web.security import check_settings

        check_settings(config.web)
    sys.stdout.write(dump_config(config))
    return 0


def _built_in_config(args: argparse.Namespace) -> bool:
    """Whether the configuration is the built-in one (no --config, no $MAPSERVER_CONFIG): its
    folders are in the current directory."""
    return args.config is None and not os.environ.get(ENV_VAR)


def _cmd_process(args: argparse.Namespace) -> int:
    from mapserver.outbox import RESULT, write_result
    from mapserver.pipeline import process_bundle

    config = load_config(args.config)
    _setup_logging(config.log_level)
    outbox = Path(args.outbox).resolve() if args.outbox else config.outbox
    _refuse_a_daemons_outbox(config, outbox)
    if not outbox.exists() and args.outbox is None and _built_in_config(args):
        sys.stderr.write(
            f"mapserver: results go to {outbox} (the built-in default; choose with --outbox DIR "
            "or --config FILE)\n"
        )
    exits = contextlib.ExitStack()
    store = None
    if config.maps is not None:
        exits.enter_context(store_lock(config.maps))  # refused while a daemon feeds the store
        store = exits.enter_context(open_store(config, create=True))
    failures = 0
    with exits:
        # The fleet map counts bundles in stamp order: process them in that order.
        for bundle_dir in _by_stamp([Path(b) for b in args.bundles]):
            try:
                outcome = process_bundle(bundle_dir, config)
                if store is not None and outcome.observation is not None:
                    update = store.apply(outcome.observation)
                    update.annotate(outcome.result)
                    log.info("%s: update %s", outcome.bundle_id, update.summary())
                replaced = (outbox / outcome.bundle_id / RESULT).exists()
                final = write_result(outbox, outcome)
            except MapserverError as error:
                failures += 1
                sys.stderr.write(f"mapserver: error: {error.reason}\n")
                continue
            except OSError as error:  # a full disk, a folder it may not write: the next one
                failures += 1
                where = error.filename or outbox
                sys.stderr.write(
                    f"mapserver: error: {bundle_dir}: cannot write its result to {where}: "
                    f"{error.strerror or error}\n"
                )
                continue
            except Exception as error:  # a bug: this bundle fails, the others are processed
                failures += 1
                log.exception("%s: internal error", bundle_dir)
                sys.stderr.write(
                    f"mapserver: error: {bundle_dir}: internal error ({type(error).__name__}: "
                    f"{error}); please report this bundle\n"
                )
                continue
            differences = outcome.result.get("differences") or []
            note = " (replaced the earlier result)" if replaced else ""
            lines = [
                f"{outcome.bundle_id}: {len(differences)} differences -> {final / RESULT}{note}"
            ]
            notice = trust_notice(outcome.result.get("alignment") or {})
            if notice:
                lines.append(f"{outcome.bundle_id}: {notice}")
            lines += [_difference_line(d) for d in differences]
            sys.stdout.write("\n".join(lines) + "\n")
    return 1 if failures else 0


def _by_stamp(bundles: list[Path]) -> list[Path]:
    """Bundles sorted by their manifest's stamp (stable; unreadable ones keep their place at
    the end, where processing reports what is wrong with them)."""
    if len(bundles) < 2:  # nothing to order: not a manifest read more than processing does
        return bundles
    from mapserver.bundle import read_manifest
    from mapserver.fleet.tracker import parse_stamp

    def key(item: tuple[int, Path]) -> tuple[int, float, int]:
        index, path = item
        try:
            return (0, parse_stamp(read_manifest(path).stamp).timestamp(), index)
        except (MapserverError, OSError, ValueError):
            return (1, 0.0, index)

    return [p for _, p in sorted(enumerate(bundles), key=key)]


def _difference_line(d: dict[str, Any]) -> str:
    """One difference of a result.yaml: id, kind, area and centroid in metres, its box, and the
    fleet map's change it belongs to."""
    c, b = d.get("centroid", {}), d.get("bbox", {})
    return (
        f"  {d.get('id')}. {d.get('kind', '?'):7} {d.get('area_m2', 0):7.2f} m2 at "
        f"x={c.get('x', 0):.2f} y={c.get('y', 0):.2f}  "
        f"(box x {b.get('min_x', 0):.2f}..{b.get('max_x', 0):.2f}, "
        f"y {b.get('min_y', 0):.2f}..{b.get('max_y', 0):.2f})"
        + (f"  change {d['change']}" if d.get("change") is not None else "")
    )


def _refuse_a_daemons_outbox(config: Config, outbox: Path) -> None:
    """A running daemon is the only writer of its outbox: a result written beside it would
    replace one of its results, or take an id it is about to give."""
    if outbox != config.outbox:
        return
    pid = daemon_pid(config)
    if pid is not None:
        # With a map store, --outbox alone is refused too (the daemon feeds the store).
        store = (
            " and a configuration with maps: null (the daemon alone feeds the map store; to "
            "feed it, upload the bundle to its inbox)"
            if config.maps is not None
            else ""
        )
        raise MapserverError(
            f"{AlreadyRunning(pid, config.inbox).reason}, and {outbox} is its outbox; "
            f"write these results elsewhere with --outbox DIR{store}",
            stage="process",
        )


# -- mapserver run ---------------------------------------------------------------------------

_PRIORITY = {"DEBUG": 7, "INFO": 6, "WARNING": 4, "ERROR": 3, "CRITICAL": 2}


class _JournalFormatter(logging.Formatter):
    """Prefixes ``<N>`` (the syslog priority) so that journald keeps each line's level."""

    def format(self, record: logging.LogRecord) -> str:
        return f"<{_PRIORITY.get(record.levelname, 6)}>{super().format(record)}"


def _stdout_is_journal() -> bool:
    stream = os.environ.get("JOURNAL_STREAM", "")
    try:
        device, inode = (int(part) for part in stream.split(":"))
        st = os.fstat(sys.stdout.fileno())
    except (ValueError, OSError):
        return False
    return (st.st_dev, st.st_ino) == (device, inode)


def _setup_daemon_logging(level: str) -> None:
    """Plain lines on stdout (journald adds the time), with priorities when stdout is the journal.
    Also called in each worker process."""
    handler = logging.StreamHandler(sys.stdout)
    fmt = "%(levelname)s %(name)s: %(message)s"
    handler.setFormatter(_JournalFormatter(fmt) if _stdout_is_journal() else logging.Formatter(fmt))
    logging.basicConfig(level=getattr(logging, level), handlers=[handler], force=True)


def _cmd_run(args: argparse.Namespace) -> int:
    from mapserver.service import Service

    config = load_config(args.config)
    # A daemon started by mistake in the wrong directory would make four folders there and watch
    # an inbox no robot uploads to.
    if _built_in_config(args) and not config.inbox.is_dir():
        raise MapserverError(
            f"no configuration given (--config FILE, or $MAPSERVER_CONFIG), and no inbox/ in "
            f"the current directory {Path.cwd()}: the built-in defaults would create inbox/, "
            "outbox/, archive/ and failed/ here. Give --config, or create inbox/ here to run on "
            "the built-in defaults in this directory",
            stage="run",
        )
    _setup_daemon_logging(config.log_level)
    if _built_in_config(args):
        log.warning("no --config: the built-in defaults, with every folder in %s", Path.cwd())
    setup = functools.partial(_setup_daemon_logging, config.log_level)
    web = None
    if config.web is not None and config.web.with_daemon and not args.no_web:
        from mapserver.web.server import make_server

        web = make_server(config)  # refuses a bad address or token before the daemon starts
        web.start_thread()
        log.info("web: serving %s", web.url)
    try:
        return Service(config, worker_setup=setup).run()
    finally:
        if web is not None:
            web.stop()


def _cmd_web(args: argparse.Namespace) -> int:
    from mapserver.web.server import make_server

    config = load_config(args.config)
    if args.listen:
        from pydantic import ValidationError

        from mapserver.config import WebConfig

        # Validated as the configuration file's web.listen is (model_copy checks nothing).
        try:
            web = WebConfig.model_validate(
                {**(config.web or WebConfig()).model_dump(), "listen": args.listen}
            )
        except ValidationError as error:
            raise ConfigError(f"--listen: {describe_validation(error)}") from None
        config = config.model_copy(update={"web": web})
    _setup_daemon_logging(config.log_level)
    server = make_server(config)
    log.info("web: serving %s (Ctrl-C stops)", server.url)
    sys.stdout.flush()
    server.run()
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from mapserver.status import report

    config = load_config(args.config)
    found = report(config)
    sys.stdout.write("\n".join(found.lines(config)) + "\n")
    return 0 if found.running else _NOT_RUNNING


# The exit code of ``status`` when no daemon runs (LSB's "program is not running").
_NOT_RUNNING = 3


def _cmd_requeue(args: argparse.Namespace) -> int:
    from mapserver.requeue import failed_since, parse_time, requeue

    config = load_config(args.config)
    ids = list(args.ids)
    if args.failed_since is not None:
        try:
            since = parse_time(args.failed_since)
        except ValueError:
            raise MapserverError(
                f"--failed-since: not a date or time: {args.failed_since!r} (give 2026-11-21 "
                "or 2026-11-21T10:15:00Z)",
                stage="requeue",
            ) from None
        ids += failed_since(config, since)
        if not ids:
            sys.stdout.write(f"no bundle in {config.failed} failed since {since.isoformat()}\n")
            return 0
    elif not ids:
        raise MapserverError("give the ids of failed bundles, or --failed-since DATE")
    for done in requeue(config, ids):
        sys.stdout.write(
            f"requeued {done.bundle_id} (failed {done.failed_at} at stage {done.stage}: "
            f"{done.reason}) -> {done.path}\n"
        )
    return 0


# -- mapserver bundle (the robot side) -------------------------------------------------------


def _pose_arg(text: str) -> dict[str, float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f"expected x,y,yaw (metres, metres, radians: three finite numbers), got {text!r}"
        )
    return {"x": values[0], "y": values[1], "yaw": values[2]}


def _read_trajectory(path: Path) -> list[dict[str, float]]:
    """Poses from a YAML/JSON list ({x, y, yaw} or [x, y, yaw]) or text lines ``x y yaw`` /
    ``x,y,yaw`` (``#`` starts a comment)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise MapserverError(
            f"cannot read the trajectory: {error}", file=path, stage="bundle"
        ) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        data = None
    if isinstance(data, dict) and "trajectory" in data:
        data = data["trajectory"]
    rows: list[Any]
    if isinstance(data, list):
        rows = data
    else:
        rows = []
        for line in text.splitlines():
            line = line.split("#", 1)[0].replace(",", " ").strip()
            if line:
                rows.append(line.split())
    poses = []
    for number, row in enumerate(rows, start=1):
        if isinstance(row, dict):
            row = [row.get("x"), row.get("y"), row.get("yaw")]
        try:
            x, y, yaw = (float(v) for v in row)
        except (TypeError, ValueError):
            raise MapserverError(
                f"pose {number}: expected x, y, yaw, got {row!r}", file=path, stage="bundle"
            ) from None
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise MapserverError(f"pose {number}: not finite", file=path, stage="bundle")
        poses.append({"x": x, "y": y, "yaw": yaw})
    return poses


def _copy_map(map_yaml: Path, out_dir: Path, stem: str) -> list[str]:
    """Copy a map YAML and its image into ``out_dir`` as ``<stem>.yaml`` / ``<stem>.<ext>``."""
    try:
        data = yaml.safe_load(map_yaml.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise MapFileError(f"cannot read the map YAML: {error}", file=map_yaml) from None
    if not isinstance(data, dict) or not isinstance(data.get("image"), str):
        raise MapFileError("map YAML has no 'image:' entry", file=map_yaml)
    image = Path(data["image"])
    image = image if image.is_absolute() else map_yaml.parent / image
    if not image.is_file():
        raise MapFileError(f"the image '{data['image']}' is not there", file=map_yaml)
    from mapserver.maps import load_map

    # Read as the server will (its default limits): a map it would refuse is refused here, not
    # after the upload (session 53's review: a YAML without resolution, a text file as image).
    defaults = Config()
    load_map(
        map_yaml,
        max_pixels=defaults.max_image_pixels,
        resolution_range_m=defaults.limits.resolution_range_m,
        max_extent_m=defaults.limits.max_map_extent_m,
    )
    image_name = stem + (image.suffix.lower() or ".pgm")
    try:
        shutil.copyfile(image, out_dir / image_name)
    except OSError as error:
        raise MapFileError(
            f"cannot copy the image '{data['image']}' into {out_dir}: {error.strerror or error}",
            file=map_yaml,
        ) from None
    data["image"] = image_name
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None)
    (out_dir / f"{stem}.yaml").write_text(text, encoding="utf-8")
    return [f"{stem}.yaml", image_name]


def _utc_stamp() -> str:
    return datetime.now(timezone.utc).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def _cmd_bundle(args: argparse.Namespace) -> int:
    from mapserver.bundle import (
        MANIFEST,
        check_bundle_files,
        is_valid_bundle_id,
        parse_manifest,
        sha256_file,
        upload_commands,
    )

    out_dir = Path(args.output)
    bundle_id = out_dir.resolve().name
    if not is_valid_bundle_id(bundle_id):
        raise MapserverError(
            f"the output directory's name is the bundle id, and {bundle_id!r} is not a valid one: "
            "use 1 to 128 letters, digits, '.', '_' and '-', starting with a letter or digit",
            stage="bundle",
        )
    if out_dir.exists() and any(out_dir.iterdir()):
        raise MapserverError("the output directory exists and is not empty", file=out_dir)
    robot = args.robot or (re.sub(r"[^A-Za-z0-9._-]", "_", socket.gethostname()) or "robot")
    trajectory = _read_trajectory(args.trajectory) if args.trajectory is not None else None
    created = not out_dir.exists()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise MapserverError(
            f"cannot make the output directory: {error.strerror or error}", file=out_dir
        ) from None
    try:
        files = _copy_map(args.slam_map, out_dir, "slam_map")
        manifest: dict[str, object] = {
            "format": 1,
            "robot": robot,
            "stamp": args.stamp or _utc_stamp(),
            "slam_map": "slam_map.yaml",
        }
        if args.nav2_map is not None:
            files += _copy_map(args.nav2_map, out_dir, "nav2_map")
            manifest["nav2_map"] = "nav2_map.yaml"
        manifest["pose"] = {"nav2": args.nav2_pose, "slam": args.slam_pose}
        if trajectory is not None:
            manifest["trajectory"] = trajectory
        manifest["checksums"] = {name: sha256_file(out_dir / name) for name in files}
        text = yaml.safe_dump(manifest, sort_keys=False, default_flow_style=None)
        parse_manifest(text, source=out_dir / MANIFEST)  # refuse a manifest the server rejects
        partial = out_dir / f".{MANIFEST}.tmp"
        partial.write_text(text, encoding="utf-8")
        os.rename(partial, out_dir / MANIFEST)
        check_bundle_files(out_dir, verify_checksums=False)  # the checksums were just made
    except BaseException:
        if created:  # leave nothing half-made behind
            shutil.rmtree(out_dir, ignore_errors=True)
        raise
    maps_call, manifest_call = upload_commands(str(args.output), args.upload_to)
    sys.stdout.write(
        f"wrote bundle {bundle_id} in {out_dir.resolve()} ({len(files) + 1} files)\n"
        "upload it with two rsync calls, the manifest last and only once the maps arrived "
        "(README: Deploying):\n"
        f"  {shlex.join(maps_call)} \\\n    && {shlex.join(manifest_call)}\n"
    )
    return 0


# -- mapserver demo --------------------------------------------------------------------------

SAMPLES = Path(__file__).parent / "data" / "samples"
_DEMO_DIRS = ("inbox", "outbox", "archive", "failed", "maps")


def _prepare_demo_dir(root: Path) -> None:
    if root.exists() and any(root.iterdir()):
        if not (root / DEMO_MARKER).is_file():
            raise MapserverError(
                "exists and is not a demo folder made by 'mapserver demo'; choose another with "
                "--dir",
                file=root,
                stage="demo",
            )
        _stop_demo_web(root)
        for name in _DEMO_DIRS:  # what the previous demo made, nothing else
            shutil.rmtree(root / name, ignore_errors=True)
    root.mkdir(parents=True, exist_ok=True)
    (root / DEMO_MARKER).write_text("made by 'mapserver demo'; it may delete its subfolders\n")
    for name in _DEMO_DIRS:  # made here: the daemon warns about folders it has to create
        (root / name).mkdir()
    config: dict[str, Any] = {name: name for name in _DEMO_DIRS}
    config.update(settle_seconds=0.5, rescan_seconds=10, stale_after_seconds=60)
    # The demo publishes at once what three sessions confirm; a deployment's default is review.
    config["update"] = {"mode": "auto"}
    (root / "mapserver.yaml").write_text(yaml.safe_dump(config, sort_keys=False))


_DEMO_WEB_PID = "web.pid"
# The demo's web pages: the web command's default port, else any free one.
_DEMO_PORT = 8350


def _stop_demo_web(root: Path) -> None:
    """Stop the web server an earlier demo left running in this folder (its pid file)."""
    pid_file = root / _DEMO_WEB_PID
    try:
        pid = int(pid_file.read_text().split()[0])
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (OSError, ValueError, IndexError):
        pid_file.unlink(missing_ok=True)
        return
    if b"mapserver" in cmdline and str(root).encode() in cmdline:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    pid_file.unlink(missing_ok=True)


def _free_port(preferred: int) -> int:
    for port in (preferred, 0):
        with socket.socket() as probe:
            # As uvicorn binds: a port in TIME_WAIT after an earlier demo is free for it.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
            return int(probe.getsockname()[1])
    raise MapserverError("no free port on 127.0.0.1 for the demo's web pages", stage="demo")


def _start_demo_web(root: Path) -> tuple[str, int] | None:
    """Start ``mapserver web`` on the demo folder, detached (it outlives the demo, so that the
    operator can look); returns its URL and pid, or None when it did not come up."""
    port = _free_port(_DEMO_PORT)
    log_path = root / "web.log"
    with log_path.open("wb") as log_file:
        process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "mapserver.cli",
                "web",
                "--config",
                str(root / "mapserver.yaml"),
                "--listen",
                f"127.0.0.1:{port}",
            ],
            stdout=log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    (root / _DEMO_WEB_PID).write_text(f"{process.pid}\n")

    def listening() -> bool:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return True
        except OSError:
            return False

    if not _wait_for(listening, time.monotonic() + 30, process):
        return None
    return f"http://127.0.0.1:{port}/", process.pid


def _upload_like_rsync(bundle: Path, inbox: Path) -> None:
    """Copy a bundle the way ``rsync`` does it: each file under a dot-temp name, then renamed;
    the maps first, ``bundle.yaml`` last (the README's second rsync call)."""
    target = inbox / bundle.name
    target.mkdir()
    files = sorted(p for p in bundle.iterdir() if p.is_file())
    files.sort(key=lambda p: p.name == "bundle.yaml")
    for source in files:
        temp = target / f".{source.name}.{os.urandom(3).hex()}"
        shutil.copy2(source, temp)
        os.rename(temp, target / source.name)


def _wait_for(
    predicate: Callable[[], bool], deadline: float, daemon: subprocess.Popen[bytes]
) -> bool:
    while time.monotonic() < deadline:
        if predicate():
            return True
        if daemon.poll() is not None:
            return predicate()
        time.sleep(0.05)
    return predicate()


def _any_file(*paths: Path) -> bool:
    return any(p.is_file() for p in paths)


def _describe_result(bundle_id: str, result_dir: Path) -> list[str]:
    result = yaml.safe_load((result_dir / "result.yaml").read_text(encoding="utf-8"))
    differences = result.get("differences") or []
    alignment = result.get("alignment") or {}
    lines = [
        f"{bundle_id}: {result.get('status', 'ok')}, {len(differences)} differences "
        f"(alignment {alignment.get('method', '?')}, score {alignment.get('score', '?')})",
        f"  result.yaml  {result_dir / 'result.yaml'}",
        f"  overlay.png  {result_dir / 'overlay.png'}",
    ]
    notice = trust_notice(alignment)
    if notice:
        lines.insert(1, f"  {notice}")
    lines += [_difference_line(d) for d in differences]
    return lines


def _demo_maps(root: Path, bundles: list[Path]) -> list[str]:
    """Register each sample's global map in the demo's map store, named after the first bundle
    that carries it (``depot-demo-01`` -> ``depot``). Returns what it did, a line each."""
    from mapserver.bundle import read_manifest, sha256_file
    from mapserver.config import load_config
    from mapserver.fleet.store import FleetStore

    config = load_config(root / "mapserver.yaml")
    assert config.maps is not None
    lines: list[str] = []
    seen: set[str] = set()
    with FleetStore(config.maps, config.update) as store:
        for bundle in bundles:
            nav2 = read_manifest(bundle).nav2_map
            if nav2 is None:
                continue
            yaml_path = bundle / nav2
            from mapserver.bundle import map_image_name

            digest = sha256_file(yaml_path.parent / map_image_name(yaml_path))
            if digest in seen:
                continue
            seen.add(digest)
            name = bundle.name.split("-")[0] or bundle.name
            if name in {m.name for m in store.maps()}:
                name = bundle.name
            v = store.add_map(name, yaml_path)
            lines.append(f"map {name}: version 1 from {bundle.name}'s global map -> {v.yaml}")
    return lines


def _describe_maps(root: Path) -> list[str]:
    from mapserver.config import load_config
    from mapserver.fleet.store import FleetStore

    config = load_config(root / "mapserver.yaml")
    assert config.maps is not None
    lines = []
    with FleetStore(config.maps, config.update) as store:
        for m in store.maps():
            changes = store.changes(m.name)
            published = [c for c in changes if c.state == "published"]
            lines.append(
                f"fleet map {m.name}: version {m.current_version} -> "
                f"{config.maps / m.name / 'current.yaml'} (what Nav2's map_server loads)"
            )
            for v in store.versions(m.name)[1:]:
                lines.append(
                    f"  version {v.version}: changes {', '.join(map(str, v.changes))} ({v.note})"
                )
            for c in changes:
                lines.append(
                    f"  change {c.id}: {c.kind} {c.state}, seen in {c.sessions} "
                    f"session{'s' if c.sessions != 1 else ''} by "
                    f"{', '.join(c.robots)}" + (f"; {c.note}" if c.note else "")
                )
            if not published:
                u = config.update
                lines.append(
                    f"  nothing published yet: a change needs {u.confirm_sessions} sessions "
                    f"over {u.confirm_span_hours:g} hours"
                )
    return lines


def _cmd_demo(args: argparse.Namespace) -> int:
    root = Path(args.dir).resolve()
    samples = Path(args.samples) if args.samples else SAMPLES
    bundles = (
        sorted(p for p in samples.iterdir() if (p / "bundle.yaml").is_file())
        if samples.is_dir()
        else []
    )
    if not bundles:
        raise MapserverError("no sample bundles here", file=samples, stage="demo")
    try:
        _prepare_demo_dir(root)
    except OSError as refused:
        raise MapserverError(
            f"cannot make the demo folder: {refused.strerror or refused}; choose another with "
            "--dir",
            file=Path(refused.filename) if refused.filename else root,
            stage="demo",
        ) from None
    out = sys.stdout
    out.write(f"demo folder: {root}\n")
    for line in _demo_maps(root, bundles):
        out.write(line + "\n")
    # Sessions happen one after another: the fleet map counts them in that order.
    bundles = _by_stamp(bundles)
    log_path = root / "mapserver.log"
    with log_path.open("wb") as log_file:
        command = [
            sys.executable,
            "-m",
            "mapserver.cli",
            "run",
            "--config",
            str(root / "mapserver.yaml"),
        ]
        daemon = subprocess.Popen(command, stdout=log_file, stderr=subprocess.STDOUT)
        try:
            out.write(f"started the daemon (pid {daemon.pid}); its log: {log_path}\n")
            ready = _wait_for(
                lambda: b"ready:" in log_path.read_bytes(), time.monotonic() + 120, daemon
            )
            if not ready:
                raise MapserverError(
                    "the daemon did not start; see its log", file=log_path, stage="demo"
                )
            out.write(
                f"uploading {len(bundles)} sample bundles the way rsync does, one session "
                "after another...\n"
            )
            ok = True
            deadline = time.monotonic() + 120 + 30 * len(bundles)
            for bundle in bundles:
                _upload_like_rsync(bundle, root / "inbox")
                result_dir = root / "outbox" / bundle.name
                error = root / "failed" / bundle.name / "error.yaml"
                done = functools.partial(_any_file, result_dir / "result.yaml", error)
                if not _wait_for(done, deadline, daemon):
                    out.write(f"{bundle.name}: no result in time; see {log_path}\n")
                    ok = False
                elif error.is_file():
                    doc = yaml.safe_load(error.read_text(encoding="utf-8"))
                    out.write(
                        f"{bundle.name}: failed at stage {doc.get('stage')}: {doc.get('reason')}\n"
                        f"  error.yaml  {error}\n"
                    )
                    ok = False
                else:
                    out.write("\n".join(_describe_result(bundle.name, result_dir)) + "\n")
        finally:
            daemon.send_signal(signal.SIGTERM)
            try:
                code = daemon.wait(timeout=90)
            except subprocess.TimeoutExpired:
                daemon.kill()
                code = daemon.wait()
    out.write(
        f"stopped the daemon (exit code {code}). Inputs as they arrived: {root / 'archive'}\n"
    )
    for line in _describe_maps(root):
        out.write(line + "\n")
    web = _start_demo_web(root)
    if web is None:
        out.write(f"the web pages did not start; see {root / 'web.log'}\n")
        return 1
    url, pid = web
    if not url.endswith(f":{_DEMO_PORT}/"):
        out.write(f"port {_DEMO_PORT} is taken on 127.0.0.1: the web pages use another one\n")
    out.write(
        f"\nopen {url} : the demo's results, its failures and the depot map with its changes "
        f"and versions.\nThe page server keeps running (pid {pid}); stop it with: kill {pid}\n"
    )
    return 0 if ok and code == 0 else 1


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mapserver")
    except PackageNotFoundError:  # run from a source tree that is not installed
        import mapserver

        return mapserver.__version__


def _command(
    sub: Any, name: str, summary: str, description: str, example: str
) -> argparse.ArgumentParser:
    parser: argparse.ArgumentParser = sub.add_parser(
        name,
        help=summary,
        description=textwrap.fill(description, 79),
        epilog=f"example:\n{example}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    return parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mapserver",
        description=textwrap.fill(
            "mapserver: robots upload bundles (a SLAM map, the map they navigated on, one pose "
            "in both); mapserver aligns the maps and reports the obstacles added and removed. "
            "'mapserver run' is the daemon; the other commands are for one-off work and for the "
            "operator.",
            79,
        ),
        epilog="examples:\n"
        "  mapserver status --config /etc/mapserver/mapserver.yaml\n"
        "  mapserver process --outbox /tmp/results ~/bundles/run-0042\n"
        "  mapserver demo\n"
        "'mapserver COMMAND --help' explains each command.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mapserver {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = _command(
        sub,
        "run",
        "the daemon: watch the inbox and process every bundle (until SIGTERM or Ctrl-C)",
        "Watch the inbox, take each bundle once its upload is complete, process it in a pool of "
        "worker processes, and write outbox/<id>/ (result.yaml, overlay.png, diff.png); the "
        "bundle moves to archive/, or to failed/ with error.yaml saying why. One daemon per "
        "inbox: a second one exits 1. SIGTERM or Ctrl-C finishes the bundles in hand and exits "
        "0. Under systemd, use deploy/systemd/mapserver.service.",
        "  mapserver run --config /etc/mapserver/mapserver.yaml",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.add_argument(
        "--no-web",
        action="store_true",
        help="do not serve the web pages even when the configuration's web: is set (systemd runs "
        "them in a unit of their own)",
    )
    p.set_defaults(func=_cmd_run)

    p = _command(
        sub,
        "web",
        "the operator's web pages, HTTP API and /metrics (until Ctrl-C)",
        "Serve the dashboard, each bundle's result, the maps with their tracked changes and "
        "versions (approve, reject, rollback with the review token), the JSON API (its schema "
        "at /docs), current.yaml for robots (with ETag), /healthz and /metrics (Prometheus). "
        "Reads the folders and the map store; only the review actions write. The address is "
        "web.listen (127.0.0.1:8350 by default); any other than the loopback needs "
        "web.token_file.",
        "  mapserver web --config /etc/mapserver/mapserver.yaml\n"
        "  curl -s http://127.0.0.1:8350/api/maps",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.add_argument("--listen", default=None, metavar="HOST:PORT", help="instead of web.listen")
    p.set_defaults(func=_cmd_web)

    p = _command(
        sub,
        "status",
        "is the daemon running; its queue, the last 24 h, the free space (exit 3: not running)",
        "Say whether a daemon serves this configuration's inbox (and its pid), how many bundles "
        "are uploading, queued and processing, the results and failures of the last 24 hours "
        "(the failures with their reason), and the free space of each folder. Exit code 0 when "
        "the daemon runs, 3 when it does not (for monitoring).",
        "  mapserver status --config /etc/mapserver/mapserver.yaml || echo 'mapserver is down'",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.set_defaults(func=_cmd_status)

    p = _command(
        sub,
        "requeue",
        "send failed bundles back to the inbox, to be processed again",
        "Move each failed bundle (failed/<id>/) back into the inbox by one rename, once the "
        "cause is fixed (a missing reference_map, a limit raised, an upgrade); the daemon, "
        "running or started later, takes it like any upload. Its error.yaml stays with it as "
        ".mapserver-history/error-<n>.yaml (the server never reads dot-names). An id that is "
        "not in failed/ is refused (exit 1), and then nothing is moved.",
        "  mapserver requeue --config /etc/mapserver/mapserver.yaml run-0042 run-0043\n"
        "  mapserver requeue --config /etc/mapserver/mapserver.yaml --failed-since 2026-11-21",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.add_argument(
        "--failed-since",
        default=None,
        metavar="DATE",
        help="every bundle that failed at or after DATE (2026-11-21, or 2026-11-21T10:15:00Z; "
        "UTC when no zone is given)",
    )
    p.add_argument("ids", nargs="*", metavar="ID", help="a bundle id in failed/")
    p.set_defaults(func=_cmd_requeue)

    p = _command(
        sub,
        "process",
        "process bundle folders once, without the daemon",
        "Process each bundle folder given, write its result to the outbox (replacing an earlier "
        "result of the same id, and saying so), and print one line per bundle and one per "
        "difference. The bundles are left as they are. Exit code 0 when every bundle "
        "succeeded, 1 otherwise (one error line per bundle that did not).",
        "  mapserver process --outbox /tmp/results ~/bundles/run-0042 ~/bundles/run-0043",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.add_argument(
        "--outbox",
        type=Path,
        default=None,
        metavar="DIR",
        help="where results go (default: the configuration's outbox)",
    )
    p.add_argument("bundles", nargs="+", metavar="BUNDLE_DIR", help="a bundle folder")
    p.set_defaults(func=_cmd_process)

    p = _command(
        sub,
        "check-config",
        "validate a configuration file and print every setting in effect",
        "Read the configuration file, report every bad key or value (and a missing "
        "reference_map) in one line, and print the effective settings, defaults included. Exit "
        "code 1 when the file is wrong.",
        "  mapserver check-config --config /etc/mapserver/mapserver.yaml",
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.set_defaults(func=_cmd_check_config)

    p = _command(
        sub,
        "bundle",
        "write a bundle folder on a robot, ready to upload",
        "Copy the robot's SLAM map and (optionally) the map it navigated on into a new bundle "
        "folder, with bundle.yaml: the pose in both frames, the trajectory, the sha256 of each "
        "map file. The folder's name is the bundle id. Poses are x,y,yaw in metres and "
        "radians; negative numbers are fine (--slam-pose -1.5,2,0).",
        "  mapserver bundle --slam-map ~/maps/session.yaml --nav2-map /opt/maps/depot.yaml \\\n"
        "      --nav2-pose 12.3,-4.5,1.5708 --slam-pose -0.8,0.1,0.02 -o run-0042",
    )
    p.add_argument("--slam-map", type=Path, required=True, help="slam_toolbox map YAML")
    p.add_argument("--nav2-map", type=Path, default=None, help="global map YAML (optional)")
    p.add_argument("--nav2-pose", type=_pose_arg, required=True, metavar="X,Y,YAW")
    p.add_argument("--slam-pose", type=_pose_arg, required=True, metavar="X,Y,YAW")
    p.add_argument(
        "--trajectory",
        type=Path,
        default=None,
        metavar="FILE",
        help="slam-frame poses, oldest first: lines 'x y yaw' or a YAML list",
    )
    p.add_argument("--robot", default=None, help="robot id (default: the host name)")
    p.add_argument(
        "--upload-to",
        default=UPLOAD_TO,
        metavar="DEST",
        help=f"the rsync destination of the inbox, in the upload commands printed (default: "
        f"{UPLOAD_TO}, the ssh host of the README's deployment)",
    )
    p.add_argument("--stamp", default=None, help="when the maps were saved (default: now)")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        metavar="DIR",
        help="the bundle directory to create; its name is the bundle id",
    )
    p.set_defaults(func=_cmd_bundle)

    register_fleet_commands(sub)

    p = _command(
        sub,
        "demo",
        "see it work: a real daemon on the shipped sample bundles",
        "Make a demo folder, start the daemon on it, upload the shipped sample bundles the way "
        "rsync does, print each result and where its files are, and stop the daemon. The web "
        "pages showing it all keep running (on 127.0.0.1:8350, or a free port when that one is "
        "taken): the demo prints their URL and how to stop them; the next demo in the same "
        "folder stops them first.",
        "  mapserver demo --dir /tmp/mapserver-demo",
    )
    p.add_argument(
        "--dir",
        type=Path,
        default=Path("mapserver-demo"),
        help="the demo folder (default: ./mapserver-demo)",
    )
    p.add_argument(
        "--samples",
        type=Path,
        default=None,
        help="a folder of bundle folders to upload instead of the shipped samples",
    )
    p.set_defaults(func=_cmd_demo)
    return parser


def _join_negative_poses(argv: list[str], options: set[str]) -> list[str]:
    """``--nav2-pose -1,2,0`` as ``--nav2-pose=-1,2,0``: argparse takes a value that starts
    with '-' (and is not one plain number) for an option."""
    out: list[str] = []
    args = iter(argv)
    for arg in args:
        if arg == "--":
            out += [arg, *args]
            break
        if arg in options:
            value = next(args, None)
            if value is not None and re.match(r"-[0-9.]", value):
                out.append(f"{arg}={value}")
                continue
            out.append(arg)
            if value is not None:
                out.append(value)
            continue
        out.append(arg)
    return out


def _pose_options(parser: argparse.ArgumentParser) -> set[str]:
    """The option strings, in every subcommand, whose value is a pose."""
    found = set()
    for action in parser._actions:  # argparse has no public walk of its parsers
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                found |= _pose_options(subparser)
        elif action.type is _pose_arg:
            found.update(action.option_strings)
    return found


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    raw = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(_join_negative_poses(raw, _pose_options(parser)))
    try:
        return int(args.func(args))
    except MapserverError as error:
        sys.stderr.write(f"mapserver: error: {error.reason}\n")
        return 1


if __name__ == "__main__":
    sys.exit(main())
