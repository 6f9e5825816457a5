"""``mapserver maps ...`` and ``mapserver changes ...``: the operator's commands of the fleet map.

Every command opens the store of the configuration's ``maps:``, does one thing, prints what it
did, and exits 1 with one line (``mapserver: error: ...``) when it cannot, changing nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mapserver.config import CONFIG_HELP, Config, load_config
from mapserver.errors import ConfigError
from mapserver.fleet.db import MAX_ROW_ID


def open_store(config: Config, *, create: bool = False) -> Any:
    from mapserver.fleet.store import FleetStore

    if config.maps is None:
        raise ConfigError(
            "the fleet map is off in this configuration ('maps: null'): set 'maps:' to the map "
            "store's folder, for example 'maps: /var/lib/mapserver/maps'"
        )
    return FleetStore(config.maps, config.update, create=create)


def _cmd_maps_add(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    with open_store(config, create=True) as store:
        v = store.add_map(args.name, args.map_yaml, max_pixels=config.max_image_pixels)
    folder = v.yaml.parent
    sys.stdout.write(
        f"map {v.map}: version 1 stored as {v.yaml} (sha256 {v.sha256[:12]}...)\n"
        f"point Nav2's map_server at {folder / 'current.yaml'}; "
        f"its keepout mask is {folder / 'keepout.yaml'}\n"
    )
    return 0


def _cmd_maps_list(args: argparse.Namespace) -> int:
    with open_store(load_config(args.config)) as store:
        maps = store.maps()
    if not maps:
        sys.stdout.write(
            "no maps in the store yet (add one with 'mapserver maps add NAME MAP_YAML')\n"
        )
        return 0
    sys.stdout.write(
        f"{'map':<24} {'version':>7} {'size':>11} {'res m':>6} {'bundles':>8}  changes\n"
    )
    for m in maps:
        counts = ", ".join(f"{n} {s}" for s, n in m.counts.items() if n)
        size = f"{m.lattice.width}x{m.lattice.height}"
        sys.stdout.write(
            f"{m.name:<24} {m.current_version:>7} {size:>11} {m.lattice.resolution:>6.3f} "
            f"{m.bundles:>8}  {counts or 'none'}\n"
        )
    return 0


def _cmd_maps_show(args: argparse.Namespace) -> int:
    with open_store(load_config(args.config)) as store:
        info = store.map_info(args.name)
        versions = store.versions(args.name)
    lat = info.lattice
    sys.stdout.write(
        f"map {info.name}: {lat.width}x{lat.height} cells at {lat.resolution:g} m, origin "
        f"({lat.x0:g}, {lat.y0:g}), {info.bundles} bundles applied; current version "
        f"{info.current_version}\n"
    )
    for v in versions:
        changes = ", ".join(str(c) for c in v.changes) or "-"
        sys.stdout.write(
            f"  v{v.version:<4} {v.created_at}  sha256 {v.sha256[:12]}  changes {changes}  "
            f"({v.note})\n"
        )
    return 0


def _cmd_maps_rollback(args: argparse.Namespace) -> int:
    with open_store(load_config(args.config)) as store:
        v = store.rollback(args.name, args.version, actor=_actor())
    sys.stdout.write(
        f"map {v.map}: published version {v.version}, equal to version {args.version} "
        f"-> {v.yaml.parent / 'current.yaml'}\n"
    )
    return 0


def _change_line(c: Any) -> str:
    xs = [p[0] for p in c.polygon] or [0.0]
    ys = [p[1] for p in c.polygon] or [0.0]
    centre = f"({(min(xs) + max(xs)) / 2:.2f}, {(min(ys) + max(ys)) / 2:.2f})"
    version = f" v{c.version}" if c.version is not None else ""
    return (
        f"{c.id:>5} {c.map:<16} {c.kind:<8} {c.state + version:<14} at {centre:<18} "
        f"{c.sessions:>3} session{'' if c.sessions == 1 else 's'} {c.first_seen} .. {c.last_seen}  "
        f"robots {','.join(c.robots)}{'  ' + c.note if c.note else ''}\n"
    )


def _cmd_changes_list(args: argparse.Namespace) -> int:
    with open_store(load_config(args.config)) as store:
        changes = store.changes(args.map, state=args.state)
    if not changes:
        sys.stdout.write(
            "no tracked changes" + (f" in state {args.state}" if args.state else "") + "\n"
        )
        return 0
    for c in changes:
        sys.stdout.write(_change_line(c))
    return 0


def _cmd_changes_approve(args: argparse.Namespace) -> int:
    with open_store(load_config(args.config)) as store:
        v = store.approve(args.id, actor=_actor())
    sys.stdout.write(
        f"change {args.id} approved: map {v.map} version {v.version} published "
        f"-> {v.yaml.parent / 'current.yaml'}\n"
    )
    return 0


def _cmd_changes_reject(args: argparse.Namespace) -> int:
    with open_store(load_config(args.config)) as store:
        c = store.reject(args.id, actor=_actor())
    sys.stdout.write(f"change {c.id} rejected: it will not be published\n")
    return 0


def _actor() -> str:
    """Who runs this command, for the change's history."""
    import getpass

    try:
        return f"{getpass.getuser()} (command line)"
    except (KeyError, OSError):
        return "command line"


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {value}")
    if value > MAX_ROW_ID:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_ROW_ID}, got {value}")
    return value


def _leaf(
    sub: Any,
    name: str,
    help_text: str,
    func: Any,
    example: str | None = None,
    description: str | None = None,
) -> argparse.ArgumentParser:
    """One ``maps``/``changes`` subcommand: its help, example, ``--config`` and function."""
    extra: dict[str, Any] = {}
    if example is not None:
        extra = {"formatter_class": argparse.RawDescriptionHelpFormatter, "epilog": example}
    p: argparse.ArgumentParser = sub.add_parser(
        name, help=help_text, description=description, **extra
    )
    p.add_argument("--config", type=Path, default=None, metavar="FILE", help=CONFIG_HELP)
    p.set_defaults(func=func)
    return p


def register(sub: Any) -> None:
    """Add the ``maps`` and ``changes`` commands to the ``mapserver`` parser."""
    from mapserver.fleet.model import STATES

    fmt = argparse.RawDescriptionHelpFormatter
    maps = sub.add_parser(
        "maps",
        help="the fleet's building maps and their versions",
        description="The map store (configuration key 'maps:'): each building map, the versions "
        "published from confirmed changes, current.yaml for Nav2's map_server.",
        formatter_class=fmt,
        epilog="example:\n  mapserver maps add depot /opt/maps/depot.yaml --config /etc/mapserver/mapserver.yaml",
    )
    msub = maps.add_subparsers(dest="maps_command", required=True)
    p = _leaf(
        msub,
        "add",
        "register a building map as version 1",
        _cmd_maps_add,
        "example:\n  mapserver maps add depot /opt/maps/depot.yaml\n"
        "then point Nav2's map_server at <maps>/depot/current.yaml",
    )
    p.add_argument("name", help="the map's name: letters, digits, '.', '_', '-'")
    p.add_argument("map_yaml", type=Path, help="the map's YAML (ROS map_server format)")
    _leaf(
        msub,
        "list",
        "the stored maps with their current version",
        _cmd_maps_list,
        "example:\n  mapserver maps list --config /etc/mapserver/mapserver.yaml",
    )
    p = _leaf(
        msub,
        "show",
        "a map's versions: time, changes published, sha256",
        _cmd_maps_show,
        "example:\n  mapserver maps show depot",
    )
    p.add_argument("name")
    p = _leaf(
        msub,
        "rollback",
        "publish a new version equal to an earlier one",
        _cmd_maps_rollback,
        "example:\n  mapserver maps rollback depot 3",
        description="Publishes a NEW version equal to VERSION (history is never rewritten). "
        "Changes published after VERSION become rejected, so that they are not published again.",
    )
    p.add_argument("name")
    p.add_argument("version", type=_positive_int)

    changes = sub.add_parser(
        "changes",
        help="tracked changes of the fleet map: list, approve, reject",
        formatter_class=fmt,
        epilog="example:\n  mapserver changes list --state confirmed\n  mapserver changes approve 17",
    )
    csub = changes.add_subparsers(dest="changes_command", required=True)
    p = _leaf(
        csub,
        "list",
        "tracked changes, oldest first",
        _cmd_changes_list,
        "example:\n  mapserver changes list --state confirmed --map depot",
    )
    p.add_argument("--state", choices=STATES, default=None)
    p.add_argument("--map", default=None, help="only this map's changes")
    p = _leaf(
        csub,
        "approve",
        "publish a confirmed change (review mode)",
        _cmd_changes_approve,
        "example:\n  mapserver changes approve 17",
    )
    p.add_argument("id", type=_positive_int)
    p = _leaf(
        csub,
        "reject",
        "never publish a pending or confirmed change",
        _cmd_changes_reject,
        "example:\n  mapserver changes reject 18",
    )
    p.add_argument("id", type=_positive_int)
