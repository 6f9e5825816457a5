"""The map store from planted evidence sequences (contract section 7): a person seen once, a
wall seen three times over two days, a published wall seen gone, review mode, exactly once,
late bundles, bad requests, a lost or damaged database, a full disk while publishing."""

from __future__ import annotations

import dataclasses
import errno
import sqlite3
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
import yaml

from mapserver.config import UpdateConfig
from mapserver.errors import MapFileError, StoreError
from mapserver.fleet import evidence, publish
from mapserver.fleet.observe import Found
from mapserver.fleet.store import FleetStore
from mapserver.maps import FREE, OCCUPIED, UNKNOWN, load_map, save_map
from tests.fleet_support import (
    COLUMN,
    PERSON,
    WALL,
    Robot,
    building,
    cells,
    stamp,
    write_building,
)

AUTO = UpdateConfig(mode="auto")
# A gap cut in the hall's top wall (rows 8-12): 0.8 m of it.
GAP = (slice(8, 13), slice(200, 216))
REVIEW = UpdateConfig(mode="review")


@pytest.fixture
def hall(tmp_path: Path) -> Path:
    return write_building(tmp_path / "src")


def new_store(tmp_path: Path, hall: Path, settings: UpdateConfig = AUTO) -> FleetStore:
    store = FleetStore(tmp_path / "maps", settings)
    store.add_map("hall", hall)
    return store


def current(tmp_path: Path) -> np.ndarray:
    return load_map(tmp_path / "maps" / "hall" / "current.yaml").state


def wall_seen(robot: Robot, hours: float, **kw: object) -> object:
    return robot.observe(hours, added=(WALL,), found=(("added", WALL),), **kw)  # type: ignore[arg-type]


def test_add_map_stores_version_1_byte_for_byte_and_current_points_at_it(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    folder = tmp_path / "maps" / "hall"
    assert (folder / "v0001.pgm").read_bytes() == hall.with_suffix(".pgm").read_bytes()
    assert yaml.safe_load((folder / "current.yaml").read_text())["image"] == "v0001.pgm"
    assert np.array_equal(current(tmp_path), building())
    keepout = load_map(folder / "keepout.yaml")
    assert (keepout.state == FREE).all() and keepout.state.shape == (240, 400)
    doc = yaml.safe_load((folder / "changes.yaml").read_text())
    assert doc == {"format": 1, "map": "hall", "current_version": 1, "changes": []}
    assert [v.version for v in store.versions("hall")] == [1]


def test_a_map_whose_image_is_already_in_the_store_is_refused(tmp_path: Path, hall: Path) -> None:
    """Bundles find their map by the image's sha256 (session 44's review: the same building
    added twice under two names split its evidence between them)."""
    store = new_store(tmp_path, hall)
    with pytest.raises(StoreError, match="already version 1 of map 'hall'"):
        store.add_map("hall-copy", hall)
    assert [m.name for m in store.maps()] == ["hall"]
    assert not (tmp_path / "maps" / "hall-copy").exists()


def test_a_person_seen_once_expires_when_the_next_bundle_sees_the_spot_free(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    first = store.apply(robot.observe(0, added=(PERSON,), found=(("added", PERSON),)))
    assert len(first.created) == 1 and first.changes == first.created
    (change,) = store.changes("hall")
    assert (change.state, change.sessions) == ("pending", 1)
    later = store.apply(robot.observe(2))
    assert later.expired == first.created
    (change,) = store.changes("hall")
    assert change.state == "expired" and change.contradicted == 1
    assert store.map_info("hall").current_version == 1
    assert np.array_equal(current(tmp_path), building())


def test_a_wall_seen_three_times_over_two_days_is_published_once(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    a, b = Robot("r1"), Robot("r2")
    u1 = store.apply(wall_seen(a, 0))
    u2 = store.apply(wall_seen(b, 6))
    assert u2.supported == u1.created and u2.created == ()  # one change, two robots
    assert store.changes("hall")[0].state == "pending"  # 2 sessions
    u3 = store.apply(wall_seen(a, 30))
    assert u3.confirmed == u1.created and u3.published == u1.created and u3.new_version == 2
    (change,) = store.changes("hall")
    assert (change.state, change.version, change.sessions) == ("published", 2, 3)
    assert change.robots == ["r1", "r2"]
    now = current(tmp_path)
    expected = building()
    expected[WALL] = OCCUPIED
    assert np.array_equal(now, expected)  # the wall's cells, nothing else
    # A bundle judged against version 2 finds nothing new there; version 1 bundles match v2 too.
    u4 = store.apply(b.observe(40, added=(WALL,), judged_version=2))
    assert u4.created == () and u4.new_version is None


def test_a_published_version_differs_from_version_1_only_inside_its_changes(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (0, 8, 16):
        store.apply(
            robot.observe(
                hours,
                added=(WALL,),
                removed=(COLUMN,),
                found=(("added", WALL), ("removed", COLUMN)),
            )
        )
    folder = tmp_path / "maps" / "hall"
    v1, v2 = load_map(folder / "v0001.yaml"), load_map(folder / "v0002.yaml")
    inside = np.zeros(v1.state.shape, bool)
    inside[WALL] = inside[COLUMN] = True
    assert np.array_equal(v1.state[~inside], v2.state[~inside])
    assert (v2.state[WALL] == OCCUPIED).all() and (v2.state[COLUMN] == FREE).all()
    # map_saver's files: trinary values only, its YAML keys and thresholds, version 1's frame.
    raw = (folder / "v0002.pgm").read_bytes()
    assert raw.startswith(b"P5\n# CREATOR: map_saver.cpp 0.050 m/pix\n400 240\n255\n")
    assert set(np.unique(np.frombuffer(raw[-400 * 240 :], np.uint8))) <= {0, 205, 254}
    doc = yaml.safe_load((folder / "v0002.yaml").read_text())
    assert doc == {
        "image": "v0002.pgm",
        "mode": "trinary",
        "resolution": 0.05,
        "origin": [0.0, 0.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }


def test_a_published_wall_seen_gone_becomes_a_removal_that_needs_the_same_persistence(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (0, 8, 16):
        store.apply(wall_seen(robot, hours))
    assert store.map_info("hall").current_version == 2
    # The wall is taken away again: robots judged against v2 find it removed.
    gone = dict(removed=(WALL,), found=(("removed", WALL),), judged_version=2)
    u = store.apply(robot.observe(24, **gone))  # type: ignore[arg-type]
    assert len(u.created) == 1 and u.new_version is None
    store.apply(robot.observe(30, **gone))  # type: ignore[arg-type]
    assert store.map_info("hall").current_version == 2  # 2 sessions over 6 h: not yet
    u = store.apply(robot.observe(40, **gone))  # type: ignore[arg-type]
    assert u.new_version == 3
    assert np.array_equal(current(tmp_path), building())
    kinds = [(c.kind, c.state, c.version) for c in store.changes("hall")]
    assert kinds == [("added", "published", 2), ("removed", "published", 3)]


def test_a_cart_parked_for_an_afternoon_is_never_confirmed(tmp_path: Path, hall: Path) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (0, 1, 2, 3):  # four sessions, but within 3 hours
        store.apply(robot.observe(hours, added=(PERSON,), found=(("added", PERSON),)))
    (change,) = store.changes("hall")
    assert (change.state, change.sessions) == ("pending", 4)
    store.apply(robot.observe(20))  # gone the next morning
    (change,) = store.changes("hall")
    assert change.state == "expired"
    assert store.map_info("hall").current_version == 1


def test_review_mode_waits_for_approval_and_marks_the_keepout_mask(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    for hours in (0, 8, 16):
        u = store.apply(wall_seen(robot, hours))
    (cid,) = u.confirmed
    assert u.new_version is None and store.changes("hall")[0].state == "confirmed"
    keepout = load_map(tmp_path / "maps" / "hall" / "keepout.yaml").state
    assert (keepout[WALL] == OCCUPIED).all() and (keepout == OCCUPIED).sum() == cells(WALL).size
    version = store.approve(cid)
    assert version.version == 2 and version.changes == (cid,)
    assert (current(tmp_path)[WALL] == OCCUPIED).all()
    assert (load_map(tmp_path / "maps" / "hall" / "keepout.yaml").state == FREE).all()


def test_a_rejected_change_absorbs_later_sightings(tmp_path: Path, hall: Path) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    (cid,) = store.apply(wall_seen(robot, 0)).created
    assert store.reject(cid).state == "rejected"
    for hours in (8, 16, 24):
        u = store.apply(wall_seen(robot, hours))
        assert u.created == () and u.changes == (cid,)
    assert [c.state for c in store.changes("hall")] == ["rejected"]


def test_bad_requests_are_refused_and_change_nothing(tmp_path: Path, hall: Path) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    (cid,) = store.apply(wall_seen(Robot(), 0)).created
    before = (tmp_path / "maps" / "hall" / "changes.yaml").read_bytes()
    with pytest.raises(StoreError, match="already in the store"):
        store.add_map("hall", hall)
    with pytest.raises(StoreError, match="no map named 'nope'"):
        store.versions("nope")
    with pytest.raises(StoreError, match=f"change {cid} is pending, not confirmed"):
        store.approve(cid)
    with pytest.raises(StoreError, match="no change 99"):
        store.approve(99)
    with pytest.raises(StoreError, match="has no version 5"):
        store.rollback("hall", 5)
    assert (tmp_path / "maps" / "hall" / "changes.yaml").read_bytes() == before
    assert [v.version for v in store.versions("hall")] == [1]
    broken = tmp_path / "broken.yaml"
    broken.write_text(
        "image: missing.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    with pytest.raises(MapFileError):
        store.add_map("other", broken)
    assert not (tmp_path / "maps" / "other").exists()
    assert [m.name for m in store.maps()] == ["hall"]


def test_each_bundle_counts_once_whatever_order_it_comes_in(tmp_path: Path, hall: Path) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    first = wall_seen(robot, 0)
    store.apply(first)
    again = store.apply(first)  # a repeated upload, or a restart after the commit
    assert again.repeated and again.changes == store.apply(first).changes
    store.apply(wall_seen(robot, 30))
    late = store.apply(wall_seen(robot, 10))  # arrives last, stamped in between
    (change,) = store.changes("hall")
    assert change.sessions == 3 and change.state == "confirmed"
    assert change.first_seen.endswith("08:00:00Z") and change.last_seen.startswith("2026-11-22T14")
    assert late.confirmed == (change.id,)


def test_a_late_bundle_that_saw_the_spot_free_does_not_expire_a_newer_sighting(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    store.apply(wall_seen(robot, 0))
    store.apply(wall_seen(robot, 20))
    store.apply(robot.observe(10))  # older than the last sighting: counted, but not the latest
    (change,) = store.changes("hall")
    assert change.state == "pending" and change.contradicted == 1
    # It contradicts the run; its sessions and the cells they showed stay counted together
    # (session 54's second review: taking the earlier sessions out left their cells' hits).
    assert change.sessions == 2


@pytest.mark.parametrize("settings", [REVIEW, AUTO])
def test_late_bundles_cannot_confirm_what_a_newer_bundle_saw_as_before(
    tmp_path: Path, hall: Path, settings: UpdateConfig
) -> None:
    # Session 53's review: the bundles that saw a structure back came first, the three that
    # saw it gone (a temporary removal) arrived late, and made a new change that the latest
    # bundle to observe the area had not shown: confirmed, in auto mode published.
    store = new_store(tmp_path, hall, settings)
    robot = Robot()
    store.apply(robot.observe(30))  # the newest: the hall as the map has it
    for hours in (0, 8, 16):  # older, arriving last: a span of 16 h, three sessions
        update = store.apply(wall_seen(robot, hours))
        assert update.confirmed == () and update.new_version is None
    # Each late finder's change is judged on the newer bundle's kept observation, as that
    # bundle would have judged it had it come after them: as before, so expired.
    assert {c.state for c in store.changes("hall")} == {"expired"}
    # A bundle newer than that one begins a run of its own.
    assert store.apply(wall_seen(robot, 40)).confirmed == ()
    (change,) = [c for c in store.changes("hall") if c.state == "pending"]
    assert (change.sessions, change.first_seen) == (1, "2026-11-23T00:00:00Z")


@pytest.mark.parametrize("settings", [REVIEW, AUTO])
def test_where_the_newer_observation_is_no_longer_kept_its_hour_keeps_late_bundles_waiting(
    tmp_path: Path, hall: Path, settings: UpdateConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(evidence, "KEEP_OBSERVATIONS", 1)
    store = new_store(tmp_path, hall, settings)
    robot = Robot()
    store.apply(robot.observe(30))  # the hall as the map has it
    store.apply(robot.observe(50, view=(slice(0, 240), slice(130, 200))))  # beside the wall
    for hours in (0, 8, 16):  # older, arriving last; the 30 h bundle's tiles are not kept
        update = store.apply(wall_seen(robot, hours))
        assert update.confirmed == () and update.new_version is None
    (change,) = store.changes("hall")
    assert (change.state, change.sessions) == ("pending", 3)
    (last_observed,) = store._conn.execute(
        "SELECT last_observed FROM changes WHERE id = ?", (change.id,)
    ).fetchone()
    assert last_observed == "2026-11-22T14:00:00Z"  # the hour of the 30 h bundle
    # A bundle newer than that one that shows it: now it is the latest word.
    assert store.apply(wall_seen(robot, 40)).confirmed == (change.id,)


def test_a_robot_clock_weeks_ahead_does_not_expire_every_pending_change(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    real = datetime.now(timezone.utc) - timedelta(hours=2)
    seen = dataclasses.replace(wall_seen(robot, 0), stamp=real.strftime("%Y-%m-%dT%H:%M:%SZ"))
    store.apply(seen)
    # Stamped two months ahead (within the year a replay may be ahead), it did not look at
    # the wall: its stamp is not "now" for the changes nobody has observed for 30 days.
    ahead = (real + timedelta(days=60)).strftime("%Y-%m-%dT%H:%M:%SZ")
    elsewhere = robot.observe(1, view=(slice(0, 240), slice(0, 200)))
    update = store.apply(dataclasses.replace(elsewhere, stamp=ahead))
    assert update.expired == ()
    (change,) = store.changes("hall")
    assert change.state == "pending"


def test_a_missing_database_refuses_with_how_to_recover(tmp_path: Path, hall: Path) -> None:
    new_store(tmp_path, hall).close()
    for name in ("store.db", "store.db-wal", "store.db-shm"):
        (tmp_path / "maps" / name).unlink(missing_ok=True)
    with pytest.raises(StoreError, match=r"database is missing.*restore .* from a backup"):
        FleetStore(tmp_path / "maps", AUTO)
    assert (tmp_path / "maps" / "hall" / "v0001.pgm").exists()


def test_a_damaged_database_refuses_with_how_to_recover(tmp_path: Path, hall: Path) -> None:
    new_store(tmp_path, hall).close()
    db = tmp_path / "maps" / "store.db"
    (tmp_path / "maps" / "store.db-wal").unlink(missing_ok=True)
    db.write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreError, match=r"unreadable.*register the maps again"):
        FleetStore(tmp_path / "maps", AUTO)


def test_a_full_disk_while_publishing_keeps_the_previous_current_and_publishes_later(
    tmp_path: Path, hall: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    store.apply(wall_seen(robot, 0))
    store.apply(wall_seen(robot, 8))
    before = (tmp_path / "maps" / "hall" / "current.yaml").read_bytes()
    real = publish.write_version

    def full(*args: object, **kw: object) -> object:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(publish, "write_version", full)
    u = store.apply(wall_seen(robot, 16))
    assert u.new_version is None and any("No space left" in w for w in u.warnings)
    assert (tmp_path / "maps" / "hall" / "current.yaml").read_bytes() == before
    assert store.changes("hall")[0].state == "confirmed"
    monkeypatch.setattr(publish, "write_version", real)
    store.sync()
    assert store.map_info("hall").current_version == 2
    assert (current(tmp_path)[WALL] == OCCUPIED).all()


def test_rollback_publishes_a_new_version_equal_to_the_old_one(tmp_path: Path, hall: Path) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (0, 8, 16):
        store.apply(wall_seen(robot, hours))
    v = store.rollback("hall", 1)
    assert v.version == 3 and np.array_equal(current(tmp_path), building())
    assert [c.state for c in store.changes("hall")] == ["rejected"]
    assert [x.version for x in store.versions("hall")] == [1, 2, 3]
    # Version 2 is still there, untouched.
    assert (load_map(tmp_path / "maps" / "hall" / "v0002.yaml").state[WALL] == OCCUPIED).all()


def test_a_rollback_to_a_version_holding_an_undone_change_publishes_it_again(
    tmp_path: Path, hall: Path
) -> None:
    """Session 44's review: after 'rollback to 1' undid the wall, 'rollback to 2' put the wall
    back in the map while its change stayed rejected (changes.yaml and the keepout mask said
    it was not there)."""
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (0, 8, 16):
        (cid,) = store.apply(wall_seen(robot, hours)).changes
    assert store.change(cid).version == 2
    store.rollback("hall", 1)  # version 3: no wall
    assert store.change(cid).state == "rejected"
    back = store.rollback("hall", 2)  # version 4: the wall again
    assert back.version == 4 and (current(tmp_path)[WALL] == OCCUPIED).all()
    assert store.change(cid).state == "published"
    assert [h["action"] for h in store.history(cid)][-2:] == ["rolled back", "published"]
    store.rollback("hall", 3)  # version 5 copies version 3, which copied version 1: no wall
    assert store.change(cid).state == "rejected"
    assert np.array_equal(current(tmp_path), building())
    store.rollback("hall", 4)  # version 4 copied version 2: the wall
    assert store.change(cid).state == "published"
    doc = yaml.safe_load((tmp_path / "maps" / "hall" / "changes.yaml").read_text())
    assert [(c["id"], c["state"]) for c in doc["changes"]] == [(cid, "published")]


def test_a_store_made_before_rollbacks_recorded_their_source_reads_it_from_the_note(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (0, 8, 16):
        (cid,) = store.apply(wall_seen(robot, hours)).changes
    store.rollback("hall", 1)
    store.close()
    conn = sqlite3.connect(tmp_path / "maps" / "store.db")  # as schema 2 left it
    conn.execute("ALTER TABLE versions DROP COLUMN copy_of")
    conn.execute("DROP TABLE observations")
    conn.execute("PRAGMA user_version = 2")
    conn.commit()
    conn.close()
    store = FleetStore(tmp_path / "maps", AUTO)
    rows = store._conn.execute("SELECT version, copy_of FROM versions ORDER BY version")
    assert rows.fetchall() == [(1, None), (2, None), (3, 1)]
    store.rollback("hall", 2)
    assert store.change(cid).state == "published"


def test_stamps_stored_with_a_part_of_a_second_lose_it_in_the_upgrade(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    (cid,) = store.apply(wall_seen(Robot(), 0)).changes
    store.close()
    conn = sqlite3.connect(tmp_path / "maps" / "store.db")  # as schema 3 left it
    conn.executescript(
        """
        DROP TABLE observations;
        DROP TABLE sightings;
        CREATE TABLE sightings (change_id INTEGER NOT NULL REFERENCES changes(id) ON DELETE
            CASCADE, bundle_id TEXT NOT NULL, robot TEXT NOT NULL, stamp TEXT NOT NULL,
            PRIMARY KEY (change_id, bundle_id)) WITHOUT ROWID;
        UPDATE changes SET first_seen = '2026-11-21T08:00:00.500Z',
            last_seen = '2026-11-21T08:00:00.500Z', last_observed = '2026-11-21T08:00:00.500Z';
        UPDATE bundles SET stamp = '2026-11-21T08:00:00.500Z';
        PRAGMA user_version = 3;
        """
    )
    conn.execute(
        "INSERT INTO sightings VALUES (?, 'r1-001', 'r1', '2026-11-21T08:00:00.500Z')", (cid,)
    )
    conn.commit()
    conn.close()
    store = FleetStore(tmp_path / "maps", REVIEW)
    (change,) = store.changes("hall")
    assert (change.first_seen, change.last_seen) == ("2026-11-21T08:00:00Z",) * 2
    rows = store._conn.execute("SELECT stamp FROM sightings UNION ALL SELECT stamp FROM bundles")
    assert {r[0] for r in rows} == {"2026-11-21T08:00:00Z"}
    # The next sessions count on it as before.
    store.apply(wall_seen(Robot(), 8))
    assert store.changes("hall")[0].sessions == 2


def test_the_database_is_wal_with_foreign_keys(tmp_path: Path, hall: Path) -> None:
    new_store(tmp_path, hall).close()
    conn = sqlite3.connect(tmp_path / "maps" / "store.db")
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert conn.execute("PRAGMA user_version").fetchone()[0] >= 1


def test_two_parts_of_one_wall_merge_into_the_older_change_and_its_id_still_answers(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    top, bottom = (slice(60, 100), WALL[1]), (slice(140, 181), WALL[1])
    # Each of the first two robots saw only its half of the hall.
    north, south = (slice(0, 110), slice(0, 400)), (slice(130, 240), slice(0, 400))
    (a,) = store.apply(robot.observe(0, added=(WALL,), found=(("added", top),), view=north)).created
    (b,) = store.apply(
        robot.observe(1, added=(WALL,), found=(("added", bottom),), view=south)
    ).created
    whole = store.apply(wall_seen(robot, 2))  # one difference over both parts
    assert whole.changes == (a,) and whole.created == ()
    (change,) = store.changes("hall")
    assert change.id == a and change.sessions == 3 and store.change(b).id == a
    with pytest.raises(StoreError, match=rf"^change {b} \(merged into {a}\) is pending, not"):
        store.approve(b)  # the state is the change's it joined: say which one that is
    rejected = store.reject(b)  # the merged id acts on the change it joined
    assert (rejected.id, rejected.state) == (a, "rejected")
    with pytest.raises(StoreError, match=rf"^change {b} \(merged into {a}\) is rejected: only"):
        store.reject(b)


def test_a_change_approved_by_another_process_shows_in_the_daemons_next_changes_yaml(
    tmp_path: Path, hall: Path
) -> None:
    daemon = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    for hours in (0, 8, 16):
        (cid,) = daemon.apply(wall_seen(robot, hours)).changes
    with FleetStore(tmp_path / "maps", REVIEW) as operator:  # the CLI or the web, meanwhile
        operator.approve(cid)
    daemon.apply(robot.observe(30, view=(slice(0, 20), slice(0, 20))))  # far from the wall
    doc = yaml.safe_load((tmp_path / "maps" / "hall" / "changes.yaml").read_text())
    assert doc["current_version"] == 2
    assert [(c["id"], c["state"], c["version"]) for c in doc["changes"]] == [(cid, "published", 2)]


def test_sessions_that_show_a_change_without_reporting_it_count_and_paint(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    store.apply(wall_seen(robot, 0))
    store.apply(robot.observe(8, added=(WALL,)))  # its local map shows the wall; no difference
    last = store.apply(robot.observe(16, added=(WALL,)))
    assert last.new_version == 2
    assert (current(tmp_path)[WALL] == OCCUPIED).all()  # painted, not an empty version
    (change,) = store.changes("hall")
    assert change.sessions == 3 and change.version == 2


def test_sessions_before_a_change_was_found_count_when_their_local_maps_showed_it(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    store.apply(robot.observe(0))  # before the wall was built: the hall as it was
    store.apply(robot.observe(8, added=(WALL,)))  # its local map shows the wall; no difference
    store.apply(robot.observe(16, added=(WALL,)))  # the same
    last = store.apply(wall_seen(robot, 24))  # the first to report it: three sessions, 16 h
    assert last.new_version == 2
    (change,) = store.changes("hall")
    assert change.sessions == 3 and change.first_seen == "2026-11-21T16:00:00Z"
    assert change.bundles == ["r1-002", "r1-003", "r1-004"]
    assert (current(tmp_path)[WALL] == OCCUPIED).all()


def test_the_count_back_stops_at_a_session_that_saw_the_area_as_before(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    store.apply(robot.observe(0, added=(PERSON,)))  # a person stood there that morning
    store.apply(robot.observe(8))  # gone
    store.apply(robot.observe(16, added=(PERSON,)))  # someone again, not reported
    store.apply(robot.observe(24, added=(PERSON,), found=(("added", PERSON),)))
    (change,) = store.changes("hall")
    # The sessions at 16 h and 24 h, not the one at 0 h: the one at 8 h saw the spot free.
    assert (change.state, change.sessions) == ("pending", 2)
    assert change.first_seen == "2026-11-22T00:00:00Z"


def test_the_count_back_judges_as_the_live_judge_does_past_a_session_that_saw_it_off(
    tmp_path: Path, hall: Path
) -> None:
    # Session 54's review: judged on the change's bare box, a session that saw the new wall
    # 0.2 m off (unclear for the live judge: occupied cells beside it) was "as before" and
    # stopped the count.
    store = new_store(tmp_path, hall)
    robot = Robot()
    store.apply(robot.observe(0, added=(WALL,)))
    store.apply(robot.observe(8, added=(WALL,)))
    store.apply(robot.observe(12, added=((WALL[0], slice(243, 246)),)))  # drawn 4 cells off
    store.apply(wall_seen(robot, 24))
    (change,) = store.changes("hall")
    assert change.sessions == 3 and change.bundles == ["r1-001", "r1-002", "r1-004"]


def test_a_late_bundle_from_before_a_gap_does_not_join_the_run_after_it(
    tmp_path: Path, hall: Path
) -> None:
    # Session 54's review: the person at 0 h, gone at 8 h, someone there again at 16 and 24 h;
    # the 0 h bundle arriving last was counted, and the person published.
    store = new_store(tmp_path, hall)
    robot = Robot()
    person = {"added": (PERSON,)}
    store.apply(robot.observe(8))
    store.apply(robot.observe(16, **person))  # type: ignore[arg-type]
    store.apply(robot.observe(24, found=(("added", PERSON),), **person))  # type: ignore[arg-type]
    late = store.apply(robot.observe(0, **person))  # type: ignore[arg-type]
    assert late.new_version is None
    (change,) = store.changes("hall")
    assert (change.state, change.sessions, change.first_seen) == ("pending", 2, stamp(16))


def test_a_late_bundle_that_reported_the_change_before_a_gap_does_not_join_the_run_after_it(
    tmp_path: Path, hall: Path
) -> None:
    # Session 54's second review: the check above covered a late bundle that showed the
    # change, not one that reported it; the cart of 0 h arriving last was published.
    maps = []
    for order in ([0, 2, 20, 30], [2, 20, 30, 0]):  # in stamp order, and 0 h a day late
        root = tmp_path / "".join(map(str, order))
        store = new_store(root, hall)
        robot = Robot()
        cart = {"added": (PERSON,), "found": (("added", PERSON),)}
        seen = {
            0: robot.observe(0, **cart),  # type: ignore[arg-type]
            2: robot.observe(2),  # gone
            20: robot.observe(20, **cart),  # type: ignore[arg-type]
            30: robot.observe(30, **cart),  # type: ignore[arg-type]
        }
        for hours in order:
            store.apply(seen[hours])
        (pending,) = [c for c in store.changes("hall") if c.state == "pending"]
        assert (pending.sessions, pending.first_seen) == (2, stamp(20))
        maps.append(current(root))
        store.close()
    assert np.array_equal(maps[0], maps[1]) and np.array_equal(maps[0], building())


def test_the_sessions_of_a_change_expired_unseen_are_not_counted_again(
    tmp_path: Path, hall: Path
) -> None:
    # Session 54's second review: a cart seen twice 40 days ago, expired unseen, then seen
    # once: the count back gave the new change all three, and published it.
    store = new_store(tmp_path, hall)
    robot = Robot()
    cart = {"added": (PERSON,), "found": (("added", PERSON),)}
    days = -40 * 24  # before the server's clock, as expiry counts from it at the latest
    store.apply(robot.observe(days, **cart))  # type: ignore[arg-type]
    store.apply(robot.observe(days + 1, **cart))  # type: ignore[arg-type]
    store.apply(robot.observe(days + 31 * 24, view=(slice(0, 240), slice(0, 150))))  # elsewhere
    (old,) = store.changes("hall")
    assert old.state == "expired"
    update = store.apply(robot.observe(days + 32 * 24, **cart))  # type: ignore[arg-type]
    assert update.new_version is None
    (new,) = [c for c in store.changes("hall") if c.state == "pending"]
    assert new.sessions == 1


def test_a_session_stamped_in_the_same_second_counts_in_either_order(
    tmp_path: Path, hall: Path
) -> None:
    for first_reported in (True, False):
        root = tmp_path / str(first_reported)
        store = new_store(root, hall)
        r1, r2 = Robot("r1"), Robot("r2")
        reported, shown = wall_seen(r1, 10), r2.observe(10, added=(WALL,))
        for obs in (reported, shown) if first_reported else (shown, reported):
            store.apply(obs)
        (change,) = store.changes("hall")
        assert change.sessions == 2 and change.robots == ["r1", "r2"]
        store.close()


def test_a_late_finder_is_judged_by_the_newer_bundles_of_the_same_hour(
    tmp_path: Path, hall: Path
) -> None:
    # Session 54's review: a cart shown at 0 and 8 h, reported by a bundle of 16:10 that
    # arrived after one of 16:40 had seen the spot free: the count back confirmed and
    # published it (the evidence keeps only the hour a cell was last seen).
    store = new_store(tmp_path, hall)
    robot = Robot()
    cart = {"added": (PERSON,)}
    store.apply(robot.observe(0, **cart))  # type: ignore[arg-type]
    store.apply(robot.observe(8, **cart))  # type: ignore[arg-type]
    store.apply(robot.observe(16 + 40 / 60))  # gone
    late = store.apply(robot.observe(16 + 10 / 60, found=(("added", PERSON),), **cart))  # type: ignore[arg-type]
    assert late.new_version is None and late.expired == late.created
    (change,) = store.changes("hall")
    assert change.state == "expired" and change.sessions == 3


def test_a_bundle_id_used_again_after_retention_is_another_session(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    for hours in (0, 8, 16):
        store.apply(wall_seen(robot, hours, bundle_id="run-0001"))
    (change,) = store.changes("hall")
    assert (change.state, change.sessions) == ("confirmed", 3)
    assert change.bundles == ["run-0001"] * 3


def test_a_store_migrated_by_another_process_meanwhile_is_not_migrated_twice(
    tmp_path: Path, hall: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Session 54's review: the daemon and the web unit starting together after an upgrade:
    # both read the old schema version, the second to migrate failed ("table observations
    # already exists").
    from mapserver.fleet import db

    new_store(tmp_path, hall).close()
    conn = sqlite3.connect(tmp_path / "maps" / "store.db")
    conn.execute("DROP TABLE observations")
    conn.execute("PRAGMA user_version = 3")
    conn.commit()
    conn.close()
    real = db.transaction
    raced = []

    def other_process_first(c: sqlite3.Connection):  # type: ignore[no-untyped-def]
        if not raced:
            raced.append(True)
            db.connect(tmp_path / "maps", create=False).close()  # migrates it, meanwhile
        return real(c)

    monkeypatch.setattr(db, "transaction", other_process_first)
    conn = db.connect(tmp_path / "maps", create=False)
    assert raced and conn.execute("PRAGMA user_version").fetchone()[0] == db.SCHEMA_VERSION
    conn.close()


def test_a_gap_cut_in_a_wall_shows_beside_the_wall_ends_the_map_still_has(
    tmp_path: Path, hall: Path
) -> None:
    # The wall's ends stand within 0.2 m of the gap's end cells: counted as the structure
    # standing, they left every session that did not report the gap "unclear" (three
    # removals of wall pieces in generated histories never confirmed; session 54).
    store = new_store(tmp_path, hall)
    robot = Robot()
    gap = GAP
    store.apply(robot.observe(0, removed=(gap,), found=(("removed", gap),)))
    store.apply(robot.observe(8, removed=(gap,)))  # seen, not reported
    last = store.apply(robot.observe(16, removed=(gap,)))
    assert last.new_version == 2
    (change,) = store.changes("hall")
    assert (change.sessions, change.state) == (3, "published")
    assert (current(tmp_path)[gap] == FREE).all()


def test_a_current_version_gone_from_disk_does_not_stop_the_judging(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    gap = GAP
    store.apply(robot.observe(0, removed=(gap,), found=(("removed", gap),)))
    (tmp_path / "maps" / "hall" / "v0001.pgm").unlink()  # an operator's mistake
    update = store.apply(robot.observe(8, removed=(gap,)))  # judged as before session 54
    assert not update.repeated
    (change,) = store.changes("hall")
    assert change.state == "pending"


def test_a_gap_seen_walled_up_again_is_as_before(tmp_path: Path, hall: Path) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    gap = GAP
    store.apply(robot.observe(0, removed=(gap,), found=(("removed", gap),)))
    store.apply(robot.observe(8))  # the wall whole again: its own cells occupied
    (change,) = store.changes("hall")
    assert (change.state, change.sessions) == ("expired", 1)


def test_the_count_back_follows_a_run_longer_than_the_expiry_and_stops_at_a_gap_that_long(
    tmp_path: Path, hall: Path
) -> None:
    # Session 54's final review: it stopped expire_unseen_days (30) before the finder, not at
    # a gap of that length: a wall seen every day for 40 days counted 31 sessions.
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    start = -100 * 24
    store.apply(robot.observe(start, added=(WALL,)))  # 40 days before the daily run: a gap
    for day in range(40, 80):
        store.apply(robot.observe(start + day * 24, added=(WALL,)))
    store.apply(wall_seen(robot, start + 80 * 24))
    (change,) = store.changes("hall")
    assert change.sessions == 41 and change.first_seen == stamp(start + 40 * 24)


def test_a_late_bundle_from_before_a_gap_longer_than_the_expiry_starts_no_run(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    days = -60 * 24
    store.apply(wall_seen(robot, days + 35 * 24))
    store.apply(wall_seen(robot, days + 35 * 24 + 10))
    store.apply(wall_seen(robot, days))  # late, 35 days before: in stamp order long expired
    (pending,) = [c for c in store.changes("hall") if c.state == "pending"]
    assert pending.sessions == 2 and pending.first_seen == stamp(days + 35 * 24)


def test_a_pending_change_unseen_for_longer_than_the_expiry_is_not_revived(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    days = -60 * 24
    store.apply(wall_seen(robot, days))
    store.apply(wall_seen(robot, days + 31 * 24))  # the first expired unseen meanwhile
    states = sorted((c.state, c.sessions) for c in store.changes("hall"))
    assert states == [("expired", 1), ("pending", 1)]


def test_a_current_version_of_another_size_does_not_fail_the_bundle(
    tmp_path: Path, hall: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    gap = GAP
    store.apply(robot.observe(0, removed=(gap,), found=(("removed", gap),)))
    monkeypatch.setattr(store, "_current_state", lambda *a: building()[:100, :100])
    store.apply(robot.observe(8, removed=(gap,)))
    (change,) = store.changes("hall")
    assert change.state == "pending"


def test_a_thin_piece_flush_with_a_wall_back_a_cell_off_does_not_show_as_gone(
    tmp_path: Path,
) -> None:
    # Session 54's second review: a board one cell thick against the hall's top wall, removed,
    # then back but seen a cell off, onto the wall's cells: with the walls beside a removed
    # change ignored, nothing stood near its cells, and the removal was published.
    from mapserver.fleet.evidence import pack_tiles
    from mapserver.fleet.lattice import Window
    from mapserver.fleet.observe import Found, Observation
    from mapserver.maps import UNKNOWN, save_map
    from tests.fleet_support import RES

    board = (slice(13, 14), slice(150, 191))  # row 13: the wall is rows 8-12
    with_board = building()
    with_board[board] = OCCUPIED
    (tmp_path / "src").mkdir()
    store = FleetStore(tmp_path / "maps", AUTO)
    store.add_map("hall", save_map(tmp_path / "src" / "hall.yaml", with_board, RES, (0, 0, 0)))

    def seen(n: int, hours: float, world: np.ndarray, *, shift: int = 0) -> Observation:
        local = np.roll(np.where(np.arange(240)[:, None] < 10, UNKNOWN, world), shift, axis=0)
        occupied, free = local == OCCUPIED, local == FREE
        window = Window(0, 0, 240, 400)
        found = (Found("removed", cells(board)),) if shift == 0 and world is not with_board else ()
        return Observation(
            "hall", f"r1-{n}", f"fp-{n}", "r1", stamp(hours), 1, 1, window, occupied, free,
            found, tuple((f.kind, f.cells) for f in found), pack_tiles(window, occupied, free),
        )  # fmt: skip

    store.apply(seen(1, 0, building()))  # gone, reported
    store.apply(seen(2, 6, building()))
    store.apply(seen(3, 14, with_board, shift=-1))  # back, drawn a cell up, onto the wall
    (change,) = store.changes("hall")
    assert change.sessions == 2 and change.state == "pending"
    assert (current(tmp_path)[board] == OCCUPIED).all()


def test_two_reviewers_approving_at_once_get_two_whole_versions(tmp_path: Path, hall: Path) -> None:
    import threading

    from mapserver.bundle import sha256_file

    store = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    for hours in (0, 8, 16):
        store.apply(
            robot.observe(hours, added=(WALL, PERSON), found=(("added", WALL), ("added", PERSON)))
        )
    ids = [c.id for c in store.changes("hall", state="confirmed")]
    assert len(ids) == 2
    barrier = threading.Barrier(2)
    errors: list[BaseException] = []

    def approve(cid: int) -> None:
        with FleetStore(tmp_path / "maps", REVIEW) as mine:  # the web's threads, a command
            barrier.wait()
            try:
                mine.approve(cid, actor=f"reviewer-{cid}")
            except BaseException as error:  # pragma: no cover - reported below
                errors.append(error)

    threads = [threading.Thread(target=approve, args=(cid,)) for cid in ids]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    versions = store.versions("hall")
    assert [v.version for v in versions] == [1, 2, 3]
    for v in versions:
        image = v.yaml.parent / yaml.safe_load(v.yaml.read_text())["image"]
        assert sha256_file(image) == v.sha256
    now = current(tmp_path)
    assert (now[WALL] == OCCUPIED).all() and (now[PERSON] == OCCUPIED).all()
    assert sorted(c.state for c in store.changes("hall")) == ["published", "published"]


@pytest.mark.parametrize("stamp", ["1970-01-01T00:00:00Z", "2099-01-01T00:00:00Z"])
def test_a_robot_with_a_wrong_clock_does_not_feed_the_map(
    tmp_path: Path, hall: Path, stamp: str
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    store.apply(wall_seen(robot, 0))
    store.apply(wall_seen(robot, 1))
    wrong = dataclasses.replace(wall_seen(robot, 2), stamp=stamp)
    update = store.apply(wrong)
    assert update.warnings and "check the robot's clock" in update.warnings[0]
    (change,) = store.changes("hall")
    assert change.sessions == 2 and change.state == "pending"  # a 56-year span would confirm it


def test_a_fleet_that_keeps_time_can_refuse_a_robot_clock_a_day_ahead(
    tmp_path: Path, hall: Path
) -> None:
    # Session 53's review: a clock one day ahead made a 6-hour temporary removal span 30 hours
    # and publish. By default a day ahead counts (replays); update.max_clock_ahead_hours: 1
    # refuses it.
    ahead = (datetime.now(timezone.utc) + timedelta(days=1)).strftime("%Y-%m-%dT%H:%M:%SZ")
    strict = FleetStore(tmp_path / "maps", UpdateConfig(mode="auto", max_clock_ahead_hours=1.0))
    strict.add_map("hall", hall)
    robot = Robot()
    update = strict.apply(dataclasses.replace(wall_seen(robot, 0), stamp=ahead))
    assert update.warnings == (
        f"map hall: not applied: its stamp {ahead} is more than 1 hours ahead of this server's "
        "clock (update.max_clock_ahead_hours): check the robot's clock",
    )
    assert strict.changes("hall") == []
    (tmp_path / "default").mkdir()
    default = new_store(tmp_path / "default", hall)
    assert not default.apply(dataclasses.replace(wall_seen(robot, 1), stamp=ahead)).warnings
    assert len(default.changes("hall")) == 1


def test_sessions_dated_days_ahead_of_the_server_clock_still_feed_the_map(
    tmp_path: Path, hall: Path
) -> None:
    # Recorded sessions replayed on a server whose clock is behind them (or robots a few days
    # off): their evidence counts as stamped, so the wall is confirmed over their span.
    store = new_store(tmp_path, hall)
    robot = Robot()
    ahead = datetime.now(timezone.utc) + timedelta(days=20)
    for hours in (0, 8, 16):
        stamp = (ahead + timedelta(hours=hours)).strftime("%Y-%m-%dT%H:%M:%SZ")
        update = store.apply(dataclasses.replace(wall_seen(robot, hours), stamp=stamp))
        assert not update.warnings
    (change,) = store.changes("hall")
    assert change.sessions == 3 and change.state == "published"


def test_late_sessions_from_before_a_published_wall_do_not_erase_it(
    tmp_path: Path, hall: Path
) -> None:
    store = new_store(tmp_path, hall)
    robot = Robot()
    for hours in (40, 48, 60):
        store.apply(wall_seen(robot, hours))
    assert store.map_info("hall").current_version == 2
    # Three sessions from before the wall was built arrive late, judged against version 2.
    for hours in (0, 8, 16):
        u = store.apply(
            robot.observe(hours, removed=(WALL,), found=(("removed", WALL),), judged_version=2)
        )
        assert u.created == ()
    assert store.map_info("hall").current_version == 2
    assert (current(tmp_path)[WALL] == OCCUPIED).all()


def test_an_approval_racing_the_daemon_that_expires_the_change_publishes_nothing(
    tmp_path: Path, hall: Path
) -> None:
    """The daemon does not take the writer lock to apply a bundle: between an approval's read of
    the change and its commit, a session that sees the spot as before expires it (session 44's
    review: the expired change was published anyway, in a version nobody can approve again)."""
    daemon = new_store(tmp_path, hall, REVIEW)
    robot = Robot()
    for hours in (0, 8, 16):
        (cid,) = daemon.apply(wall_seen(robot, hours)).changes
    assert daemon.change(cid).state == "confirmed"

    import threading

    committed = threading.Event()
    updates: list[object] = []

    def the_daemon() -> None:  # its own connection, as in its own process
        def step(name: str) -> None:
            if name == "bundle-applied":  # committed; next it waits for the writer lock
                committed.set()

        with FleetStore(tmp_path / "maps", REVIEW, checkpoint=step) as store:
            updates.append(store.apply(robot.observe(20)))  # the wall is gone again

    thread = threading.Thread(target=the_daemon)

    def meanwhile(step: str) -> None:
        if step == "version-written":
            thread.start()
            assert committed.wait(30)

    with (
        FleetStore(tmp_path / "maps", REVIEW, checkpoint=meanwhile) as operator,
        pytest.raises(StoreError, match=f"change {cid} is expired now, not confirmed"),
    ):
        operator.approve(cid)
    thread.join(30)
    assert cid in updates[0].expired  # type: ignore[attr-defined]
    assert [v.version for v in daemon.versions("hall")] == [1]
    assert daemon.change(cid).state == "expired" and daemon.change(cid).version is None
    assert not (tmp_path / "maps" / "hall" / "v0002.pgm").exists()
    assert yaml.safe_load(current_yaml(tmp_path).read_text())["image"] == "v0001.pgm"
    with (
        FleetStore(tmp_path / "maps", REVIEW) as operator,
        pytest.raises(StoreError, match="expired: only a pending or confirmed"),
    ):
        operator.reject(cid)


def current_yaml(tmp_path: Path) -> Path:
    return tmp_path / "maps" / "hall" / "current.yaml"


def test_stamps_with_a_part_of_a_second_sort_as_text_in_time_order() -> None:
    # Session 54's review: kept to the millisecond, "08:00:00.500Z" sorted before "08:00:00Z"
    # as text, and the store compares stamps as text.
    from mapserver.fleet.model import utc_stamp

    stamps = ["2026-11-21T08:00:00Z", "2026-11-21T08:00:00.500Z", "2026-11-21T09:00:00.999+01:00"]
    normal = [utc_stamp(x) for x in stamps]
    assert normal == ["2026-11-21T08:00:00Z", "2026-11-21T08:00:00Z", "2026-11-21T08:00:00Z"]
    later = [utc_stamp("2026-11-21T07:59:59.999Z"), *normal, utc_stamp("2026-11-21T08:00:01.2Z")]
    assert sorted(later) == later


# A block drawn as its outline (2 cells thick) round an inside no lidar saw (unknown), as maps
# draw shelves and pillars: rows 40..59, cols 300..329 (15-16.5 m, 9-10 m).
BLOCK = (slice(40, 60), slice(300, 330))
BLOCK_INSIDE = (slice(42, 58), slice(302, 328))


def _outlined_block(tmp_path: Path, v1: np.ndarray) -> FleetStore:
    (tmp_path / "src").mkdir()
    hall = save_map(tmp_path / "src" / "hall.yaml", v1, 0.05, (0.0, 0.0, 0.0))
    store = FleetStore(tmp_path / "maps", AUTO)
    store.add_map("hall", hall)
    return store


def _seeing(
    robot: Robot, hours: float, occupied: np.ndarray, free: np.ndarray, gone: np.ndarray
) -> object:
    """An observation of the hall that saw, in the block's box, ``occupied`` and ``free``
    only (elsewhere the building's walls and floor) and reported ``gone`` (flat cells)
    removed."""
    obs = robot.observe(hours)
    elsewhere = np.ones(building().shape, bool)
    elsewhere[BLOCK] = False
    occ = (building() == OCCUPIED) & elsewhere & ~free | occupied
    fre = (building() == FREE) & elsewhere & ~occupied | free
    found = (Found("removed", gone),) if len(gone) else ()
    return dataclasses.replace(
        obs,
        occupied=occ,
        free=fre,
        tiles=evidence.pack_tiles(obs.window, occ, fre),
        found=found,
        result_cells=tuple((f.kind, f.cells) for f in found),
    )


def test_a_block_drawn_as_an_outline_gone_is_published_as_floor_inside_too(tmp_path: Path) -> None:
    """A removed block whose map drew only its outline: the version publishing its removal
    frees what its sessions saw free inside it too, not only the outline (a fresh-eyes
    review of session 58 found the demo depot's removed block left an island of unknown
    where three sessions saw floor). Inside it: cols 302-314 seen free by the three sessions
    (freed); cols 315-320 by one of them only (under paint_min_sessions, 2: unknown); cols
    321-327 seen free by the three and occupied by three sessions before (as often occupied as
    free: unknown)."""
    v1 = building()
    v1[BLOCK] = OCCUPIED
    v1[BLOCK_INSIDE] = UNKNOWN
    store = _outlined_block(tmp_path, v1)
    outline = np.zeros(v1.shape, bool)
    outline[BLOCK] = True
    outline[BLOCK_INSIDE] = False
    once, solid = np.zeros(v1.shape, bool), np.zeros(v1.shape, bool)
    once[42:58, 315:321] = True
    solid[42:58, 321:328] = True
    robot = Robot()
    nothing = np.zeros(0, np.int64)
    for hours in (0, 2, 4):  # the block standing, its east part seen solid inside
        store.apply(_seeing(robot, hours, outline | solid, np.zeros(v1.shape, bool), nothing))
    gone = np.flatnonzero(outline).astype(np.int64)
    for hours in (30, 38, 46):  # gone; the first two did not see the strip "once"
        seen_free = np.zeros(v1.shape, bool)
        seen_free[BLOCK] = True
        if hours < 46:
            seen_free &= ~once
        store.apply(_seeing(robot, hours, np.zeros(v1.shape, bool), seen_free, gone))
    assert store.map_info("hall").current_version == 2
    v2 = load_map(tmp_path / "maps" / "hall" / "v0002.yaml").state
    assert (v2[outline] == FREE).all()
    assert (v2[42:58, 302:315] == FREE).all()
    assert (v2[once] == UNKNOWN).all() and (v2[solid] == UNKNOWN).all()
    rest = np.ones(v1.shape, bool)
    rest[BLOCK] = False
    assert np.array_equal(v1[rest], v2[rest])


def test_unknown_reaching_past_a_removed_block_stays_unknown(tmp_path: Path) -> None:
    """The review's other case: unknown inside the removal's outline that runs on past it (a
    room the map never saw, behind a removed wall) is no part of the change, whatever the
    robots saw there: only an enclosed inside is freed."""
    v1 = building()
    v1[BLOCK] = OCCUPIED
    v1[BLOCK_INSIDE] = UNKNOWN
    v1[48:52, 328:360] = UNKNOWN  # a passage of unknown from the inside out east
    store = _outlined_block(tmp_path, v1)
    outline = (v1 == OCCUPIED) & (building() == FREE)
    gone = np.flatnonzero(outline).astype(np.int64)
    seen_free = np.zeros(v1.shape, bool)
    seen_free[BLOCK] = True
    seen_free[48:52, 328:360] = True
    robot = Robot()
    for hours in (0, 8, 16):
        store.apply(_seeing(robot, hours, np.zeros(v1.shape, bool), seen_free, gone))
    assert store.map_info("hall").current_version == 2
    v2 = load_map(tmp_path / "maps" / "hall" / "v0002.yaml").state
    assert (v2[outline] == FREE).all()
    assert (v2[BLOCK_INSIDE] == UNKNOWN).all()


@pytest.mark.parametrize("name", ["0042", "1.10", "null", "on", "2026-11-21"])
def test_changes_yaml_names_a_map_whose_name_yaml_would_read_as_another_type(
    tmp_path: Path, hall: Path, name: str
) -> None:
    """The bundle-id pattern allows names YAML reads as numbers, null, booleans or dates;
    changes.yaml wrote them unquoted (session 59's review: '0042' came back as 34)."""
    store = FleetStore(tmp_path / "maps", AUTO)
    store.add_map(name, hall)
    doc = yaml.safe_load((tmp_path / "maps" / name / "changes.yaml").read_text())
    assert doc["map"] == name and doc["current_version"] == 1


def test_a_version_the_database_does_not_know_is_set_aside_and_its_number_never_reused(
    tmp_path: Path, hall: Path
) -> None:
    """Restoring store.db from a backup made before version 2 (README, "Back up the map
    store") left v0002 on disk; the next publication overwrote it with other contents, and a
    robot still on the old v2 matched no version (session 59's store review)."""
    store = new_store(tmp_path, hall, REVIEW)
    folder = tmp_path / "maps" / "hall"
    backup = tmp_path / "store-backup.db"
    live, copy = sqlite3.connect(tmp_path / "maps" / "store.db"), sqlite3.connect(backup)
    live.backup(copy)  # SQLite's online backup, as the README's backup does
    live.close()
    copy.close()
    robot = Robot()
    for hours in (0, 8, 16):
        (cid,) = store.apply(wall_seen(robot, hours)).changes
    assert store.approve(cid).version == 2
    published = (folder / "v0002.pgm").read_bytes()
    store.close()
    for suffix in ("", "-wal", "-shm"):
        (tmp_path / "maps" / f"store.db{suffix}").unlink(missing_ok=True)
    (tmp_path / "maps" / "store.db").write_bytes(backup.read_bytes())

    store = FleetStore(tmp_path / "maps", REVIEW)
    store.sync()
    assert [v.version for v in store.versions("hall")] == [1]
    assert not (folder / "v0002.pgm").exists() and not (folder / "v0002.yaml").exists()
    assert (folder / ".unpublished" / "v0002.pgm").read_bytes() == published
    assert yaml.safe_load((folder / "current.yaml").read_text())["image"] == "v0001.pgm"
    # The sightings again (the bundles applied after the backup, uploaded once more).
    for hours in (24, 32, 40):
        (cid,) = store.apply(wall_seen(robot, hours)).changes
    assert store.approve(cid).version == 3
    assert (folder / ".unpublished" / "v0002.pgm").read_bytes() == published
    assert yaml.safe_load((folder / "current.yaml").read_text())["image"] == "v0003.pgm"


def test_sync_removes_the_temporary_files_of_interrupted_writes_and_nothing_else(
    tmp_path: Path, hall: Path
) -> None:
    """A kill between a temporary file's write and its rename left a full-size map image
    behind for good (session 59's store review)."""
    store = new_store(tmp_path, hall)
    folder = tmp_path / "maps" / "hall"
    left = [folder / ".v0002.pgm.092248c7.tmp", folder / ".current.yaml.0a1b2c3d.tmp"]
    kept = [folder / ".notes.tmp", folder / "README.txt"]
    for path in left + kept:
        path.write_bytes(b"x" * 100)
    store.sync()
    assert [p.exists() for p in left] == [False, False]
    assert [p.exists() for p in kept] == [True, True]
    assert [v.version for v in store.versions("hall")] == [1]


def test_a_retried_approve_mends_the_files_a_killed_one_left_stale(
    tmp_path: Path, hall: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An approve killed between its commit and current.yaml's rename left current.yaml on
    version 1 and the keepout mask marking the approved wall; the retried approve was refused
    as published and nothing mended them until the daemon's next bundle for that map
    (session 59's store review). An operator's action now mends them first."""
    store = new_store(tmp_path, hall, REVIEW)
    folder = tmp_path / "maps" / "hall"
    robot = Robot()
    for hours in (0, 8, 16):
        (cid,) = store.apply(wall_seen(robot, hours)).changes
    write_current = publish.write_current

    def killed(*args: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C or a kill right after the commit

    monkeypatch.setattr(publish, "write_current", killed)
    with pytest.raises(KeyboardInterrupt):
        store.approve(cid)
    monkeypatch.setattr(publish, "write_current", write_current)
    assert [v.version for v in store.versions("hall")] == [1, 2]
    assert yaml.safe_load((folder / "current.yaml").read_text())["image"] == "v0001.pgm"
    assert (load_map(folder / "keepout.yaml").state[WALL] == OCCUPIED).all()
    with pytest.raises(StoreError, match="published"):
        store.approve(cid)
    assert yaml.safe_load((folder / "current.yaml").read_text())["image"] == "v0002.pgm"
    assert (current(tmp_path)[WALL] == OCCUPIED).all()
    assert (load_map(folder / "keepout.yaml").state == FREE).all()
