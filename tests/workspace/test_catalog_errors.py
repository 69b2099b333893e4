"""The catalog on a full disk or a failing device: real SQLite errors, told apart from a damaged
file, with safe advice; and a recorded take file registered afterwards (`dualhuman import WS T.mcap`)."""

import json
import os
import resource
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dualhuman_builder.capture.log.writer import TakeWriter
from dualhuman_builder.capture.samples import TrackerSample
from dualhuman_builder.capture.sources import RawPacket
from dualhuman_builder.capture.stage import register_take_file
from dualhuman_builder.errors import FormatError, WorkspaceError
from dualhuman_builder.workspace import CATALOG_NAME, Workspace
from dualhuman_builder.workspace.catalog import CatalogError

REPO = Path(__file__).resolve().parents[2]
REINIT = ("dualhuman init", "move it aside and")


def _cli(*args):
    from dualhuman_builder import cli

    return CliRunner().invoke(cli.main, [str(a) for a in args])


def test_a_full_catalog_says_so_and_stays_intact(ws):
    ws.add_take("T0")
    ws.conn.execute(f"PRAGMA max_page_count = {ws.conn.execute('PRAGMA page_count').fetchone()[0]}")  # SQLite: full
    with pytest.raises(CatalogError) as e:
        for i in range(200):
            ws.add_take(f"T{i + 1}", meta={"notes": "x" * 3000})
    assert "database or disk is full (SQLITE_FULL)" in e.value.message and e.value.code == sqlite3.SQLITE_FULL
    assert "catalog is intact" in e.value.fix and not any(w in e.value.fix for w in REINIT)
    takes = ws.takes()
    ws.close()
    with Workspace.open(ws.root) as again:  # every complete transaction is there, the failed one is not
        assert again.takes() == takes and again.conn.execute("PRAGMA quick_check").fetchone()[0] == "ok"


IOERR_SCRIPT = textwrap.dedent("""
    import json, resource, sys
    limit = int(sys.argv[2])
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))  # writes past it fail with EFBIG, as on a full disk
    from dualhuman_builder.workspace import Workspace
    try:
        Workspace.open(sys.argv[1]).add_actor("alice", 1.7)
        print(json.dumps(None))
    except Exception as e:
        print(json.dumps([type(e).__name__, e.message, e.fix, getattr(e, "code", None)]))
""")


def test_a_disk_io_error_names_the_real_reason_and_never_advises_a_new_catalog(tmp_path):
    root = tmp_path / "ws"
    Workspace.init(root).close()
    before = (root / CATALOG_NAME).read_bytes()
    proc = subprocess.run([sys.executable, "-c", IOERR_SCRIPT, str(root), "8000"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    kind, message, fix, code = json.loads(proc.stdout)
    assert kind == "CatalogError" and code & 0xFF == sqlite3.SQLITE_IOERR
    assert "disk I/O error (SQLITE_IOERR" in message and "File too large (EFBIG)" in message  # what the OS says
    assert "free space" in fix and "catalog is intact" in fix and not any(w in fix for w in REINIT)
    assert (root / CATALOG_NAME).read_bytes() == before
    with Workspace.open(root) as w:  # and it opens once there is room again
        assert w.takes() == []


def test_a_damaged_catalog_still_gets_the_restore_advice(tmp_path):
    root = tmp_path / "ws"
    with Workspace.init(root) as w:
        for i in range(200):
            w.add_actor(f"actor{i}", 1.7)
    cat = root / CATALOG_NAME
    data = bytearray(cat.read_bytes())
    data[5000:9000] = b"\xff" * 4000
    cat.write_bytes(bytes(data))
    with pytest.raises(WorkspaceError, match="damaged|integrity") as e:
        Workspace.open(root)
    assert "backup" in e.value.fix


# ------------------------------------------------------------------------------ registering a take file
def _take_file(path: Path, take: str = "T7", samples: int = 20, finish: bool = True):
    """A take file of ``samples`` tracker samples; unfinished (flushed, no index yet): its writer."""
    w = TakeWriter(path, take=take, sources=[("trackers", "vive+udp://127.0.0.1:8051", "vive")],
                   bindings={"*": {"vive/LHR-1": {"actor": "alice", "segment": "Head"},
                                   "vive/LHR-2": {"actor": "carol", "segment": "Head"}}})  # fmt: skip
    for k in range(samples):
        t = 1_000_000_000 + k * 10_000_000
        w.add_raw(0, RawPacket(t, bytes([k % 256]) * 8))
        w.add_sample(0, TrackerSample("LHR-1", True, t, t + 1000, np.zeros(3), np.array([0, 0, 0, 1.0]), np.zeros(3),
                                      np.zeros(3)))  # fmt: skip
    if finish:
        w.close()
        return path
    w.flush()
    return w


def test_a_recorded_take_file_is_registered_in_place_or_copied(ws, tmp_path):
    ws.add_actor("alice", 1.7)
    inside = _take_file(ws.root / "takes" / "T7" / "T7.mcap")
    t = register_take_file(ws, inside, log=lambda m: None)
    assert t.name == "T7" and t.actors == ("alice",) and t.meta["unregistered_actors"] == ["carol"]
    assert [f["path"] for f in t.files] == ["takes/T7/T7.mcap"] and t.sample_counts == {"trackers/vive/LHR-1/TrackerSample": 20}
    assert ws.verify_take_files("T7") == [] and [p.name for p in inside.parent.iterdir()] == ["T7.mcap"]
    elsewhere = _take_file(tmp_path / "recorded.mcap", take="T7")
    with pytest.raises(WorkspaceError, match="take 'T7' already exists"):
        register_take_file(ws, elsewhere, log=lambda m: None)
    t2 = register_take_file(ws, elsewhere, take="T8", log=lambda m: None)
    assert [f["path"] for f in t2.files] == ["takes/T8/recorded.mcap"] and elsewhere.is_file()


def test_a_cut_off_or_foreign_file_is_refused_and_nothing_is_written(ws, tmp_path):
    cut = tmp_path / "cut.mcap"
    w = _take_file(cut, samples=400, finish=False)
    with pytest.raises(FormatError, match="cut off") as e:
        register_take_file(ws, cut, log=lambda m: None)
    assert f"dualhuman log repair {cut}" in e.value.fix
    w.close()
    other = tmp_path / "notes.mcap"
    other.write_bytes(b"not a take" * 20)
    with pytest.raises(FormatError, match="not an MCAP file"):
        register_take_file(ws, other, log=lambda m: None)
    assert ws.takes() == [] and list((ws.root / "takes").iterdir()) == []


def test_import_registers_a_take_file_from_the_command_line(tmp_path):
    root = tmp_path / "ws"
    Workspace.init(root).close()
    f = _take_file(tmp_path / "T7.mcap")
    r = _cli("import", root, f, "--actor", "alice")
    assert r.exit_code == 2 and "--actor, --scale and --z-up apply to .mvnx and .bvh" in r.output
    r = _cli("import", root, f, "--take", "T9")
    assert r.exit_code == 0, r.output
    assert "registered T7.mcap as take 'T9': 20 samples on 1 topics" in r.output
    assert "actors not in the workspace: alice, carol" in r.output
    with Workspace.open(root, readonly=True) as w:
        assert w.takes() == ["T9"] and w.verify_take_files("T9") == []


@pytest.mark.slow
def test_a_capture_whose_registration_fails_keeps_the_take_and_says_how_to_register_it(tmp_path):
    """The catalog cannot grow (RLIMIT_FSIZE in the capture's process; a reader here keeps the WAL
    from being reset) while the take itself still fits: the capture exits 1 with SQLite's and the
    system's reasons and the command that registers the kept file, which then works."""
    root = tmp_path / "ws"
    Workspace.init(root).close()
    conn = sqlite3.connect(root / CATALOG_NAME, isolation_level=None)
    conn.execute("PRAGMA wal_autocheckpoint = 0")
    for i in range(40):
        conn.execute("INSERT INTO rigs (name, sha256, content, created_at) VALUES (?, '', ?, 'now')", (f"r{i}", "x" * 3000))
    conn.execute("BEGIN")
    conn.execute("SELECT count(*) FROM rigs").fetchone()
    limit = 200_000
    assert os.path.getsize(f"{root / CATALOG_NAME}-wal") > limit

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.run([sys.executable, "-c", "from dualhuman_builder.cli import main; main()", "capture", "--source",
                           "mvn+udp://127.0.0.1:0", "--duration", "0.3", "-w", str(root), "--take", "T1", "--quiet"],
                          capture_output=True, text=True, preexec_fn=small_files)  # fmt: skip
    conn.execute("COMMIT")
    conn.close()
    take = root / "takes" / "T1" / "T1.mcap"
    err = " ".join(proc.stderr.split())
    assert proc.returncode == 1, proc.stderr
    assert "could not be registered" in err and "SQLITE_IOERR" in err and "File too large (EFBIG)" in err
    assert f"register the recording with `dualhuman import {root} {take}`" in err and "dualhuman init" not in err
    r = _cli("capture", "--source", "mvn+udp://127.0.0.1:0", "--duration", "0.1", "-w", root, "--take", "T1")
    assert r.exit_code == 2 and "recorded to" in r.output and "dualhuman import" in r.output  # not recorded over
    r = _cli("import", root, take)
    assert r.exit_code == 0, r.output
    with Workspace.open(root, readonly=True) as w:
        assert w.takes() == ["T1"] and w.take("T1").files[0]["path"] == "takes/T1/T1.mcap"
