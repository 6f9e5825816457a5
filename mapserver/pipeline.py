"""The only module that knows the order of the stages: load, align, roi, diff, cluster, render.

``process_bundle`` turns a bundle directory into an :class:`Outcome` (the result document and the
encoded images) without writing anything; publishing it is :mod:`mapserver.outbox`'s job.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mapserver.config import Config


@dataclass(frozen=True)
class Outcome:
    """What processing one bundle produced.

    ``result`` is the ``result.yaml`` document (contract section 3); ``images`` maps file names
    (``overlay.png``, ``diff.png``) to PNG bytes.
    """

    bundle_id: str
    result: dict[str, Any]
    images: dict[str, bytes]


def process_bundle(bundle_dir: Path, config: Config, *, bundle_id: str | None = None) -> Outcome:
    """Process one complete bundle. Raises a :class:`~mapserver.errors.MapserverError` subclass
    for bad input (its ``stage`` says where it failed). Reads the inputs, never modifies them."""
    raise NotImplementedError
