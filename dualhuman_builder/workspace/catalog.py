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
* ``stage_runs`` (rebuilt in version 3) — one row per (take, sequence or none, stage): the
  published result (parameters hash and JSON, artifact paths with sizes and SHA-256, the JSON
  summary the stage returned, when it ended) and its ``status``: ``done``, ``stale`` (an input
  changed since: ``stale_reason`` says which), or, while nothing is published, ``running`` /
  ``failed``; ``attempt`` (``running`` / ``failed`` / ``publishing``) for a re-run over a published
  result, with ``publish_json`` the set being switched in; the start time, pid and host of the
  latest attempt and its error text; ``reads_json``, the stages this run read (``STAGE`` of the same
  take, ``TAKE/STAGE`` of another), whose changes make it stale. See
  :mod:`dualhuman_builder.workspace.runner`.
* ``quality_checks`` and ``quality_flags`` (version 4) — the quality gates' verdict on a take
  (:mod:`dualhuman_builder.quality.gates`): one ``quality_checks`` row per take checked (when, the
  gates evaluated and skipped, the ``ended_at`` of each stage run they read) and one
  ``quality_flags`` row per failed gate (gate, stage, subject such as a tracker or an actor, value,
  threshold, message, the ``ended_at`` of the stage run it read); checking a take again replaces
  both (:func:`replace_flags`, :func:`take_flags`).

Opening checks the file is a SQLite database, passes ``PRAGMA quick_check``, and was written by a
format version this code reads, before anything is written. A catalog of an older version is
brought up to date (in one transaction) the first time it is opened for writing; read-only opens
leave it as it is. SQLite's errors become a :class:`WorkspaceError` that tells a damaged file
(restore it) from a full disk, an I/O error, a lock or a read-only file (:func:`catalog_error`: the
catalog is intact, nothing is to be re-created).
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import os
import shutil
import sqlite3
from pathlib import Path

from dualhuman_builder import __version__
from dualhuman_builder.errors import FormatVersionError, WorkspaceError

CATALOG_NAME = "catalog.sqlite"
CATALOG_VERSION = 4
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
#: The reads ``MIGRATIONS[2]`` gives the runs of a version 2 catalog (the stage declarations of then).
V2_READS = {"devices": ("scene",), "capture": ("scene",), "sync": ("capture",), "fuse": ("sync",), "fit": ("fuse",),
            "contacts": ("fit",), "render": ("fit",), "sheet": ("contacts", "fit", "render")}  # fmt: skip
_V2_READS_CASES = " ".join(f"WHEN '{k}' THEN '{json.dumps(list(v))}'" for k, v in V2_READS.items())
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
    # stage_runs gains the stale state, re-runs over a published result and what each run read; the
    # reads of existing runs are those their stages declared when version 3 was made (V2_READS)
    2: f"""
CREATE TABLE stage_runs_v3 (
    id INTEGER PRIMARY KEY,
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    sequence_id INTEGER REFERENCES sequences(id) ON DELETE CASCADE,
    stage TEXT NOT NULL,
    params_hash TEXT NOT NULL,
    params_json TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('running', 'done', 'failed', 'stale')),
    artifacts_json TEXT NOT NULL DEFAULT '{{}}',
    started_at TEXT NOT NULL,
    ended_at TEXT,
    summary_json TEXT NOT NULL DEFAULT '{{}}',
    error TEXT,
    pid INTEGER,
    host TEXT,
    attempt TEXT CHECK (attempt IN ('running', 'failed', 'publishing')),
    publish_json TEXT,
    reads_json TEXT NOT NULL DEFAULT '[]',
    stale_reason TEXT
);
INSERT INTO stage_runs_v3 (id, take_id, sequence_id, stage, params_hash, params_json, status, artifacts_json, started_at,
                           ended_at, summary_json, error, pid, host, reads_json)
    SELECT id, take_id, sequence_id, stage, params_hash, params_json, status, artifacts_json, started_at, ended_at,
           summary_json, error, pid, host,
           CASE stage {_V2_READS_CASES} ELSE '[]' END
    FROM stage_runs;
DROP TABLE stage_runs;
ALTER TABLE stage_runs_v3 RENAME TO stage_runs;
CREATE UNIQUE INDEX stage_runs_key ON stage_runs (take_id, IFNULL(sequence_id, 0), stage);
""",
    # the quality gates' flags per take (dualhuman_builder.quality.gates)
    3: """
CREATE TABLE quality_checks (
    take_id INTEGER PRIMARY KEY REFERENCES takes(id) ON DELETE CASCADE,
    checked_at TEXT NOT NULL,
    evaluated_json TEXT NOT NULL DEFAULT '[]',
    skipped_json TEXT NOT NULL DEFAULT '{}',
    stages_json TEXT NOT NULL DEFAULT '{}'
);
CREATE TABLE quality_flags (
    id INTEGER PRIMARY KEY,
    take_id INTEGER NOT NULL REFERENCES takes(id) ON DELETE CASCADE,
    gate TEXT NOT NULL,
    stage TEXT NOT NULL,
    subject TEXT NOT NULL DEFAULT '',
    value REAL,
    threshold REAL,
    message TEXT NOT NULL,
    stage_ended_at TEXT
);
CREATE INDEX quality_flags_take ON quality_flags (take_id);
""",
}


def replace_flags(conn: sqlite3.Connection, take_id: int, flags: list[dict], check: dict) -> None:
    """Store the quality gates' verdict on take ``take_id`` in one transaction, replacing the one
    before: ``flags`` (dicts with ``gate``, ``stage``, ``subject``, ``value``, ``threshold``,
    ``message``, ``stage_ended_at``) and ``check`` (``evaluated``: gate names, ``skipped``: gate ->
    why, ``stages``: stage -> ``ended_at`` of the run read)."""
    with _transaction(conn):
        conn.execute("DELETE FROM quality_flags WHERE take_id = ?", (take_id,))
        conn.execute("INSERT OR REPLACE INTO quality_checks (take_id, checked_at, evaluated_json, skipped_json, stages_json) "
                     "VALUES (?, ?, ?, ?, ?)", (take_id, now_iso(), json.dumps(list(check.get("evaluated", ()))),
                     json.dumps(dict(check.get("skipped", {}))), json.dumps(dict(check.get("stages", {})))))  # fmt: skip
        conn.executemany("INSERT INTO quality_flags (take_id, gate, stage, subject, value, threshold, message, stage_ended_at) "
                         "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                         [(take_id, f["gate"], f["stage"], f.get("subject") or "", f.get("value"), f.get("threshold"),
                           f["message"], f.get("stage_ended_at")) for f in flags])  # fmt: skip


def take_flags(conn: sqlite3.Connection, take_id: int | None = None) -> dict[str, dict]:
    """The stored quality verdicts by take name (of ``take_id``, or every take checked):
    ``{"checked_at", "evaluated", "skipped", "stages", "flags": [dict, ...], "outdated": [stage, ...]}``;
    ``outdated`` lists the stages whose run the gates read has been replaced or is no longer done
    since (check the take again). A catalog not yet migrated (opened read-only) has none."""
    if not conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'quality_checks'").fetchone():
        return {}
    where, args = ("WHERE c.take_id = ?", (take_id,)) if take_id is not None else ("", ())
    out: dict[str, dict] = {}
    for r in conn.execute(f"SELECT c.*, t.name AS take FROM quality_checks c JOIN takes t ON t.id = c.take_id {where} "
                          "ORDER BY t.name", args).fetchall():  # fmt: skip
        stages = json.loads(r["stages_json"])
        current = {s["stage"]: s["ended_at"] for s in conn.execute(
            "SELECT stage, ended_at FROM stage_runs WHERE take_id = ? AND sequence_id IS NULL AND status = 'done'",
            (r["take_id"],))}  # fmt: skip
        flags = [{k: f[k] for k in ("gate", "stage", "subject", "value", "threshold", "message", "stage_ended_at")}
                 for f in conn.execute("SELECT * FROM quality_flags WHERE take_id = ? ORDER BY id", (r["take_id"],))]  # fmt: skip
        out[r["take"]] = {"checked_at": r["checked_at"], "evaluated": json.loads(r["evaluated_json"]),
                          "skipped": json.loads(r["skipped_json"]), "stages": stages, "flags": flags,
                          "outdated": sorted(s for s, t in stages.items() if current.get(s) != t)}  # fmt: skip
    return out


def now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


class CatalogConnection(sqlite3.Connection):
    """A connection that knows which catalog file it is on (:attr:`path`), to name it in errors."""

    path: Path | None = None


def _connect(uri: str, path: Path | None = None) -> sqlite3.Connection:
    conn = sqlite3.connect(uri, uri=True, timeout=30.0, isolation_level=None, factory=CatalogConnection)
    conn.path = path
    conn.row_factory = sqlite3.Row
    conn.execute("PRAGMA foreign_keys = ON")
    conn.execute("PRAGMA busy_timeout = 30000")
    return conn


def create_catalog(path: Path) -> sqlite3.Connection:
    """Create a new catalog at ``path`` (which must not exist) in WAL mode."""
    try:
        conn = _connect(f"file:{path}?mode=rwc", path)
        conn.execute("PRAGMA journal_mode = WAL")
        conn.execute("PRAGMA synchronous = NORMAL")
    except sqlite3.Error as e:
        raise catalog_error(e, path) from e
    with _transaction(conn):
        for statement in _statements(SCHEMA + "".join(MIGRATIONS.values())):
            conn.execute(statement)
        conn.executemany(
            "INSERT INTO meta (key, value) VALUES (?, ?)",
            [("format_version", str(CATALOG_VERSION)), ("created_with", f"dualhuman-builder {__version__}"),
             ("created_at", now_iso())],
        )  # fmt: skip
    return conn


def _statements(script: str) -> list[str]:
    return [s for s in script.split(";") if s.strip()]


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
        return _connect(f"file:{path}?mode=ro&immutable=1", path)
    conn = _connect(f"file:{path}?mode=ro", path)
    try:
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.OperationalError:  # WAL side files cannot be created in a read-only folder
        conn.close()
        return _connect(f"file:{path}?mode=ro&immutable=1", path)


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
        conn = _connect(f"file:{path}?mode=rw", path)
        conn.execute("PRAGMA synchronous = NORMAL")
        _migrate(conn)
        return conn
    except sqlite3.Error as e:
        raise catalog_error(e, path) from e


class CatalogError(WorkspaceError):
    """SQLite failed on the catalog; :attr:`code` is SQLite's extended result code (None if unknown)."""

    def __init__(self, message: str, *, code: int | None = None, fix: str | None = None, path=None):
        super().__init__(message, fix=fix, path=path)
        self.code = code


def catalog_error(e: sqlite3.Error, path: Path | None) -> CatalogError:
    """The :class:`CatalogError` for SQLite error ``e`` on the catalog at ``path``: the real
    reason (SQLite's message and result code name) and advice that is safe for it. Only a damaged
    file (``SQLITE_CORRUPT``, ``SQLITE_NOTADB``) is told to be restored or re-created; a full disk
    or an I/O error (``SQLITE_FULL``, ``SQLITE_IOERR``; what writing in the folder gives and the
    free space are added), a lock (``SQLITE_BUSY``, ``SQLITE_LOCKED``) and a file that cannot be
    written or opened leave the catalog intact, since SQLite rolls back what it could not finish."""
    code = getattr(e, "sqlite_errorcode", None)
    primary = code & 0xFF if isinstance(code, int) else None
    what = f"{e} ({getattr(e, 'sqlite_errorname', None) or type(e).__name__})"
    path = Path(path) if path is not None else Path(CATALOG_NAME)
    ws = path.parent
    intact = "the catalog is intact (SQLite rolled back what it could not finish): do not move it aside or re-create it"
    if primary in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB):
        return CatalogError(f"catalog is damaged: {what}", code=code, path=path,
                            fix=f"restore {path.name} from a backup, or move it aside and run `dualhuman init {ws}` for "
                                "a new, empty catalog (files under artifacts/ and takes/ are not touched)")  # fmt: skip
    if primary in (sqlite3.SQLITE_FULL, sqlite3.SQLITE_IOERR):
        found = disk_problem(ws)
        head = "cannot write the catalog" if primary == sqlite3.SQLITE_FULL else "I/O error on the catalog"
        return CatalogError(f"{head}: {what}" + (f"; {found}" if found else ""), code=code, path=path,
                            fix=f"free space on the disk holding {ws} (or fix the device); {intact}")  # fmt: skip
    if primary in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED):
        return CatalogError(f"catalog is locked by another process: {what}", code=code, path=path,
                            fix="wait for the other command on this workspace to finish; the catalog is intact")  # fmt: skip
    if primary in (sqlite3.SQLITE_READONLY, sqlite3.SQLITE_CANTOPEN, sqlite3.SQLITE_PERM, sqlite3.SQLITE_AUTH):
        return CatalogError(f"catalog cannot be opened or written: {what}", code=code, path=path,
                            fix=f"make {ws} and the catalog's files ({path.name}, {path.name}-wal, {path.name}-shm) "
                                f"writable (chmod -R u+w {ws}); {intact}")  # fmt: skip
    return CatalogError(f"catalog error: {what}", code=code, path=path,
                        fix=f"if it fails the same way again, copy the workspace and check the copy with `dualhuman "
                            f"status COPY --verify`; {intact}")  # fmt: skip


def disk_problem(folder: Path) -> str | None:
    """What the operating system says about writing in ``folder``: the error of writing a 1 MiB
    probe file there (removed again) and the free space, or only the free space when under 1 MiB;
    None when writing works and space is left."""
    probe = Path(folder) / f".dualhuman-write-probe-{os.getpid()}"
    found = None
    try:
        with open(probe, "wb") as f:
            f.write(bytes(1 << 20))
            f.flush()
            os.fsync(f.fileno())
    except OSError as e:
        found = f"writing in {folder} fails: {e.strerror} ({errno.errorcode.get(e.errno, e.errno)})"
    finally:
        try:
            probe.unlink()
        except OSError:
            pass
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return found
    if found or free < 1 << 20:
        return f"{found + ', ' if found else ''}{free:,} bytes free on its disk"
    return found


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
            for statement in _statements(MIGRATIONS[k]):
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
    """``with _transaction(conn):`` — BEGIN IMMEDIATE ... COMMIT, ROLLBACK on error. A SQLite error
    (in the block, or beginning or committing) is raised as :func:`catalog_error`'s WorkspaceError."""

    def __init__(self, conn: sqlite3.Connection):
        self.conn = conn

    def __enter__(self):
        try:
            self.conn.execute("BEGIN IMMEDIATE")
        except sqlite3.Error as e:
            raise catalog_error(e, getattr(self.conn, "path", None)) from e
        return self.conn

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                self.conn.execute("COMMIT")
                return False
            except sqlite3.Error as e:
                exc = e
        self._rollback()
        if isinstance(exc, sqlite3.Error):
            raise catalog_error(exc, getattr(self.conn, "path", None)) from exc
        return False

    def _rollback(self) -> None:
        if self.conn.in_transaction:
            try:
                self.conn.execute("ROLLBACK")
            except sqlite3.Error:
                pass  # SQLite rolls back itself when it cannot (a full disk, an I/O error)


transaction = _transaction
