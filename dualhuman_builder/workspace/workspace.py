"""A workspace: a folder holding a catalog and the artifacts of every take and stage.

Layout::

    WS/
      catalog.sqlite            the catalog (SQLite, WAL); see :mod:`.catalog`
      takes/<take>/             a take's source files (recordings, imports)
      artifacts/<take>/<seq>/<stage>/   what each stage wrote (``_take`` for take-level stages)

Every method that writes checks first and raises :class:`WorkspaceError` (or
:class:`~dualhuman_builder.errors.RigError`) without modifying anything when input is bad.
"""

from __future__ import annotations

import json
import os
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.fileio import sha256_file
from dualhuman_builder.workspace.catalog import (
    CATALOG_NAME,
    check_catalog_file,
    create_catalog,
    now_iso,
    open_catalog,
    transaction,
)

#: Folder name of a take-level stage's artifacts (in place of a sequence name).
TAKE_LEVEL = "_take"


#: Unicode categories a name may not contain, and that :func:`printable` escapes: control
#: characters (terminal escapes, newlines), format characters (bidirectional overrides),
#: surrogates, private use, line and paragraph separators.
UNSAFE_CATEGORIES = frozenset({"Cc", "Cf", "Cs", "Co", "Zl", "Zp"})


def printable(text: str) -> str:
    """``text`` with every character of :data:`UNSAFE_CATEGORIES` written as its escape
    (``\\x1b``, ``\\n``, ``\\u202e``), so that printing a name cannot move the cursor, clear the
    screen or reorder what follows."""
    return "".join(c.encode("unicode_escape").decode("ascii") if unicodedata.category(c) in UNSAFE_CATEGORIES else c
                   for c in str(text))  # fmt: skip


def check_printable(kind: str, text: str) -> str:
    """``text``, or a :class:`WorkspaceError` naming the control or format characters it holds."""
    bad = sorted({c for c in str(text) if unicodedata.category(c) in UNSAFE_CATEGORIES})
    if bad:
        raise WorkspaceError(
            f"{kind} '{printable(text)}' contains control characters ({', '.join(map(printable, bad))})",
            fix=f"give the {kind} without control characters (no escape sequences, tabs or line breaks)",
        )
    return text


def _check_name(kind: str, name: str) -> str:
    check_printable(f"{kind} name", name)
    if not name or name.startswith(".") or name.startswith("_") or any(c in name for c in "/\\\0") or len(name) > 128:
        raise WorkspaceError(
            f"invalid {kind} name {name!r}",
            fix="use letters, digits, '-', '.' or '_' (not first), no slashes, at most 128 characters",
        )
    return name


@dataclass(frozen=True)
class Actor:
    name: str
    height_m: float | None
    gender: str | None
    shape: dict[str, float] | None
    shape_source: str | None


@dataclass(frozen=True)
class Take:
    name: str
    rig: str | None
    actors: tuple[str, ...]
    start_time: str | None
    duration_s: float | None
    sample_counts: dict[str, int]
    files: tuple[dict, ...]
    meta: dict[str, Any]


@dataclass(frozen=True)
class SequenceInfo:
    take: str
    name: str
    frame_start: int
    frame_stop: int
    labels: tuple[str, ...]
    text: tuple[str, ...]


class Workspace:
    """Open with :meth:`open` (existing) or :meth:`init` (create or reuse). Use as a context manager."""

    def __init__(self, root: Path, conn, readonly: bool):
        self.root = root
        self.conn = conn
        self.readonly = readonly

    # ------------------------------------------------------------------ open / create
    @classmethod
    def init(cls, root: str | Path) -> "Workspace":
        """Create a workspace at ``root`` (the folder may exist), or open the one already there."""
        root = Path(root)
        catalog = root / CATALOG_NAME
        if catalog.exists():
            return cls.open(root)
        if root.exists() and not root.is_dir():
            raise WorkspaceError("exists and is not a folder", path=root, fix="choose another path")
        parent = root if root.exists() else _existing_parent(root)
        if not os.access(parent, os.W_OK | os.X_OK):
            raise WorkspaceError(
                "cannot create a workspace here: folder is not writable",
                path=parent,
                fix="choose a folder you can write to, or fix its permissions (chmod u+w)",
            )
        root.mkdir(parents=True, exist_ok=True)
        for sub in ("takes", "artifacts"):
            (root / sub).mkdir(exist_ok=True)
        conn = create_catalog(catalog)
        return cls(root, conn, readonly=False)

    @classmethod
    def open(cls, root: str | Path, readonly: bool = False) -> "Workspace":
        """Open an existing workspace; ``readonly`` for commands that only read (``status``)."""
        root = Path(root)
        if not root.is_dir():
            raise WorkspaceError("no such workspace folder", path=root, fix=f"create one with `dualhuman init {root}`")
        check_catalog_file(root / CATALOG_NAME)
        if not readonly:
            for p in (root, root / CATALOG_NAME):
                if not os.access(p, os.W_OK):
                    raise WorkspaceError(
                        "workspace is not writable",
                        path=p,
                        fix=f"fix permissions (chmod -R u+w {root}) or copy the workspace somewhere writable",
                    )
        conn = open_catalog(root / CATALOG_NAME, readonly=readonly)
        ws = cls(root, conn, readonly=readonly)
        if not readonly:
            from dualhuman_builder.workspace.runner import finish_publications

            try:
                finish_publications(ws)  # stage results a killed process left half published
            except BaseException:
                ws.close()
                raise
        return ws

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> "Workspace":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def catalog_path(self) -> Path:
        return self.root / CATALOG_NAME

    def _require_writable(self) -> None:
        if self.readonly:
            raise WorkspaceError("workspace was opened read-only", path=self.root)

    # ------------------------------------------------------------------ actors
    def add_actor(self, name: str, height_m: float | None = None, gender: str | None = None,
                  shape: Mapping[str, float] | None = None, shape_source: str | None = None) -> Actor:  # fmt: skip
        """Register an actor (or update the given fields of an existing one)."""
        self._require_writable()
        _check_name("actor", name)
        if height_m is not None and not (0.5 < float(height_m) < 2.6):
            raise WorkspaceError(f"height {height_m} is not a human height in metres", fix="give the height in metres")
        now = now_iso()
        with transaction(self.conn):
            row = self.conn.execute("SELECT * FROM actors WHERE name = ?", (name,)).fetchone()
            if row is None:
                self.conn.execute(
                    "INSERT INTO actors (name, height_m, gender, shape_json, shape_source, created_at, updated_at) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (name, height_m, gender, json.dumps(dict(shape)) if shape else None, shape_source, now, now),
                )
            else:
                self.conn.execute(
                    "UPDATE actors SET height_m = COALESCE(?, height_m), gender = COALESCE(?, gender), "
                    "shape_json = COALESCE(?, shape_json), shape_source = COALESCE(?, shape_source), updated_at = ? "
                    "WHERE name = ?",
                    (height_m, gender, json.dumps(dict(shape)) if shape else None, shape_source, now, name),
                )
        return self.actor(name)

    def actor(self, name: str) -> Actor:
        row = self.conn.execute("SELECT * FROM actors WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise WorkspaceError(f"no actor {name!r} in this workspace", path=self.root,
                                 fix=f"add it with `dualhuman actor add {self.root} {name} --height H`")  # fmt: skip
        return _actor(row)

    def actors(self) -> list[Actor]:
        return [_actor(r) for r in self.conn.execute("SELECT * FROM actors ORDER BY name")]

    # ------------------------------------------------------------------ rigs
    def add_rig(self, path: str | Path) -> str:
        """Check a rig file and store its text in the catalog (replacing an older version)."""
        from dualhuman_builder.rig import load_rig

        self._require_writable()
        rig = load_rig(path)
        check_printable("rig name", rig.name)
        with transaction(self.conn):
            self.conn.execute(
                "INSERT INTO rigs (name, path, sha256, content, created_at) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT(name) DO UPDATE SET path = excluded.path, sha256 = excluded.sha256, "
                "content = excluded.content",
                (rig.name, str(Path(path).resolve()), rig.sha256, rig.text, now_iso()),
            )
        return rig.name

    def rig_text(self, name: str) -> str:
        row = self.conn.execute("SELECT content FROM rigs WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise WorkspaceError(f"no rig {name!r} in this workspace", path=self.root,
                                 fix=f"register it with `dualhuman rig add {self.root} RIG.toml`")  # fmt: skip
        return row["content"]

    def rigs(self) -> list[tuple[str, str]]:
        return [(r["name"], r["sha256"]) for r in self.conn.execute("SELECT name, sha256 FROM rigs ORDER BY name")]

    # ------------------------------------------------------------------ takes and sequences
    def take_dir(self, take: str) -> Path:
        return self.root / "takes" / _check_name("take", take)

    def add_take(self, name: str, *, rig: str | None = None, actors: Sequence[str] = (), files: Iterable[str | Path] = (),
                 start_time: str | None = None, duration_s: float | None = None,
                 sample_counts: Mapping[str, int] | None = None, meta: Mapping[str, Any] | None = None) -> Take:  # fmt: skip
        """Register a take with its source files (hashed here), rig and actors (in slot order)."""
        self._require_writable()
        _check_name("take", name)
        if self.conn.execute("SELECT 1 FROM takes WHERE name = ?", (name,)).fetchone():
            raise WorkspaceError(f"take {name!r} already exists", path=self.root, fix="choose another take name")
        rig_id = None
        if rig is not None:
            r = self.conn.execute("SELECT id FROM rigs WHERE name = ?", (rig,)).fetchone()
            if r is None:
                raise WorkspaceError(f"no rig {rig!r} in this workspace", path=self.root,
                                     fix=f"register it with `dualhuman rig add {self.root} RIG.toml`")  # fmt: skip
            rig_id = r["id"]
        actor_ids = [self._actor_id(a) for a in actors]
        hashed = []
        for f in files:
            p = Path(f)
            if not p.is_file():
                raise WorkspaceError("take source file not found", path=p)
            rel = os.path.relpath(p.resolve(), self.root.resolve())
            hashed.append((rel, sha256_file(p), p.stat().st_size))
        with transaction(self.conn):
            cur = self.conn.execute(
                "INSERT INTO takes (name, rig_id, start_time, duration_s, sample_counts_json, meta_json, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (name, rig_id, start_time, duration_s, json.dumps(dict(sample_counts or {})),
                 json.dumps(dict(meta or {})), now_iso()),
            )  # fmt: skip
            take_id = cur.lastrowid
            self.conn.executemany("INSERT INTO take_actors (take_id, slot, actor_id) VALUES (?, ?, ?)",
                                  [(take_id, i, a) for i, a in enumerate(actor_ids)])  # fmt: skip
            self.conn.executemany("INSERT INTO take_files (take_id, path, sha256, size_bytes) VALUES (?, ?, ?, ?)",
                                  [(take_id, *h) for h in hashed])  # fmt: skip
        return self.take(name)

    def _actor_id(self, name: str) -> int:
        row = self.conn.execute("SELECT id FROM actors WHERE name = ?", (name,)).fetchone()
        if row is None:
            self.actor(name)  # raises the specific error
        return row["id"]

    def _take_id(self, name: str) -> int:
        row = self.conn.execute("SELECT id FROM takes WHERE name = ?", (name,)).fetchone()
        if row is None:
            raise WorkspaceError(f"no take {name!r} in this workspace", path=self.root,
                                 fix=f"list takes with `dualhuman status {self.root}`")  # fmt: skip
        return row["id"]

    def take(self, name: str) -> Take:
        tid = self._take_id(name)
        row = self.conn.execute(
            "SELECT t.*, r.name AS rig_name FROM takes t LEFT JOIN rigs r ON r.id = t.rig_id WHERE t.id = ?", (tid,)
        ).fetchone()
        actors = [r["name"] for r in self.conn.execute(
            "SELECT a.name FROM take_actors ta JOIN actors a ON a.id = ta.actor_id WHERE ta.take_id = ? ORDER BY slot",
            (tid,))]  # fmt: skip
        files = [dict(r) for r in self.conn.execute(
            "SELECT path, sha256, size_bytes, role FROM take_files WHERE take_id = ? ORDER BY path", (tid,))]  # fmt: skip
        return Take(name, row["rig_name"], tuple(actors), row["start_time"], row["duration_s"],
                    json.loads(row["sample_counts_json"]), tuple(files), json.loads(row["meta_json"]))  # fmt: skip

    def takes(self) -> list[str]:
        return [r["name"] for r in self.conn.execute("SELECT name FROM takes ORDER BY name")]

    def verify_take_files(self, take: str) -> list[str]:
        """Problems with a take's source files (missing, changed); empty when all match."""
        problems = []
        for f in self.take(take).files:
            p = self.root / f["path"]
            if not p.is_file():
                problems.append(f"{f['path']}: missing")
            elif sha256_file(p) != f["sha256"]:
                problems.append(f"{f['path']}: SHA-256 differs from the catalog")
        return problems

    def add_sequence(self, take: str, name: str, frame_start: int, frame_stop: int,
                     labels: Sequence[str] = (), text: Sequence[str] = ()) -> SequenceInfo:  # fmt: skip
        """Register frames ``[frame_start, frame_stop)`` of ``take`` as sequence ``name``."""
        self._require_writable()
        _check_name("sequence", name)
        for label in labels:
            check_printable("label", label)
        tid = self._take_id(take)
        if not 0 <= int(frame_start) < int(frame_stop):
            raise WorkspaceError(f"sequence {name!r}: need 0 <= frame_start < frame_stop, got {frame_start}, {frame_stop}")
        if self.conn.execute("SELECT 1 FROM sequences WHERE take_id = ? AND name = ?", (tid, name)).fetchone():
            raise WorkspaceError(f"take {take!r} already has a sequence {name!r}", fix="choose another name")
        with transaction(self.conn):
            self.conn.execute(
                "INSERT INTO sequences (take_id, name, frame_start, frame_stop, labels_json, text_json, created_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (tid, name, int(frame_start), int(frame_stop), json.dumps(list(labels)), json.dumps(list(text)), now_iso()),
            )
        return self.sequence(take, name)

    def _sequence_id(self, take: str, name: str | None) -> int | None:
        if name is None:
            return None
        row = self.conn.execute("SELECT id FROM sequences WHERE take_id = ? AND name = ?",
                                (self._take_id(take), name)).fetchone()  # fmt: skip
        if row is None:
            raise WorkspaceError(f"take {take!r} has no sequence {name!r}", path=self.root,
                                 fix=f"list sequences with `dualhuman status {self.root}`")  # fmt: skip
        return row["id"]

    def sequence(self, take: str, name: str) -> SequenceInfo:
        sid = self._sequence_id(take, name)
        r = self.conn.execute("SELECT * FROM sequences WHERE id = ?", (sid,)).fetchone()
        return SequenceInfo(take, r["name"], r["frame_start"], r["frame_stop"],
                            tuple(json.loads(r["labels_json"])), tuple(json.loads(r["text_json"])))  # fmt: skip

    def sequences(self, take: str) -> list[SequenceInfo]:
        rows = self.conn.execute("SELECT name FROM sequences WHERE take_id = ? ORDER BY name", (self._take_id(take),))
        return [self.sequence(take, r["name"]) for r in rows.fetchall()]

    # ------------------------------------------------------------------ annotations
    def annotate(self, annotations: Iterable) -> int:
        """Store :class:`~dualhuman_builder.labels.Annotation` records, all or none (one
        transaction); a record replaces the one of the same take, sequence and annotator. The
        records must be checked already (:func:`~dualhuman_builder.labels.check_annotation`);
        an unknown take or sequence is an error. Returns the number stored."""
        self._require_writable()
        rows = []
        for a in annotations:
            check_printable("annotator name", a.annotator)
            for kind, value in (("actor name", a.actor), ("reactor name", a.reactor), ("annotation source", a.source)):
                if value is not None:
                    check_printable(kind, value)
            for label in a.labels:
                check_printable("label", label)
            tid = self._take_id(a.take)
            sid = self._sequence_id(a.take, a.sequence)
            rows.append((tid, sid, a.annotator, json.dumps(list(a.labels)), json.dumps(list(a.texts), ensure_ascii=False),
                         a.actor, a.reactor, None if a.symmetric is None else int(a.symmetric), a.annotated_at or now_iso(),
                         a.source))  # fmt: skip
        with transaction(self.conn):
            for r in rows:
                self.conn.execute("DELETE FROM annotations WHERE take_id = ? AND IFNULL(sequence_id, 0) = IFNULL(?, 0) "
                                  "AND annotator = ?", r[:3])  # fmt: skip
                self.conn.execute("INSERT INTO annotations (take_id, sequence_id, annotator, labels_json, texts_json, actor, "
                                  "reactor, symmetric, annotated_at, source) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", r)  # fmt: skip
        return len(rows)

    def annotations(self, take: str | None = None) -> list:
        """The stored annotations (of ``take``, or all), ordered by take, sequence (take-level
        first), annotator. An old catalog not yet migrated (opened read-only) has none."""
        from dualhuman_builder.labels import Annotation

        if not self.conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'annotations'").fetchone():
            return []
        q = ("SELECT t.name AS take, s.name AS seq, a.* FROM annotations a JOIN takes t ON t.id = a.take_id "
             "LEFT JOIN sequences s ON s.id = a.sequence_id")  # fmt: skip
        args: tuple = ()
        if take is not None:
            q += " WHERE a.take_id = ?"
            args = (self._take_id(take),)
        rows = self.conn.execute(q + " ORDER BY t.name, IFNULL(s.name, ''), a.annotator", args).fetchall()
        return [Annotation(r["take"], r["seq"], r["annotator"], tuple(json.loads(r["labels_json"])),
                           tuple(json.loads(r["texts_json"])), r["actor"], r["reactor"],
                           None if r["symmetric"] is None else bool(r["symmetric"]), r["annotated_at"], r["source"])
                for r in rows]  # fmt: skip

    # ------------------------------------------------------------------ stages
    def artifact_dir(self, stage: str, take: str, sequence: str | None = None) -> Path:
        return self.root / "artifacts" / _check_name("take", take) / (sequence or TAKE_LEVEL) / stage

    def run_stage(self, stage, compute, *, take: str, sequence: str | None = None,
                  params: Mapping[str, Any] | None = None, depends_on: Sequence[Sequence] = (),
                  version: str = "1", force: bool = False):  # fmt: skip
        """Run ``compute(out)`` for one (take, sequence, stage) unless it is up to date, and publish
        its result atomically (``stage``: a :class:`~dualhuman_builder.workspace.runner.Stage` or
        its name). See :func:`dualhuman_builder.workspace.runner.run_stage`.
        """
        from dualhuman_builder.workspace.runner import run_stage

        self._require_writable()
        return run_stage(self, stage, compute, take=take, sequence=sequence, params=params or {},
                         depends_on=depends_on, version=version, force=force)  # fmt: skip

    def stage_record(self, stage: str, take: str, sequence: str | None = None):
        """The catalog row of a stage run as a dict, or None if it never ran."""
        from dualhuman_builder.workspace.runner import stage_record

        return stage_record(self, stage, take, sequence)

    def artifacts(self, stage: str, take: str, sequence: str | None = None) -> dict[str, Path]:
        """Paths of a completed stage's artifacts by name; raises if the stage is not done."""
        rec = self.stage_record(stage, take, sequence)
        where = f"{take}/{sequence}" if sequence else take
        if rec is None or rec["status"] != "done":
            state = "never ran" if rec is None else rec["status"]
            if rec is not None and rec["status"] == "stale" and rec["stale_reason"]:
                state += f": {rec['stale_reason']}"
            raise WorkspaceError(f"stage {stage!r} of {where} is not complete ({state})",
                                 path=self.root, fix=f"run the {stage} stage first")  # fmt: skip
        return {name: self.root / a["path"] for name, a in rec["artifacts"].items()}

    def verify(self) -> list[str]:
        """Re-hash every take source file and every published stage result's artifacts (done or
        stale) against the catalog; returns the problems found (empty when everything matches)."""
        from dualhuman_builder.workspace.runner import _record, artifact_problems

        problems = []
        for take in self.takes():
            problems += [f"take {take}: {p}" for p in self.verify_take_files(take)]
        rows = self.conn.execute(
            "SELECT r.*, t.name AS take_name, s.name AS seq_name FROM stage_runs r JOIN takes t ON t.id = r.take_id "
            "LEFT JOIN sequences s ON s.id = r.sequence_id WHERE r.status IN ('done', 'stale') "
            "ORDER BY t.name, s.name, r.stage"
        ).fetchall()
        for r in rows:
            where = f"{r['take_name']}/{r['seq_name']}" if r["seq_name"] else r["take_name"]
            rec = _record(r)
            if rec["status"] in ("publishing", "interrupted"):
                problems.append(f"{where} {r['stage']}: its new result is being published, or was cut off while it was "
                                "(open the workspace for writing, e.g. run the stage again, to finish it)")  # fmt: skip
                continue
            problems += [f"{where} {r['stage']}: {p}" for p in artifact_problems(self, rec, verify=True)]
        return problems

    def status_rows(self) -> list[dict[str, Any]]:
        """One row per take and per sequence: ``{"take", "sequence", "stages": {stage: info}}``."""
        from dualhuman_builder.workspace.runner import describe_run

        rows = []
        runs: dict[tuple[int, int | None], dict[str, Any]] = {}
        for r in self.conn.execute("SELECT * FROM stage_runs"):
            runs.setdefault((r["take_id"], r["sequence_id"]), {})[r["stage"]] = describe_run(r)
        for t in self.conn.execute("SELECT id, name FROM takes ORDER BY name").fetchall():
            rows.append({"take": t["name"], "sequence": None, "stages": runs.get((t["id"], None), {})})
            for s in self.conn.execute("SELECT id, name, frame_start, frame_stop FROM sequences WHERE take_id = ? "
                                       "ORDER BY name", (t["id"],)).fetchall():  # fmt: skip
                rows.append({"take": t["name"], "sequence": s["name"], "frames": (s["frame_start"], s["frame_stop"]),
                             "stages": runs.get((t["id"], s["id"]), {})})  # fmt: skip
        return rows


def _actor(row) -> Actor:
    return Actor(row["name"], row["height_m"], row["gender"],
                 json.loads(row["shape_json"]) if row["shape_json"] else None, row["shape_source"])  # fmt: skip


def _existing_parent(p: Path) -> Path:
    p = p.absolute()
    while not p.exists():
        p = p.parent
    return p
