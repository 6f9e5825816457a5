"""config/mapserver.example.yaml: every key, each at its default except the paths."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from mapserver.config import Config, load_config

EXAMPLE = Path(__file__).resolve().parents[1] / "config" / "mapserver.example.yaml"
PATHS = {"inbox", "outbox", "archive", "failed", "maps"}


def keys(data: dict[str, Any], prefix: str = "") -> set[str]:
    out = set()
    for key, value in data.items():
        out.add(prefix + key)
        if isinstance(value, dict):
            out |= keys(value, f"{prefix}{key}.")
    return out


def test_the_example_loads_and_equals_the_defaults_except_the_paths() -> None:
    config = load_config(EXAMPLE)
    assert config.model_dump(exclude=PATHS) == Config().model_dump(exclude=PATHS), (
        "config/mapserver.example.yaml no longer shows the defaults: update it"
    )
    for key in PATHS:
        assert getattr(config, key) == Path("/var/lib/mapserver") / key


def test_the_example_writes_out_every_key() -> None:
    written = keys(yaml.safe_load(EXAMPLE.read_text()))
    assert written == keys(Config().model_dump(mode="json")), (
        "config/mapserver.example.yaml must name every configuration key"
    )
