"""``/metrics``: the Prometheus exposition of what the pages show, computed at each scrape from
the same sources (the bundle index, the daemon's status file, the map store), so that it reads
the same whether the web runs inside ``mapserver run`` or in a unit of its own."""

from __future__ import annotations

import shutil
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from mapserver.config import Config
from mapserver.web.index import BundleIndex

STAGE_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
SCORE_BUCKETS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0)


def _histogram(
    name: str,
    doc: str,
    values: dict[tuple[str, ...], list[float]],
    labels: list[str],
    buckets: tuple[float, ...],
) -> HistogramMetricFamily:
    family = HistogramMetricFamily(name, doc, labels=labels)
    for label_values, samples in sorted(values.items()):
        ordered = np.sort(np.asarray(samples, float))
        below = np.searchsorted(ordered, np.asarray(buckets), side="right")
        counts = [(repr(bound), float(n)) for bound, n in zip(buckets, below, strict=True)]
        counts.append(("+Inf", float(len(ordered))))
        family.add_metric(list(label_values), counts, sum_value=float(ordered.sum()))
    return family


class MapserverCollector(Collector):
    """Collects at each scrape. ``status`` returns the daemon's status (``mapserver.status``
    report) and ``fleet`` the map store's figures (or None when the fleet map is off)."""

    def __init__(
        self,
        config: Config,
        index: BundleIndex,
        status: Callable[[], Any],
        fleet: Callable[[], list[dict[str, Any]] | None],
    ) -> None:
        self.config = config
        self.index = index
        self.status = status
        self.fleet = fleet

    def collect(self) -> Iterator[Metric]:
        results = self.index.all_results()
        failures = self.index.all_failures()
        yield CounterMetricFamily(
            "mapserver_bundles_processed",
            "Bundles with a result in the outbox.",
            value=len(results),
        )
        failed = CounterMetricFamily(
            "mapserver_bundles_failed",
            "Bundles in failed/, by the stage that failed them.",
            labels=["stage"],
        )
        for stage, n in sorted(Counter(f.stage for f in failures).items()):
            failed.add_metric([stage], n)
        yield failed
        stages: dict[tuple[str, ...], list[float]] = {}
        scores: dict[tuple[str, ...], list[float]] = {(): []}
        for row in results:
            for stage, ms in row.timings_ms.items():
                stages.setdefault((stage,), []).append(ms / 1000.0)
            if row.score is not None:
                scores[()].append(row.score)
        yield _histogram(
            "mapserver_stage_duration_seconds",
            "Time of each processing stage per bundle (from result.yaml's timings).",
            stages,
            ["stage"],
            STAGE_BUCKETS_S,
        )
        yield _histogram(
            "mapserver_alignment_score",
            "Alignment score of each processed bundle (0..1).",
            scores,
            [],
            SCORE_BUCKETS,
        )
        report = self.status()
        up = GaugeMetricFamily("mapserver_daemon_up", "1 when a mapserver run serves the inbox.")
        up.add_metric([], 1.0 if report.running else 0.0)
        yield up
        queue = GaugeMetricFamily(
            "mapserver_queue_bundles", "Bundles waiting, by state.", labels=["state"]
        )
        for state in ("uploading", "queued", "processing"):
            queue.add_metric([state], float(getattr(report, state)))
        yield queue
        busy = GaugeMetricFamily("mapserver_workers_busy", "Worker processes processing a bundle.")
        busy.add_metric([], float(report.processing))
        yield busy
        degraded = GaugeMetricFamily(
            "mapserver_degraded", "1 when the daemon reports itself degraded (a full disk, ...)."
        )
        degraded.add_metric([], 1.0 if report.degraded is not None else 0.0)
        yield degraded
        free = GaugeMetricFamily(
            "mapserver_free_bytes", "Free space of each folder.", labels=["folder"]
        )
        for name in ("inbox", "outbox", "archive", "failed", "maps"):
            path = getattr(self.config, name)
            if path is None:
                continue
            try:
                free.add_metric([name], float(shutil.disk_usage(path).free))
            except OSError:
                continue
        yield free
        maps = self.fleet()
        if maps is None:
            return
        changes = GaugeMetricFamily(
            "mapserver_changes", "Tracked changes by map and state.", labels=["map", "state"]
        )
        versions = CounterMetricFamily(
            "mapserver_map_versions_published",
            "Versions published after version 1, per map.",
            labels=["map"],
        )
        current = GaugeMetricFamily(
            "mapserver_map_current_version", "The current version of each map.", labels=["map"]
        )
        for m in maps:
            for state, n in m["counts"].items():
                changes.add_metric([m["name"], state], float(n))
            versions.add_metric([m["name"]], float(m["current_version"] - 1))
            current.add_metric([m["name"]], float(m["current_version"]))
        yield changes
        yield versions
        yield current
