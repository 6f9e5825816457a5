"""The ``mapserver`` command: a thin layer over the library. The only place that configures logging."""

from __future__ import annotations

import argparse
import functools
import logging
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import yaml

from mapserver.config import dump_config, load_config
from mapserver.errors import MapFileError, MapserverError
from mapserver.fleet.cli import open_store
from mapserver.fleet.cli import register as register_fleet_commands

log = logging.getLogger("mapserver")


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level),
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stdout,
    )


def _cmd_check_config(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    sys.stdout.write(dump_config(config))
    return 0


def _cmd_process(args: argparse.Namespace) -> int:
    from mapserver.outbox import write_result
    from mapserver.pipeline import process_bundle

    config = load_config(args.config)
    _setup_logging(config.log_level)
    outbox = Path(args.outbox).resolve() if args.outbox else config.outbox
    store = open_store(config, create=True) if config.maps is not None else None
    failures = 0
    try:
        # The fleet map counts bundles in stamp order: process them in that order.
        for bundle_dir in _by_stamp([Path(b) for b in args.bundles]):
            try:
                if not bundle_dir.is_dir():
                    raise MapserverError("not a bundle directory", file=bundle_dir, stage="bundle")
                outcome = process_bundle(bundle_dir, config)
                if store is not None and outcome.observation is not None:
                    update = store.apply(outcome.observation)
                    update.annotate(outcome.result)
                    log.info("%s: update %s", outcome.bundle_id, update.summary())
                final = write_result(outbox, outcome)
            except MapserverError as error:
                failures += 1
                sys.stderr.write(f"mapserver: error: {error.reason}\n")
                continue
            n = len(outcome.result.get("differences", []))
            sys.stdout.write(f"{outcome.bundle_id}: {n} differences -> {final / 'result.yaml'}\n")
    finally:
        if store is not None:
            store.close()
    return 1 if failures else 0


def _by_stamp(bundles: list[Path]) -> list[Path]:
    """Bundles sorted by their manifest's stamp (stable; unreadable ones keep their place at
    the end, where processing reports what is wrong with them)."""
    from mapserver.bundle import read_manifest
    from mapserver.fleet.tracker import parse_stamp

    def key(item: tuple[int, Path]) -> tuple[int, float, int]:
        index, path = item
        try:
            return (0, parse_stamp(read_manifest(path).stamp).timestamp(), index)
        except (MapserverError, OSError, ValueError):
            return (1, 0.0, index)

    return [p for _, p in sorted(enumerate(bundles), key=key)]


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
    _setup_daemon_logging(config.log_level)
    setup = functools.partial(_setup_daemon_logging, config.log_level)
    return Service(config, worker_setup=setup).run()


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
    image_name = stem + (image.suffix.lower() or ".pgm")
    shutil.copyfile(image, out_dir / image_name)
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
    out_dir.mkdir(parents=True, exist_ok=True)
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
    where = out_dir.resolve()
    sys.stdout.write(
        f"wrote bundle {bundle_id} in {where} ({len(files) + 1} files)\n"
        "upload it with two rsync calls, the manifest last:\n"
        f"  rsync -a --exclude={MANIFEST} {where}/ SERVER:INBOX/{bundle_id}/\n"
        f"  rsync -a {where}/{MANIFEST} SERVER:INBOX/{bundle_id}/\n"
    )
    return 0


# -- mapserver demo --------------------------------------------------------------------------

SAMPLES = Path(__file__).parent / "data" / "samples"
_DEMO_MARKER = ".mapserver-demo"
_DEMO_DIRS = ("inbox", "outbox", "archive", "failed", "maps")


def _prepare_demo_dir(root: Path) -> None:
    if root.exists() and any(root.iterdir()):
        if not (root / _DEMO_MARKER).is_file():
            raise MapserverError(
                "exists and is not a demo folder made by 'mapserver demo'; choose another with "
                "--dir",
                file=root,
                stage="demo",
            )
        for name in _DEMO_DIRS:  # what the previous demo made, nothing else
            shutil.rmtree(root / name, ignore_errors=True)
    root.mkdir(parents=True, exist_ok=True)
    (root / _DEMO_MARKER).write_text("made by 'mapserver demo'; it may delete its subfolders\n")
    config: dict[str, Any] = {name: name for name in _DEMO_DIRS}
    config.update(settle_seconds=0.5, rescan_seconds=10, stale_after_seconds=60)
    # The demo publishes at once what three sessions confirm; a deployment's default is review.
    config["update"] = {"mode": "auto"}
    (root / "mapserver.yaml").write_text(yaml.safe_dump(config, sort_keys=False))


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
    for d in differences:
        c, b = d.get("centroid", {}), d.get("bbox", {})
        lines.append(
            f"  {d.get('id')}. {d.get('kind', '?'):7} {d.get('area_m2', 0):7.2f} m2 at "
            f"x={c.get('x', 0):.2f} y={c.get('y', 0):.2f}  "
            f"(box x {b.get('min_x', 0):.2f}..{b.get('max_x', 0):.2f}, "
            f"y {b.get('min_y', 0):.2f}..{b.get('max_y', 0):.2f})"
            + (f"  change {d['change']}" if d.get("change") is not None else "")
        )
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
    _prepare_demo_dir(root)
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
    return 0 if ok and code == 0 else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mapserver", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("process", help="process bundle directories once")
    p.add_argument("--config", type=Path, default=None)
    p.add_argument("--outbox", type=Path, default=None, help="where results go (default: config)")
    p.add_argument("bundles", nargs="+", metavar="BUNDLE_DIR")
    p.set_defaults(func=_cmd_process)

    p = sub.add_parser("check-config", help="validate a configuration and print the effective one")
    p.add_argument("--config", type=Path, default=None)
    p.set_defaults(func=_cmd_check_config)

    p = sub.add_parser("run", help="watch the inbox and process bundles until SIGTERM/SIGINT")
    p.add_argument("--config", type=Path, default=None)
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "bundle",
        help="write a bundle (robot side)",
        description="Write a bundle directory with checksums. Give negative poses with '=': "
        "--nav2-pose=-1.5,2.0,0.3",
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

    p = sub.add_parser("demo", help="process the shipped sample bundles with a real daemon")
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


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except MapserverError as error:
        sys.stderr.write(f"mapserver: error: {error.reason}\n")
        return 1


if __name__ == "__main__":
    sys.exit(main())
