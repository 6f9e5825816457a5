"""A store and outbox built by processing the shipped depot samples, for the web tests."""

from __future__ import annotations

import secrets
import shutil
from pathlib import Path

import yaml

from mapserver.cli import SAMPLES, main
from mapserver.config import Config, load_config

DEPOT = sorted(SAMPLES.glob("depot-demo-*"))
TOKEN = "t0ken-" + "x" * 20


def build_site(root: Path, *, mode: str = "review", page_size: int = 50) -> Config:
    """Process the depot samples (and an office sample that fails) into ``root`` with a map
    store in ``mode``; return the configuration (web token in ``root/token``)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "token").write_text(TOKEN + "\n")
    cfg = root / "mapserver.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "maps": "maps",
                "update": {"mode": mode},
                "log_level": "WARNING",
                "web": {"token_file": "token", "page_size": page_size},
            }
        )
    )
    assert (
        main(["maps", "add", "depot", str(DEPOT[0] / "nav2_map.yaml"), "--config", str(cfg)]) == 0
    )
    assert main(["process", "--config", str(cfg), *map(str, DEPOT)]) == 0
    config = load_config(cfg)
    failed = config.failed / "broken-upload"
    failed.mkdir(parents=True)
    (failed / "error.yaml").write_text(
        yaml.safe_dump(
            {
                "format": 1,
                "bundle": "broken-upload",
                "failed_at": "2026-11-22T09:00:00.000Z",
                "stage": "bundle",
                "reason": "bundle.yaml: missing key 'pose'",
            }
        )
    )
    return config


def copy_results(config: Config, n: int) -> list[str]:
    """``n`` more results (copies of a sample's, other ids and times) for the paging tests."""
    source = config.outbox / DEPOT[0].name
    ids = []
    for i in range(n):
        bundle_id = f"copy-{i:03d}-{secrets.token_hex(2)}"
        target = config.outbox / bundle_id
        shutil.copytree(source, target)
        doc = yaml.safe_load((target / "result.yaml").read_text())
        doc["bundle"] = bundle_id
        doc["processed_at"] = f"2026-11-23T10:{i // 60:02d}:{i % 60:02d}.000Z"
        (target / "result.yaml").write_text(yaml.safe_dump(doc))
        ids.append(bundle_id)
    return ids
