"""The exception tree of mapserver.

Every error the product raises on bad input derives from :class:`MapserverError` and carries
enough context (the stage, the file, the field) to write one line a person can act on.

``MapserverError``
    ``ConfigError``      -- the configuration file is wrong (unknown key, bad value).
    ``MapFileError``     -- a map YAML or image cannot be read or is invalid.
    ``BundleError``      -- a bundle manifest or its files are wrong (bad field, checksum, path).
        ``BundleIncomplete`` -- not an error yet: some file is missing or still changing.
    ``ProcessingError``  -- the pipeline failed on otherwise valid input.
    ``StoreError``       -- the map store refused an operation or cannot be used.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pydantic import ValidationError


class MapserverError(Exception):
    """Base class: a problem with an input, with the file and stage it concerns.

    Parameters
    ----------
    problem
        What is wrong, in words a person can act on.
    file
        The file the problem is in, when there is one.
    stage
        The pipeline stage that found it (``config``, ``bundle``, ``load``, ``align``, ...).
    """

    default_stage = "process"

    def __init__(self, problem: str, *, file: str | Path | None = None, stage: str | None = None):
        self.problem = problem
        self.file = Path(file) if file is not None else None
        self.stage = stage or self.default_stage
        super().__init__(self.reason)

    @property
    def reason(self) -> str:
        """One line: ``<file>: <problem>``, or just the problem when no file is known."""
        text = self.problem if self.file is None else f"{self.file}: {self.problem}"
        return " ".join(text.split())


class ConfigError(MapserverError):
    default_stage = "config"


class MapFileError(MapserverError):
    default_stage = "load"


class BundleError(MapserverError):
    default_stage = "bundle"


class BundleIncomplete(BundleError):
    """The bundle is not complete yet (a file is missing, or its checksum does not match yet)."""


class ProcessingError(MapserverError):
    default_stage = "process"


class StoreError(MapserverError):
    """The map store (contract section 7) refused an operation (an unknown map or change, a
    change not in a state that allows it) or cannot be used (its database missing or damaged)."""

    default_stage = "update"


def describe_validation(error: ValidationError) -> str:
    """One line for a person from a pydantic validation error: every bad field named."""
    parts = []
    for item in error.errors():
        key = ".".join(str(p) for p in item["loc"]) or "(top level)"
        if item["type"] == "extra_forbidden":
            parts.append(f"unknown key '{key}'")
        elif item["type"] == "missing":
            parts.append(f"missing key '{key}'")
        else:
            parts.append(f"'{key}': {item['msg']}")
    return "; ".join(parts)
