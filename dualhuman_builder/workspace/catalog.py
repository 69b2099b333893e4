"""The workspace catalog: one SQLite file (WAL mode) per workspace, ``WS/catalog.sqlite``.

Tables (format version :data:`CATALOG_VERSION`):

* ``meta(key, value)`` — ``format_version``, ``created_with``, ``created_at``.
* ``actors`` — name, height (m), gender, anny shape parameters (JSON) once calibrated and where
  they came from.
* ``rigs`` — name, the path it was registered from, its SHA-256 and its full TOML text.
* ``takes`` — name, rig, start time, duration (s), per-source sample counts (JSON);
  ``take_files`` — the take's source files with SHA-256 and size; ``take_actors`` — who was in it.
* ``sequences`` — named frame ranges ``[frame_start, frame_stop)`` of a take, labels and text.
* ``annotations`` (version 2) — interaction labels of a take (``sequence_id`` NULL) or of one of its
  sequences: labels (JSON list of vocabulary names, :mod:`dualhuman_builder.labels`), free-text
  descriptions (JSON list), actor and reactor (actor names of the take; NULL for symmetric or unknown),
  symmetric flag, annotator and time; one row per (take, sequence, annotator): re-importing replaces it.
* ``stage_runs`` — one row per (take, sequence or none, stage): parameters hash and JSON, status
  (``running`` / ``done`` / ``failed``), artifact paths with sizes and SHA-256, a JSON summary the
  stage returned, start and end times, error text, and the pid and host of the process that ran it.

Opening checks the file is a SQLite database, passes ``PRAGMA quick_check``, and was written by a
format version this code reads, before anything is written. A catalog of an older version is
brought up to date (new tables only, in one transaction) the first time it is opened for writing;
read-only opens leave it as it is.
"""

from __future__ import annotations

import datetime as _dt
import sqlite3
from pathlib import Path

from dualhuman_builder import __version__
from dualhuman_builder.errors import FormatVersionError, WorkspaceError

CATALOG_NAME = "catalog.sqlite"
CATALOG_VERSION = 2
SQLITE_MAGIC = b"SQLite format 3\x00"

SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE actors (
    id INTEGER PRIMARY KEY,
    name TEXT UNIQUE NOT NULL,
    height_m REAL,
    gender TEXT,
    shape_json TEXT,
    shape_source TEXT,
    created_at TEXT NOT NULL,
    updated_at TEXT NOT NULL
);
CREATE TABLE rigs (
    id INTEGER PRIMARY KEY,
    name TEXT UNIQUE NOT NULL,
    path TEXT,
    sha256 TEXT NOT NULL,
    content TEXT NOT NULL,
    created_at TEXT NOT NULL
);
CREATE TABLE takes (
    id INTEGER PRIMARY KEY,
    name TEXT UNIQUE NOT NULL,
    rig_id INTEGER REFERENCES rigs(id),
    start_time TEXT,
    duration_s REAL,
    sample_counts_json TEXT NOT NULL DEFAULT '{}',
    meta_json TEXT NOT NULL DEFAULT '{}',
    created_at TEXT NOT NULL
);
CREATE TABLE take_files (
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    path TEXT NOT NULL,
    sha256 TEXT NOT NULL,
    size_bytes INTEGER NOT NULL,
    role TEXT NOT NULL DEFAULT 'source',
    PRIMARY KEY (take_id, path)
);
CREATE TABLE take_actors (
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    slot INTEGER NOT NULL,
    actor_id INTEGER NOT NULL REFERENCES actors(id),
    PRIMARY KEY (take_id, slot)
);
CREATE TABLE sequences (
    id INTEGER PRIMARY KEY,
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    name TEXT NOT NULL,
    frame_start INTEGER NOT NULL,
    frame_stop INTEGER NOT NULL,
    labels_json TEXT NOT NULL DEFAULT '[]',
    text_json TEXT NOT NULL DEFAULT '[]',
    created_at TEXT NOT NULL,
    UNIQUE (take_id, name),
    CHECK (frame_stop > frame_start AND frame_start >= 0)
);
CREATE TABLE stage_runs (
    id INTEGER PRIMARY KEY,
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    sequence_id INTEGER REFERENCES sequences(id) ON DELETE CASCADE,
    stage TEXT NOT NULL,
    params_hash TEXT NOT NULL,
    params_json TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('running', 'done', 'failed')),
    artifacts_json TEXT NOT NULL DEFAULT '{}',
    started_at TEXT NOT NULL,
    ended_at TEXT,
    summary_json TEXT NOT NULL DEFAULT '{}',
    error TEXT,
    pid INTEGER,
    host TEXT
);
CREATE UNIQUE INDEX stage_runs_key ON stage_runs (take_id, IFNULL(sequence_id, 0), stage);
"""
#: Statements that bring a catalog of version ``k`` to ``k + 1``.
MIGRATIONS = {
    1: """
CREATE TABLE annotations (
    id INTEGER PRIMARY KEY,
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    sequence_id INTEGER REFERENCES sequences(id) ON DELETE CASCADE,
    annotator TEXT NOT NULL,
    labels_json TEXT NOT NULL DEFAULT '[]',
    texts_json TEXT NOT NULL DEFAULT '[]',
    actor TEXT,
    reactor TEXT,
    symmetric INTEGER CHECK (symmetric IN (0, 1)),
    annotated_at TEXT NOT NULL,
    source TEXT
);
CREATE UNIQUE INDEX annotations_key ON annotations (take_id, IFNULL(sequence_id, 0), annotator);
""",
}


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _connect(uri: str) -> sqlite3.Connection:
    conn = sqlite3.connect(uri, uri=True, timeout=30.0, isolation_level=None)
    conn.row_factory = sqlite3.Row
    conn.execute("PRAGMA foreign_keys = ON")
    conn.execute("PRAGMA busy_timeout = 30000")
    return conn


def create_catalog(path: Path) -> sqlite3.Connection:
    """Create a new catalog at ``path`` (which must not exist) in WAL mode."""
    conn = _connect(f"file:{path}?mode=rwc")
    conn.execute("PRAGMA journal_mode = WAL")
    conn.execute("PRAGMA synchronous = NORMAL")
    with _transaction(conn):
        for statement in (SCHEMA + "".join(MIGRATIONS.values())).split(";"):
            if statement.strip():
                conn.execute(statement)
        conn.executemany(
            "INSERT INTO meta (key, value) VALUES (?, ?)",
            [("format_version", str(CATALOG_VERSION)), ("created_with", f"dualhuman-builder {__version__}"),
             ("created_at", now_iso())],
        )  # fmt: skip
    return conn


def check_catalog_file(path: Path) -> None:
    """Raise :class:`WorkspaceError` unless ``path`` looks like a SQLite file (reads 16 bytes)."""
    ws = path.parent
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except FileNotFoundError:
        raise WorkspaceError(
            f"not a dualhuman workspace: {CATALOG_NAME} is missing",
            path=ws,
            fix=f"create one with `dualhuman init {ws}`",
        ) from None
    except PermissionError:
        raise WorkspaceError("catalog is not readable", path=path, fix=f"chmod u+r {path}") from None
    if head != SQLITE_MAGIC:
        raise WorkspaceError(
            "catalog is not a SQLite database (corrupt or overwritten)",
            path=path,
            fix=f"restore {path.name} from a backup, or move it aside and run `dualhuman init {ws}` "
            "for a new, empty catalog (files under artifacts/ and takes/ are not touched)",
        )


def _connect_readonly(path: Path) -> sqlite3.Connection:
    """A read-only connection that creates no files when it can avoid it.

    Without a ``-wal`` file every committed transaction is in the main file, and a writer that
    starts meanwhile writes to a new WAL, not to it, so reading it as immutable is exact and
    leaves no ``-wal``/``-shm`` side files behind (a failed command changes nothing). With a WAL
    present, a normal read-only connection reads through it.
    """
    if not Path(f"{path}-wal").exists():
        return _connect(f"file:{path}?mode=ro&immutable=1")
    conn = _connect(f"file:{path}?mode=ro")
    try:
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.OperationalError:  # WAL side files cannot be created in a read-only folder
        conn.close()
        return _connect(f"file:{path}?mode=ro&immutable=1")


def open_catalog(path: Path, readonly: bool = False) -> sqlite3.Connection:
    """Open and validate an existing catalog. Nothing is written before validation passes."""
    check_catalog_file(path)
    try:
        conn = _connect_readonly(path)
        try:
            _validate(conn, path)
        finally:
            if not readonly:
                conn.close()
        if readonly:
            return conn
        conn = _connect(f"file:{path}?mode=rw")
        conn.execute("PRAGMA synchronous = NORMAL")
        _migrate(conn)
        return conn
    except sqlite3.DatabaseError as e:
        raise WorkspaceError(
            f"catalog is unreadable ({e})",
            path=path,
            fix=f"restore {path.name} from a backup, or move it aside and run `dualhuman init {path.parent}`",
        ) from e


def _migrate(conn: sqlite3.Connection) -> None:
    """Apply :data:`MIGRATIONS` from the catalog's version up to :data:`CATALOG_VERSION`, in one
    transaction (a crash leaves the old version intact)."""

    def version() -> int:
        return int(conn.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone()[0])

    if version() >= CATALOG_VERSION:
        return
    with _transaction(conn):
        if version() >= CATALOG_VERSION:  # another process migrated it meanwhile
            return
        for k in range(version(), CATALOG_VERSION):
            for statement in MIGRATIONS[k].split(";"):
                if statement.strip():
                    conn.execute(statement)
        conn.execute("UPDATE meta SET value = ? WHERE key = 'format_version'", (str(CATALOG_VERSION),))
        conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('migrated_at', ?)", (now_iso(),))


def _validate(conn: sqlite3.Connection, path: Path) -> None:
    ok = conn.execute("PRAGMA quick_check").fetchone()[0]
    if ok != "ok":
        raise WorkspaceError(f"catalog fails SQLite's integrity check: {ok}", path=path,
                             fix=f"restore {path.name} from a backup")  # fmt: skip
    try:
        rows = dict(conn.execute("SELECT key, value FROM meta").fetchall())
    except sqlite3.OperationalError as e:
        raise WorkspaceError(f"not a dualhuman catalog ({e})", path=path,
                             fix="this SQLite file was not created by `dualhuman init`") from e  # fmt: skip
    try:
        version = int(rows["format_version"])
    except (KeyError, ValueError):
        raise WorkspaceError("catalog has no valid format_version", path=path) from None
    if version > CATALOG_VERSION:
        raise FormatVersionError(
            f"workspace format version {version} (created with {rows.get('created_with', 'unknown')}); "
            f"this dualhuman-builder {__version__} reads versions up to {CATALOG_VERSION}",
            path=path,
            fix="upgrade dualhuman-builder (git pull && scripts/setup.sh); the workspace was left untouched",
        )


class _transaction:
    """``with _transaction(conn):`` — BEGIN IMMEDIATE ... COMMIT, ROLLBACK on error."""

    def __init__(self, conn: sqlite3.Connection):
        self.conn = conn

    def __enter__(self):
        self.conn.execute("BEGIN IMMEDIATE")
        return self.conn

    def __exit__(self, exc_type, exc, tb):
        self.conn.execute("ROLLBACK" if exc_type else "COMMIT")
        return False


transaction = _transaction
