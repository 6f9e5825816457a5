"""The ``mapserver`` command: a thin layer over the library. The only place that configures logging."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from mapserver.config import dump_config, load_config
from mapserver.errors import MapserverError

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
    failures = 0
    for bundle in args.bundles:
        bundle_dir = Path(bundle)
        try:
            if not bundle_dir.is_dir():
                raise MapserverError("not a bundle directory", file=bundle_dir, stage="bundle")
            outcome = process_bundle(bundle_dir, config)
            final = write_result(outbox, outcome)
        except MapserverError as error:
            failures += 1
            sys.stderr.write(f"mapserver: error: {error.reason}\n")
            continue
        n = len(outcome.result.get("differences", []))
        sys.stdout.write(f"{outcome.bundle_id}: {n} differences -> {final / 'result.yaml'}\n")
    return 1 if failures else 0


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
