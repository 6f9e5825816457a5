"""Importing a benchmark script (``benchmarks/<name>.py``) in a test, and a set of one generated
bundle with the pipeline's result for it, as the scripts read them."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import yaml

from mapserver import pipeline, synth
from mapserver.config import load_config

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@contextmanager
def benchmark_module(name: str) -> Iterator[ModuleType]:
    """``benchmarks/<name>.py`` as module ``name``, with benchmarks/ on ``sys.path`` as when a
    script in it runs (they import each other); both undone afterwards."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCHMARKS))
        del sys.modules[name]


def one_bundle_set(root: Path, scenario: synth.SyntheticBundle, stamp: str) -> tuple[Path, Path]:
    """A set of one bundle (``s1/bundles/b1`` and its truth) and an outbox holding the
    pipeline's result for it, as ``bench_public.py --out`` leaves it."""
    set_dir = root / "set"
    truth_path = set_dir / "s1" / "truth" / "b1.yaml"
    truth_path.parent.mkdir(parents=True)
    bundle = synth.write_scenario(
        scenario, set_dir / "s1" / "bundles", "b1", truth_path=truth_path, stamp=stamp
    )
    outcome = pipeline.process_bundle(bundle, load_config(None))
    outbox = root / "outbox"
    (outbox / "b1").mkdir(parents=True)
    (outbox / "b1" / "result.yaml").write_text(yaml.safe_dump(outcome.result))
    return set_dir, outbox
