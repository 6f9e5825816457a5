"""``/metrics``: the Prometheus exposition of what the pages show, computed at each scrape from
the same sources (the bundle index, the daemon's status file, the map store), so that it reads
the same whether the web runs inside ``mapserver run`` or in a unit of its own.

What is in outbox/ and failed/ goes down as well as up (requeue, retention), so it is exposed as
gauges, never as counters or histograms, which Prometheus reads as counts that only rise (a fall
is a reset). The only counters are the running daemon's own, since it started.
"""

from __future__ import annotations

import shutil
from collections import Counter
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from mapserver.config import Config
from mapserver.web.index import BundleIndex

STAGE_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
SCORE_BUCKETS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 1.0)


def _distribution(
    name: str,
    doc: str,
    values: dict[tuple[str, ...], list[float]],
    labels: list[str],
    buckets: tuple[float, ...],
) -> GaugeMetricFamily:
    """How many of ``values`` are at most each bucket's bound, as a gauge with an ``le`` label
    (cumulative, ``+Inf`` the count): the buckets of a histogram, of the results there are now
    (``histogram_quantile`` reads it the same way)."""
    family = GaugeMetricFamily(name, doc, labels=[*labels, "le"])
    for label_values, samples in sorted(values.items()):
        ordered = np.sort(np.asarray(samples, float))
        below = np.searchsorted(ordered, np.asarray(buckets), side="right")
        for bound, n in zip(buckets, below, strict=True):
            family.add_metric([*label_values, repr(bound)], float(n))
        family.add_metric([*label_values, "+Inf"], float(len(ordered)))
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
        yield GaugeMetricFamily(
            "mapserver_results",
            "Results in the outbox now (retention removes them).",
            value=len(results),
        )
        failed = GaugeMetricFamily(
            "mapserver_failed_bundles",
            "Bundles in failed/ now, by the stage that failed them (requeue and retention "
            "remove them).",
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
        yield _distribution(
            "mapserver_results_by_stage_seconds",
            "Results in the outbox now whose stage took at most le seconds (result.yaml's "
            "timings).",
            stages,
            ["stage"],
            STAGE_BUCKETS_S,
        )
        yield _distribution(
            "mapserver_results_by_alignment_score",
            "Results in the outbox now whose alignment score (0..1) is at most le.",
            scores,
            [],
            SCORE_BUCKETS,
        )
        report = self.status()
        up = GaugeMetricFamily("mapserver_daemon_up", "1 when a mapserver run serves the inbox.")
        up.add_metric([], 1.0 if report.running else 0.0)
        yield up
        # The daemon's own counts only rise while it runs, and start at 0 when it starts again:
        # a counter's reset, as Prometheus expects it. None while no daemon runs.
        daemon = report.daemon or {}
        for key, name, doc in (
            (
                "results",
                "mapserver_bundles_processed",
                "Results the daemon wrote since it started.",
            ),
            ("failed", "mapserver_bundles_failed", "Bundles the daemon failed since it started."),
        ):
            if isinstance(daemon.get(key), int):
                yield CounterMetricFamily(name, doc, value=daemon[key])
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
