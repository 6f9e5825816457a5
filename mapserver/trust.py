"""What an alignment's trust means to an operator: the one line the CLI prints, the daemon logs
at WARNING and the overlay carries as a banner. Light on purpose: the daemon's main process
imports it, not the pipeline."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def trust_notice(alignment_doc: Mapping[str, Any]) -> str | None:
    """The line an operator must not miss when a result's alignment (its ``alignment``
    document) was not trusted, or only partly: None when it was trusted whole.

    The CLI prints it, the daemon logs it at WARNING and the overlay carries it as a banner.
    """
    score, min_score = alignment_doc.get("score", 0.0), alignment_doc.get("min_score", 0.0)
    if not alignment_doc.get("trusted", True):
        return (
            f"UNTRUSTED alignment (score {score:.2f} < min_score {min_score:g}): no differences "
            "reported; check the pose prior in bundle.yaml and re-upload"
        )
    share = alignment_doc.get("trusted_share")
    if share is None or share >= 0.995:
        return None
    area = alignment_doc.get("trusted_area_m2", 0.0)
    return (
        f"PARTLY TRUSTED alignment: {share:.0%} of the observed area ({area:.0f} m2) compared, "
        "differences reported there only; the rest was left out"
    )
