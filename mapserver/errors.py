"""The exception tree of mapserver.

Every error the product raises on bad input derives from :class:`MapserverError` and carries
enough context (the stage, the file, the field) to write one line a person can act on.

``MapserverError``
    ``ConfigError``      -- the configuration file is wrong (unknown key, bad value).
    ``MapFileError``     -- a map YAML or image cannot be read or is invalid.
    ``BundleError``      -- a bundle manifest or its files are wrong (bad field, checksum, path).
        ``ManifestNotYaml`` -- bundle.yaml is not YAML (in an inbox: not yet).
        ``BundleIncomplete`` -- not an error yet: some file is missing or still changing.
            ``ChecksumMismatch`` -- a file's sha256 is not the manifest's (yet).
    ``ProcessingError``  -- the pipeline failed on otherwise valid input.
        ``OutOfMemory``  -- a stage ran out of memory (the daemon's workers have a limit).
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
    def problem_line(self) -> str:
        """The problem on one line, without the file: for a message that names the place."""
        return " ".join(self.problem.split())

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


class ManifestNotYaml(BundleError):
    """``bundle.yaml`` is not YAML: a bundle said to be complete is wrong; in an inbox, where a
    bundle is complete only once its manifest parses (contract section 2), an upload that may
    still be writing it in place."""


class BundleIncomplete(BundleError):
    """The bundle is not complete yet (a file is missing, or its checksum does not match yet)."""


class FileNotThere(BundleIncomplete):
    """A file the bundle names is not there: not yet, while an upload goes on; missing, for a
    bundle said to be complete (``mapserver process``). ``what`` names it ("nav2_map
    'map.yaml'")."""

    def __init__(self, what: str, *, file: str | Path) -> None:
        self.what = what
        super().__init__(f"{what} is not there yet", file=file)


class ChecksumMismatch(BundleIncomplete):
    """Every file is there, and one's sha256 is not the one the manifest gives: still being
    rewritten, or a bundle that will never be right. ``expected`` and ``actual`` are hex."""

    def __init__(self, name: str, *, expected: str, actual: str, file: str | Path) -> None:
        self.name = name
        self.expected = expected
        self.actual = actual
        super().__init__(
            f"sha256 of '{name}' does not match the manifest: expected {expected}, actual {actual}",
            file=file,
        )


class ProcessingError(MapserverError):
    default_stage = "process"


class OutOfMemory(ProcessingError):
    """A stage could not allocate the memory it needed."""


class StoreError(MapserverError):
    """The map store (contract section 7) refused an operation (an unknown map or change, a
    change not in a state that allows it) or cannot be used (its database missing or damaged)."""

    default_stage = "update"


def no_such_path(path: Path) -> str:
    """The problem with a path that does not exist, for one line of a message: which part of it
    is missing, and the names beside it that are close (a misspelt path)."""
    import difflib

    path = Path(path)
    missing = path
    while not missing.parent.exists() and missing.parent != missing:
        missing = missing.parent
    text = "no such file or directory"
    if missing != path:
        text += f" (there is no {missing})"
    try:
        names = [p.name for p in missing.parent.iterdir()]
    except OSError:
        return text
    close = difflib.get_close_matches(missing.name, names, n=3, cutoff=0.6)
    if close:
        rest = path.relative_to(missing)
        guesses = [str(missing.parent / name / rest) for name in close]
        text += f"; did you mean {' or '.join(guesses)}?"
    return text


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
