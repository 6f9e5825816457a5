"""The map store's database: SQLite in WAL mode, foreign keys on, a schema version with numbered
migrations, one writer transaction (``BEGIN IMMEDIATE``) per bundle.

The database says what was applied; the files of the store are derived from it.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from mapserver.errors import StoreError

DB_NAME = "store.db"
MAX_ROW_ID = 2**63 - 1
"""SQLite's largest INTEGER: a larger change id or version names no row, and would reach SQLite
as an OverflowError; the command line and the web refuse it where it comes in."""

# Each entry migrates the schema from version i to i + 1 (PRAGMA user_version).
MIGRATIONS: tuple[str, ...] = (
    """
    CREATE TABLE maps (
        id INTEGER PRIMARY KEY,
        name TEXT NOT NULL UNIQUE,
        width INTEGER NOT NULL,
        height INTEGER NOT NULL,
        resolution REAL NOT NULL,
        origin_x REAL NOT NULL,
        origin_y REAL NOT NULL,
        origin_yaw REAL NOT NULL,
        created_at TEXT NOT NULL,
        keepout_sig TEXT
    );
    CREATE TABLE versions (
        map_id INTEGER NOT NULL REFERENCES maps(id),
        version INTEGER NOT NULL,
        created_at TEXT NOT NULL,
        yaml TEXT NOT NULL,
        image TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        note TEXT NOT NULL,
        PRIMARY KEY (map_id, version)
    );
    CREATE INDEX versions_by_sha ON versions(sha256);
    CREATE TABLE changes (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        map_id INTEGER NOT NULL REFERENCES maps(id),
        kind TEXT NOT NULL CHECK (kind IN ('added', 'removed')),
        state TEXT NOT NULL
            CHECK (state IN ('pending', 'confirmed', 'published', 'rejected', 'expired')),
        first_seen TEXT NOT NULL,
        last_seen TEXT NOT NULL,
        sessions INTEGER NOT NULL,
        contradicted INTEGER NOT NULL DEFAULT 0,
        last_observed TEXT NOT NULL,
        latest_shows INTEGER NOT NULL,
        version INTEGER,
        row0 INTEGER NOT NULL,
        col0 INTEGER NOT NULL,
        row1 INTEGER NOT NULL,
        col1 INTEGER NOT NULL,
        polygon TEXT NOT NULL,
        note TEXT NOT NULL DEFAULT '',
        updated_at TEXT NOT NULL
    );
    CREATE INDEX changes_by_state ON changes(map_id, state);
    CREATE TABLE sightings (
        change_id INTEGER NOT NULL REFERENCES changes(id) ON DELETE CASCADE,
        bundle_id TEXT NOT NULL,
        robot TEXT NOT NULL,
        stamp TEXT NOT NULL,
        PRIMARY KEY (change_id, bundle_id)
    ) WITHOUT ROWID;
    CREATE TABLE change_cells (
        change_id INTEGER NOT NULL REFERENCES changes(id) ON DELETE CASCADE,
        cell INTEGER NOT NULL,
        hits INTEGER NOT NULL,
        PRIMARY KEY (change_id, cell)
    ) WITHOUT ROWID;
    CREATE TABLE merges (
        old_id INTEGER PRIMARY KEY,
        new_id INTEGER NOT NULL
    );
    CREATE TABLE bundles (
        fingerprint TEXT PRIMARY KEY,
        bundle_id TEXT NOT NULL,
        map_id INTEGER NOT NULL REFERENCES maps(id),
        robot TEXT NOT NULL,
        stamp TEXT NOT NULL,
        applied_at TEXT NOT NULL,
        judged_version INTEGER NOT NULL,
        outcome TEXT NOT NULL
    );
    CREATE INDEX bundles_by_id ON bundles(bundle_id);
    CREATE TABLE evidence (
        map_id INTEGER NOT NULL REFERENCES maps(id),
        tile_row INTEGER NOT NULL,
        tile_col INTEGER NOT NULL,
        data BLOB NOT NULL,
        PRIMARY KEY (map_id, tile_row, tile_col)
    ) WITHOUT ROWID;
    CREATE TABLE evidence_deltas (
        id INTEGER PRIMARY KEY,
        map_id INTEGER NOT NULL REFERENCES maps(id),
        tile_row INTEGER NOT NULL,
        tile_col INTEGER NOT NULL,
        hour INTEGER NOT NULL,
        data BLOB NOT NULL
    );
    CREATE INDEX evidence_deltas_by_tile ON evidence_deltas(map_id, tile_row, tile_col);
    """,
    # 2: who did what to a change, and when (review actions, publications).
    """
    CREATE TABLE change_events (
        id INTEGER PRIMARY KEY,
        change_id INTEGER NOT NULL,
        at TEXT NOT NULL,
        actor TEXT NOT NULL,
        action TEXT NOT NULL,
        detail TEXT NOT NULL DEFAULT ''
    );
    CREATE INDEX change_events_by_change ON change_events(change_id);
    CREATE INDEX bundles_by_map ON bundles(map_id);
    """,
    # 3: the version a rollback copied (NULL for others), so that the changes a version holds
    # can be followed through rollbacks; the rollbacks made before it are read from their note.
    """
    ALTER TABLE versions ADD COLUMN copy_of INTEGER;
    UPDATE versions SET copy_of = CAST(
        substr(note, 21, instr(substr(note, 21) || ' ', ' ') - 1) AS INTEGER
    ) WHERE note LIKE 'rollback to version %';
    """,
    # 4: the latest bundles' observations, tile by tile, with who made them and when: a change
    # found late is counted in the earlier sessions whose local maps showed it. And a sighting is
    # a bundle id at a stamp: an id freed by retention and used again is another session. (The
    # key's columns come first: SQLite 3.40's integrity check reports a WITHOUT ROWID table's
    # NOT NULL column after a key column as NULL.) Stamps are kept to the second from now on
    # (sortable as text): those stored with a part of a second lose it.
    """
    CREATE TABLE sightings_by_stamp (
        change_id INTEGER NOT NULL,
        bundle_id TEXT NOT NULL,
        stamp TEXT NOT NULL,
        robot TEXT NOT NULL,
        PRIMARY KEY (change_id, bundle_id, stamp)
    ) WITHOUT ROWID;
    INSERT OR IGNORE INTO sightings_by_stamp (change_id, bundle_id, stamp, robot)
        SELECT change_id, bundle_id, substr(stamp, 1, 19) || 'Z', robot FROM sightings;
    UPDATE changes SET first_seen = substr(first_seen, 1, 19) || 'Z',
        last_seen = substr(last_seen, 1, 19) || 'Z',
        last_observed = substr(last_observed, 1, 19) || 'Z';
    UPDATE bundles SET stamp = substr(stamp, 1, 19) || 'Z';
    DROP TABLE sightings;
    CREATE TABLE sightings (
        change_id INTEGER NOT NULL REFERENCES changes(id) ON DELETE CASCADE,
        bundle_id TEXT NOT NULL,
        stamp TEXT NOT NULL,
        robot TEXT NOT NULL,
        PRIMARY KEY (change_id, bundle_id, stamp)
    ) WITHOUT ROWID;
    INSERT INTO sightings (change_id, bundle_id, stamp, robot)
        SELECT change_id, bundle_id, stamp, robot FROM sightings_by_stamp;
    DROP TABLE sightings_by_stamp;
    CREATE TABLE observations (
        map_id INTEGER NOT NULL REFERENCES maps(id),
        tile_row INTEGER NOT NULL,
        tile_col INTEGER NOT NULL,
        stamp TEXT NOT NULL,
        bundle_id TEXT NOT NULL,
        robot TEXT NOT NULL,
        data BLOB NOT NULL,
        PRIMARY KEY (map_id, tile_row, tile_col, stamp, bundle_id)
    ) WITHOUT ROWID;
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)


def _recovery(root: Path) -> str:
    return (
        f"restore {root / DB_NAME} from a backup (with the daemon and the web stopped, and "
        f"its -wal and -shm files removed: README, 'Backing up the map store'), or move {root} "
        "aside and register the maps again with 'mapserver maps add' (the versions on disk are "
        "never touched)"
    )


def connect(
    root: Path, *, create: bool, check: bool = True, timeout: float = 30.0
) -> sqlite3.Connection:
    """Open (and with ``create``, make and migrate) the database of the store at ``root``.
    ``timeout``: how long a write waits for another writer before "database is locked".

    Raises :class:`StoreError` with how to recover when the database is missing while the store
    holds maps, is not a database, fails its integrity check, or is newer than this program.
    """
    path = root / DB_NAME
    if not path.exists():
        held = sorted(p.parent.name for p in root.glob("*/v0001.yaml")) if root.is_dir() else []
        if held:
            raise StoreError(
                f"the map store's database is missing, but {root} holds maps "
                f"({', '.join(held)}): {_recovery(root)}",
                file=path,
            )
        if not create:
            raise StoreError(
                "no map store here yet (add a map with 'mapserver maps add')", file=path
            )
        root.mkdir(parents=True, exist_ok=True)
    try:
        conn = sqlite3.connect(path, isolation_level=None, timeout=timeout)
        conn.execute("PRAGMA foreign_keys = ON")
        conn.execute("PRAGMA synchronous = FULL")
        mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        # The full check reads the whole file: once at the daemon's start and per command, not
        # per web request (a reader of a damaged file still fails, below or at its query).
        verdict = conn.execute("PRAGMA quick_check").fetchone()[0] if check else "ok"
        version = conn.execute("PRAGMA user_version").fetchone()[0]
    except sqlite3.DatabaseError as error:
        raise StoreError(
            f"the map store's database is unreadable ({error}): {_recovery(root)}", file=path
        ) from None
    if verdict != "ok":
        conn.close()
        raise StoreError(
            f"the map store's database is damaged ({verdict}): {_recovery(root)}", file=path
        )
    if mode.lower() != "wal":
        conn.close()
        raise StoreError(f"cannot put the map store's database in WAL mode (got {mode})", file=path)
    if version > SCHEMA_VERSION:
        conn.close()
        raise StoreError(
            f"the map store's database has schema {version}, newer than this mapserver "
            f"({SCHEMA_VERSION}): upgrade mapserver",
            file=path,
        )
    if version < SCHEMA_VERSION:
        with transaction(conn):
            # Read again under the write lock: another process (the daemon and the web unit
            # started together after an upgrade) may have migrated it meanwhile.
            version = conn.execute("PRAGMA user_version").fetchone()[0]
            for step in range(version, SCHEMA_VERSION):
                for statement in _statements(MIGRATIONS[step]):
                    conn.execute(statement)
            conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
    return conn


def _statements(script: str) -> list[str]:
    return [s.strip() for s in script.split(";") if s.strip()]


def connect_readonly(root: Path) -> sqlite3.Connection | None:
    """A read-only connection for the workers, or None when there is no database."""
    path = root / DB_NAME
    if not path.exists():
        return None
    conn = sqlite3.connect(f"{path.as_uri()}?mode=ro", uri=True, timeout=30.0)
    return conn


@contextmanager
def transaction(conn: sqlite3.Connection) -> Iterator[sqlite3.Connection]:
    """``BEGIN IMMEDIATE`` ... ``COMMIT``, rolled back on any exception."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield conn
        conn.execute("COMMIT")  # may fail too (a full disk, an I/O error)
    except BaseException:
        # Left open, every later BEGIN would fail until a restart. SQLite has already rolled
        # back after some errors (SQLITE_FULL, SQLITE_IOERR): a second ROLLBACK would raise and
        # hide the error that matters.
        if conn.in_transaction:
            with suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
        raise
