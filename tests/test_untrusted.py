"""Loud when unsure: an untrusted alignment says so in result.yaml, on the command line, in the
daemon's log at WARNING and in a banner across the top of the overlay; a trusted one says nothing
more than before."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from daemon_support import Daemon, layout, make_bundle, upload, wait_until
from daemon_support import write_config as write_daemon_config

from mapserver.cli import main
from mapserver.config import parse_config
from mapserver.pipeline import process_bundle
from mapserver.render import BANNER
from mapserver.trust import trust_notice

# make_bundle's room aligns with a score of about 0.9: above 0.6, below 0.99.
STRICT = {"pipeline": {"align": {"min_score": 0.99}}}
LINE = re.compile(
    r"UNTRUSTED alignment \(score 0\.\d\d < min_score 0\.99\): no differences reported"
)


# ``run`` and ``process`` configure logging for the process (see conftest.py).
pytestmark = pytest.mark.usefixtures("keep_logging")


def _banner_rows(png: bytes) -> int:
    """How many rows at the top of an image are mostly the banner's colour."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    share = (np.abs(image.astype(int) - BANNER).sum(axis=2) < 30).mean(axis=1)
    rows = 0
    while rows < len(share) and share[rows] > 0.6:
        rows += 1
    return rows


@pytest.mark.parametrize("strict", [False, True])
def test_result_and_overlay_say_whether_the_alignment_was_trusted(
    tmp_path: Path, strict: bool
) -> None:
    bundle = make_bundle(tmp_path / "run-1")
    config = parse_config(STRICT if strict else {}, base_dir=tmp_path)
    outcome = process_bundle(bundle, config)
    a = outcome.result["alignment"]
    assert a["trusted"] is (not strict)
    assert a["min_score"] == (0.99 if strict else 0.6)
    assert outcome.result["status"] == "ok"  # processed, whatever the trust
    notice = trust_notice(a)
    if strict:
        assert outcome.result["differences"] == []
        assert notice is not None and LINE.match(notice)
        assert notice.startswith(f"UNTRUSTED alignment (score {a['score']:.2f} < ")
        assert _banner_rows(outcome.images["overlay.png"]) >= 15
    else:
        assert len(outcome.result["differences"]) == 1  # the planted box
        assert notice is None
        assert _banner_rows(outcome.images["overlay.png"]) == 0
    # Contract section 3: diff.png has the overlay's extent, pixel for pixel, banner or not
    # (session 53's review: the banner's band made the overlay 36-62 rows taller).
    over, diff = (_decoded(outcome.images[name]) for name in ("overlay.png", "diff.png"))
    assert over.shape == diff.shape
    assert _banner_rows(outcome.images["diff.png"]) == _banner_rows(outcome.images["overlay.png"])


def _decoded(png: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def test_process_prints_the_untrusted_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bundle = make_bundle(tmp_path / "run-1")
    config_file = tmp_path / "strict.yaml"
    config_file.write_text(yaml.safe_dump(STRICT))
    out = tmp_path / "out"
    assert main(["process", "--config", str(config_file), "--outbox", str(out), str(bundle)]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "INFO" not in line]
    assert lines[0] == f"run-1: 0 differences -> {out / 'run-1' / 'result.yaml'}"
    assert lines[1].startswith("run-1: UNTRUSTED alignment (score ")
    assert LINE.search(lines[1]) and "check the pose prior" in lines[1]
    assert len(lines) == 2
    result = yaml.safe_load((out / "run-1" / "result.yaml").read_text())
    assert result["alignment"]["trusted"] is False


def test_the_daemon_logs_an_untrusted_bundle_at_warning(tmp_path: Path) -> None:
    good = make_bundle(tmp_path / "src" / "run-1", checksums=False)
    config = write_daemon_config(tmp_path, workers=1, **STRICT)
    dirs = layout(tmp_path)
    with Daemon(config) as daemon:
        daemon.wait_ready()
        upload(good, dirs["inbox"])
        wait_until((dirs["archive"] / "run-1").is_dir, timeout=30, what="run-1 archived")
        wait_until(lambda: "run-1: done" in daemon.log(), timeout=10, what="run-1 done")
        assert daemon.stop() == 0
    [line] = [x for x in daemon.log().splitlines() if "UNTRUSTED" in x]
    assert line.startswith("WARNING mapserver.service: run-1: UNTRUSTED alignment (score ")
    assert LINE.search(line)


def test_an_untrusted_bundle_on_a_stored_map_names_the_map_and_its_versions(
    tmp_path: Path,
) -> None:
    # Session 54's review: it got no map name nor version (the web showed "map: null"); it adds
    # nothing to the fleet map, and says so in a warning.
    from mapserver.fleet.store import FleetStore

    bundle = make_bundle(tmp_path / "run-1")
    config = parse_config({**STRICT, "maps": "maps"}, base_dir=tmp_path)
    with FleetStore(tmp_path / "maps", config.update) as store:
        store.add_map("room", bundle / "nav2_map.yaml")
    outcome = process_bundle(bundle, config)
    assert outcome.result["alignment"]["trusted"] is False and outcome.observation is None
    m = outcome.result["map"]
    assert (m["name"], m["version"], m["current_version"]) == ("room", 1, 1)
    assert any("adds nothing to the fleet map" in w for w in outcome.result["warnings"])
