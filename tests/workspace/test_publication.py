"""Stage publication: a re-run replaces a stage's result all at once or not at all, and a new
result makes every run that reads it stale (the Stage ``reads`` declarations of the pipeline)."""

import sqlite3
import subprocess
import sys
import textwrap

import pytest

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.pipeline import CAPTURE, CONTACTS, FIT, FUSE, RENDER, SCENE, SHEET, STAGES, SYNC
from dualhuman_builder.workspace import Workspace
from dualhuman_builder.workspace import catalog as catalog_module
from dualhuman_builder.workspace.runner import OLD_PREFIX, STAGING_PREFIX


def _files(**files):
    """A compute that writes ``files`` (name -> text); names with ``__`` are sub-folders."""

    def compute(out):
        for name, text in files.items():
            out.path(name.replace("__", "/")).write_text(text)
        return {"files": len(files)}

    return compute


def _boom(out):
    out.path("sync.npz").write_text("half")
    raise RuntimeError("the recording's precondition failed")


def _pipeline(ws, take="T1", sequences=("s1",)):
    """Every stage of the pipeline, in order, with its real declaration and small made-up files."""
    ws.add_take(take)
    for seq in sequences:
        ws.add_sequence(take, seq, 0, 10)
        ws.run_stage(SCENE, _files(**{"scene.npz": f"scene {seq}"}), take=take, sequence=seq, params={})
        ws.run_stage(CAPTURE, _files(**{"take.mcap": f"take {seq}"}), take=take, sequence=seq, params={},
                     depends_on=[("scene", seq)])
    ws.run_stage(SYNC, _files(**{"sync.npz": "sync 1", "sync.json": "{}"}), take=take, params={"fps": 30},
                 depends_on=[("capture", s) for s in sequences])
    ws.run_stage(FUSE, _files(**{"a.skeleton.npz": "fuse"}), take=take, params={}, depends_on=[("sync", None)])
    ws.run_stage(FIT, _files(**{"bodies.npz": "fit"}), take=take, params={}, depends_on=[("fuse", None)])
    ws.run_stage(CONTACTS, _files(**{"contacts.npz": "c"}), take=take, params={}, depends_on=[("fit", None)])
    ws.run_stage(RENDER, _files(**{"render.json": "{}", "views__v0__rgb__00000.png": "png"}), take=take, params={},
                 depends_on=[("fit", None)])
    ws.run_stage(SHEET, _files(**{"contact_sheet.png": "sheet"}), take=take, params={},
                 depends_on=[("render", None), ("contacts", None)])


def _states(ws, take="T1"):
    """{stage or stage/sequence: state} of ``take``'s runs, as `dualhuman status` shows them."""
    out = {}
    for r in ws.status_rows():
        if r["take"] == take:
            out.update({(n if r["sequence"] is None else f"{n}/{r['sequence']}"): i["state"] for n, i in r["stages"].items()})
    return out


DOWNSTREAM_OF_SYNC = {"fuse", "fit", "contacts", "render", "sheet"}


def test_a_failed_rerun_keeps_the_published_result_and_its_state(ws):
    _pipeline(ws)
    before = {n: p.read_bytes() for n, p in ws.artifacts("sync", "T1").items()}
    with pytest.raises(RuntimeError, match="precondition failed"):
        ws.run_stage(SYNC, _boom, take="T1", params={"fps": 30}, depends_on=[("capture", "s1")], force=True)
    # the old result is where it was, still done, and so is everything that reads it
    assert {n: p.read_bytes() for n, p in ws.artifacts("sync", "T1").items()} == before
    assert set(_states(ws).values()) == {"done"} and ws.verify() == []
    rec = ws.stage_record("sync", "T1")
    assert rec["status"] == "done" and rec["attempt"] == "failed" and "precondition failed" in rec["error"]
    info = next(r for r in ws.status_rows() if r["sequence"] is None)["stages"]["sync"]
    assert info["state"] == "done" and info["error"].startswith("a re-run failed (the previous result is kept)")
    assert [p.name for p in (ws.root / "artifacts/T1/_take").iterdir() if p.name.startswith(".")] == []
    assert FIT.artifact(ws, "T1", "bodies.npz").read_text() == "fit"
    # run as before, it is up to date (the failed attempt's note is cleared); forced, a new result replaces the old
    assert ws.run_stage(SYNC, _boom, take="T1", params={"fps": 30}, depends_on=[("capture", "s1")]).skipped
    assert ws.stage_record("sync", "T1")["attempt"] is None
    r = ws.run_stage(SYNC, _files(**{"sync.npz": "sync 2", "sync.json": "{}"}), take="T1", params={"fps": 30},
                     depends_on=[("capture", "s1")], force=True)  # fmt: skip
    assert r.artifacts["sync.npz"].read_text() == "sync 2" and ws.stage_record("sync", "T1")["error"] is None


def test_a_new_result_makes_what_reads_it_stale(ws):
    _pipeline(ws, sequences=("s1", "s2"))
    r = ws.run_stage(SYNC, _files(**{"sync.npz": "sync 2", "sync.json": "{}"}), take="T1", params={"fps": 25},
                     depends_on=[("capture", "s1"), ("capture", "s2")])  # fmt: skip
    assert sorted(r.made_stale) == [("T1", None, s) for s in sorted(DOWNSTREAM_OF_SYNC)]
    states = _states(ws)
    assert {n for n, s in states.items() if s == "stale"} == DOWNSTREAM_OF_SYNC
    assert states["sync"] == "done" and states["capture/s1"] == "done"
    rec = ws.stage_record("fit", "T1")
    assert rec["status"] == "stale" and rec["stale_reason"] == "sync of T1 has a new result"
    assert FIT.state(ws, "T1") == "stale" and not FIT.done(ws, "T1")
    with pytest.raises(WorkspaceError, match=r"no fitted bodies: its fit stage is stale \(sync of T1 has a new") as e:
        FIT.artifact(ws, "T1", "bodies.npz", what="fitted bodies")
    assert e.value.fix == f"dualhuman fit {ws.root} --take T1"
    with pytest.raises(WorkspaceError, match=r"not complete \(stale: sync of T1"):
        ws.artifacts("fit", "T1")
    with pytest.raises(WorkspaceError, match=r"needs stage 'fit' of T1 to be complete first \(it is stale\)"):
        ws.run_stage(CONTACTS, _files(x="1"), take="T1", params={}, depends_on=[("fit", None)])
    assert ws.verify() == []  # stale results stay on disk, intact, until their stages run again
    ws.artifacts("sync", "T1")["sync.npz"].write_text("cut")  # an input damaged on disk: refused before starting
    with pytest.raises(WorkspaceError, match=r"needs stage 'sync' of T1, whose files changed on disk: sync.npz: size"):
        ws.run_stage(FUSE, _files(**{"a.skeleton.npz": "fuse"}), take="T1", params={}, depends_on=[("sync", None)])
    assert ws.stage_record("fuse", "T1")["attempt"] is None
    ws.artifacts("sync", "T1")["sync.npz"].write_text("sync 2")
    # the stale stages can run again; one that runs with the same result leaves the later ones stale
    ws.run_stage(FUSE, _files(**{"a.skeleton.npz": "fuse"}), take="T1", params={}, depends_on=[("sync", None)])
    assert _states(ws)["fuse"] == "done" and _states(ws)["fit"] == "stale"
    ws.run_stage(FIT, _files(**{"bodies.npz": "fit 2"}), take="T1", params={}, depends_on=[("fuse", None)])
    assert {n for n, s in _states(ws).items() if s == "stale"} == {"contacts", "render", "sheet"}
    # a per-sequence change: only that sequence's readers and the take-level ones
    ws.run_stage(SCENE, _files(**{"scene.npz": "scene s2, again"}), take="T1", sequence="s2", params={"seed": 2})
    states = _states(ws)
    assert states["capture/s2"] == "stale" and states["capture/s1"] == "done"
    assert states["sync"] == "stale" and states["fuse"] == "stale"


def test_a_forced_rerun_marks_downstream_stale_but_a_repair_does_not(ws):
    _pipeline(ws)
    contacts = ws.artifacts("contacts", "T1")["contacts.npz"]
    contacts.unlink()  # a lost artifact: the stage runs again with the same result
    ws.run_stage(CONTACTS, _files(**{"contacts.npz": "c"}), take="T1", params={}, depends_on=[("fit", None)])
    assert set(_states(ws).values()) == {"done"}
    ws.run_stage(CONTACTS, _files(**{"contacts.npz": "c"}), take="T1", params={}, depends_on=[("fit", None)],
                 force=True)
    assert {n for n, s in _states(ws).items() if s == "stale"} == {"sheet"}
    assert ws.stage_record("sheet", "T1")["stale_reason"] == "contacts of T1 was run again (forced)"


def test_another_takes_result_makes_its_readers_stale(ws):
    _pipeline(ws, take="CAL")
    _pipeline(ws, take="T2")
    ws.run_stage(SYNC, _files(**{"sync.npz": "with CAL's mounts"}), take="T2", params={"mounts_from": "CAL"},
                 depends_on=[("capture", "s1"), ("sync", None, "CAL")])  # fmt: skip
    assert ws.stage_record("sync", "T2")["reads"] == ["CAL/sync", "capture"]
    ws.run_stage(SYNC, _files(**{"sync.npz": "CAL again"}), take="CAL", params={"fps": 25})
    assert _states(ws, "T2")["sync"] == "stale" and _states(ws, "T2")["fuse"] == "stale"
    assert ws.stage_record("sync", "T2")["stale_reason"] == "sync of CAL has a new result"


def test_every_stage_reads_what_it_declares(ws):
    _pipeline(ws)
    for st in STAGES:
        if st.name in ("devices",):
            continue
        seq = "s1" if st.per == "sequence" else None
        assert ws.stage_record(st.name, "T1", seq)["reads"] == sorted(st.reads), st.name
    with pytest.raises(ValueError, match=r"depends on \['fuse'\], which its declaration does not read"):
        ws.run_stage(CONTACTS, _files(x="1"), take="T1", params={}, depends_on=[("fuse", None)])


def test_export_leaves_out_a_take_whose_fit_is_stale(ws):
    from dualhuman_builder.export.collect import workspace_items

    _pipeline(ws)
    ws.run_stage(FUSE, _files(**{"a.skeleton.npz": "fuse 2"}), take="T1", params={"v": 2}, depends_on=[("sync", None)])
    items, left_out = workspace_items(ws)
    assert items == [] and left_out == ["T1"]


# ------------------------------------------------------------------------------ kill -9 mid-publication
KILL_SCRIPT = textwrap.dedent("""
    import os, shutil, signal, sys
    from dualhuman_builder.workspace import Workspace

    point = sys.argv[2]
    real_rename, real_rmtree, renames = os.rename, shutil.rmtree, []

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    def rename(a, b):
        renames.append(b)
        if point == "before-switch" and len(renames) == 1:
            die()
        real_rename(a, b)
        if (point, len(renames)) in (("between-renames", 1), ("after-switch", 2)):
            die()

    def rmtree(p, *args, **kw):
        if point == "after-commit" and ".fit.old-" in str(p):
            die()
        real_rmtree(p, *args, **kw)

    os.rename, shutil.rmtree = rename, rmtree
    ws = Workspace.open(sys.argv[1])

    def compute(out):
        out.path("bodies.npz").write_text("new bodies")
        out.path("frames/new.npz").write_text("new frames")

    ws.run_stage("fit", compute, take="T1", params={"w": 2}, depends_on=[("fuse", None)])  # FIT's reads: fuse
""")


def _folder(path):
    return {str(p.relative_to(path)): p.read_text() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("point", ["before-switch", "between-renames", "after-switch", "after-commit"])
def test_killed_mid_publication_leaves_the_old_or_the_new_set_never_a_mix(ws, point):
    old = {"bodies.npz": "old bodies", "report.html": "only in the old set"}
    new = {"bodies.npz": "new bodies", "frames/new.npz": "new frames"}
    _pipeline(ws)
    ws.run_stage(FIT, _files(**old), take="T1", params={"w": 1}, depends_on=[("fuse", None)])
    ws.run_stage(CONTACTS, _files(**{"contacts.npz": "c2"}), take="T1", params={}, depends_on=[("fit", None)])
    proc = subprocess.run([sys.executable, "-c", KILL_SCRIPT, str(ws.root), point], capture_output=True, text=True)
    assert proc.returncode == -9, proc.stderr
    final = ws.root / "artifacts/T1/_take/fit"
    with Workspace.open(ws.root, readonly=True) as ro:  # what a reader sees before anything finishes it
        rec = ro.stage_record("fit", "T1")
        if rec["status"] == "done":
            assert point == "after-commit" and _folder(final) == new and ro.verify() == []
        else:
            assert rec["status"] == "interrupted" and not FIT.done(ro, "T1")
            assert _states(ro)["fit"] == "interrupted" and _states(ro)["contacts"] == "done"
            assert any("fit: its new result is being published, or was cut off" in p for p in ro.verify())
    with Workspace.open(ws.root) as rw:  # a writable open finishes the publication
        rec = rw.stage_record("fit", "T1")
        assert rec["status"] == "done" and rec["params"] == {"w": 2} and set(rec["artifacts"]) == set(new)
        assert _folder(final) == new and rw.verify() == []
        assert _states(rw)["contacts"] == "stale"
        rw.run_stage(FIT, _files(**new), take="T1", params={"w": 2}, depends_on=[("fuse", None)])  # up to date
        assert not [p for p in final.parent.iterdir() if STAGING_PREFIX in p.name or OLD_PREFIX in p.name]


# ------------------------------------------------------------------------------ catalog format
def test_a_version_2_catalog_is_migrated_with_the_reads_its_stages_declared(tmp_path):
    root = tmp_path / "ws"
    (root / "artifacts").mkdir(parents=True)
    conn = sqlite3.connect(root / "catalog.sqlite")
    conn.executescript(catalog_module.SCHEMA + catalog_module.MIGRATIONS[1] + """;
        INSERT INTO meta VALUES ('format_version', '2'), ('created_with', 'dualhuman-builder 0.1');
        INSERT INTO takes (id, name, created_at) VALUES (1, 'T1', 'now');
        INSERT INTO stage_runs (take_id, stage, params_hash, params_json, status, started_at)
            VALUES (1, 'sync', 'h1', '{}', 'done', 'now'), (1, 'sheet', 'h2', '{}', 'done', 'now');""")
    conn.close()
    with Workspace.open(root, readonly=True) as ro:  # read-only: not migrated, still readable
        assert _states(ro) == {"sync": "done", "sheet": "done"}
    with Workspace.open(root) as w:
        assert w.stage_record("sync", "T1")["reads"] == ["capture"]
        assert w.stage_record("sheet", "T1")["reads"] == ["contacts", "fit", "render"]
        assert w.conn.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone()[0] == str(catalog_module.CATALOG_VERSION)
    declared = {s.name: tuple(sorted(s.reads)) for s in STAGES if s.reads}
    assert catalog_module.V2_READS == declared  # the stages' declarations when version 3 was made
