"""Interaction labels: the vocabulary, annotations in the catalog (with the v1 -> v2 migration),
`dualhuman annotate import|export` in CSV and JSON Lines, and labels carried into the export."""

from __future__ import annotations

import csv
import io
import json
import sqlite3

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from dualhuman_builder.cli import main
from dualhuman_builder.errors import DualhumanError, WorkspaceError
from dualhuman_builder.export.annotate import (
    FIELDS,
    FORMULA_START,
    escape_cell,
    export_annotations,
    import_annotations,
    take_labels,
    unescape_cell,
)
from dualhuman_builder.labels import Annotation, Vocabulary, check_annotation, load_vocabulary
from dualhuman_builder.workspace import CATALOG_VERSION, Workspace

HEADER = "take,sequence,labels,actor,reactor,symmetric,annotator,annotated_at,text_1,text_2\n"


def _workspace(path, labels=("hug",)):
    w = Workspace.init(path)
    for name in ("alice", "bob", "carol"):
        w.add_actor(name, 1.7)
    w.add_take("T1", actors=["alice", "bob"])
    w.add_take("T2", actors=["bob", "carol"])
    w.add_sequence("T1", "S1", 0, 40, labels=labels)
    return w


@pytest.fixture
def ws(tmp_path):
    w = _workspace(tmp_path / "ws")
    yield w
    w.close()


def _write(path, text: str | bytes):
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


# ------------------------------------------------------------------------------ vocabulary
def test_builtin_vocabulary_has_chi3d_ntu_and_scene_types_with_multi_hot(tmp_path):
    v = load_vocabulary()
    chi3d = ["grab", "handshake", "hit", "holding_hands", "hug", "kick", "posing", "push"]
    assert v.names[:8] == chi3d and len(v) == 30
    assert {"high_five", "pat_on_back", "dance_turn", "rock_paper_scissors"} <= set(v.names)
    assert [n for n in chi3d if v[n].one_sided] == ["grab", "hit", "hug", "kick", "push"]  # CHI3D's one-sided types
    assert "NTU120:A55 hugging" in v["hug"].sources
    hot = v.multi_hot(["push", "hug"])
    assert hot.dtype == np.uint8 and hot.sum() == 2 and hot[v.index("push")] == hot[v.index("hug")] == 1
    assert v.symmetric(["handshake"]) is True and v.symmetric(["handshake", "push"]) is False and v.symmetric([]) is None
    with pytest.raises(ValueError, match=r"'hugg' is not in the interaction vocabulary.*did you mean 'hug'"):
        v.multi_hot(["hugg"])
    assert Vocabulary.from_dict(json.loads(json.dumps(v.as_dict()))).names == v.names
    # a project's own labels are appended; a clash or a malformed entry is an error naming the file
    _write(tmp_path / "labels.toml", '[[label]]\nname = "tango_dip"\ndescription = "a dip"\none_sided = true\n')
    ext = load_vocabulary(tmp_path)
    assert ext.names[-1] == "tango_dip" and len(ext) == 31 and ext.index("hug") == v.index("hug")
    _write(tmp_path / "labels.toml", '[[label]]\nname = "hug"\ndescription = "again"\none_sided = true\n')
    with pytest.raises(ValueError, match="'hug' is already in the vocabulary"):
        load_vocabulary(tmp_path)
    _write(tmp_path / "labels.toml", '[[label]]\nname = "Bad Name"\none_sided = true\n')
    with pytest.raises(ValueError, match="lower_snake_case"):
        load_vocabulary(tmp_path)


def test_check_annotation_fills_the_reactor_and_rejects_wrong_roles():
    v = load_vocabulary()
    a = check_annotation(Annotation("T1", None, "ann", ("push", "push"), ("x",), actor="bob"), v, ["alice", "bob"])
    assert a.labels == ("push",) and (a.actor, a.reactor, a.symmetric) == ("bob", "alice", False)
    assert check_annotation(Annotation("T1", None, "ann", ("handshake",)), v, ["alice", "bob"]).symmetric is True
    with pytest.raises(ValueError, match="actor 'zed' is not in this take"):
        check_annotation(Annotation("T1", None, "ann", ("push",), actor="zed"), v, ["alice", "bob"])
    with pytest.raises(ValueError, match="symmetric interaction has no actor"):
        check_annotation(Annotation("T1", None, "ann", ("push",), actor="bob", symmetric=True), v, ["alice", "bob"])


# ------------------------------------------------------------------------------ catalog
def test_a_version_1_catalog_is_migrated_when_opened_for_writing(tmp_path):
    path = tmp_path / "old"
    Workspace.init(path).close()
    conn = sqlite3.connect(path / "catalog.sqlite")  # make it what the previous release wrote
    conn.executescript("DROP TABLE annotations; DROP TABLE quality_flags; DROP TABLE quality_checks; UPDATE meta SET value = '1' WHERE key = 'format_version';")
    conn.close()
    with Workspace.open(path, readonly=True) as w:
        assert w.annotations() == []  # read-only: left as it is
    conn = sqlite3.connect(path / "catalog.sqlite")
    assert conn.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone() == ("1",)
    conn.close()
    with Workspace.open(path) as w:
        w.add_take("T", actors=[])
        assert w.annotate([Annotation("T", None, "ann", ("hug",), annotated_at="2026-01-01T00:00:00Z")]) == 1
        assert w.annotations()[0].labels == ("hug",)
        version = w.conn.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone()[0]
    assert int(version) == CATALOG_VERSION >= 2  # migrated to the current version, annotations included


# ------------------------------------------------------------------------------ import / export
def test_csv_import_stores_checked_records_and_reimport_replaces(ws, tmp_path):
    f = _write(tmp_path / "labels.csv", HEADER + (
        "T1,,hug;push,alice,,,ann1,2026-11-01T10:00:00Z,Alice hugs Bob,\"Then, she pushes him away.\"\n"
        "T1,S1,hug,,,true,ann1,,Two friends embrace — café scene.,\n"
        "T2,,,,,,,,,\n"))  # fmt: skip
    res = import_annotations(ws, f)
    assert (res["rows"], res["imported"], res["blank"], res["invalid"]) == (3, 2, 1, [])
    take_level, seq_level = ws.annotations("T1")
    assert take_level == Annotation("T1", None, "ann1", ("hug", "push"), ("Alice hugs Bob", "Then, she pushes him away."),
                                    "alice", "bob", False, "2026-11-01T10:00:00Z", "labels.csv")  # fmt: skip
    assert seq_level.sequence == "S1" and seq_level.symmetric is True and seq_level.actor is None
    assert seq_level.texts == ("Two friends embrace \u2014 caf\u00e9 scene.",) and seq_level.annotated_at  # import time
    # the same annotator again: replaced, not added; another annotator: added
    _write(f, HEADER + "T1,,push,bob,,,ann1,,Bob pushes Alice.,\nT1,,hug,,,,ann2,,,\n")
    import_annotations(ws, f)
    got = {(a.sequence, a.annotator): a for a in ws.annotations("T1")}
    assert set(got) == {(None, "ann1"), ("S1", "ann1"), (None, "ann2")}
    assert got[(None, "ann1")].labels == ("push",) and got[(None, "ann1")].actor == "bob"
    # what the export will carry for the take: the union, roles and flag from the latest with them
    lab = take_labels(ws, "T1", load_vocabulary())
    assert lab["labels"] == ["hug", "push"]  # in time order: the S1 annotation is older than the re-import
    assert lab["texts"] == ["Two friends embrace \u2014 caf\u00e9 scene.", "Bob pushes Alice."]
    assert lab["symmetric"] is False and lab["actor"] == "bob" and {a["annotator"] for a in lab["annotators"]} == {"ann1", "ann2"}


@pytest.mark.parametrize(
    "row, message",
    [
        ("T1,,hugg,,,,ann,,,", r"line 2: label 'hugg' is not in the interaction vocabulary.*did you mean 'hug'"),
        ("T9,,hug,,,,ann,,,", r"line 2: no take 'T9'"),
        ("T1,S9,hug,,,,ann,,,", r"line 2: take 'T1' has no sequence 'S9'"),
        ("T1,,push,carol,,,ann,,,", r"line 2: actor 'carol' is not in this take \(its actors: \['alice', 'bob'\]\)"),
        ("T1,,push,alice,,yes,ann,,,", r"line 2: a symmetric interaction has no actor"),
        ("T1,,push,,,maybe,ann,,,", r"line 2: symmetric must be true or false, got 'maybe'"),
        ("T1,,push,,,,,,,", r"line 2: no annotator"),
        ("T1,,push,,,,ann,,,,extra", r"line 2: 1 more cells than header columns"),
        ("T1,,push,,,,ann,yesterday,,", r"line 2: annotated_at must be an ISO 8601 time .*got 'yesterday'"),
        ("T1,,push,,,,ann,2026-13-01T10:00:00Z,,", r"line 2: annotated_at must be an ISO 8601 time"),
        ("T1,,push,,,,ann\x1b[2J,,,", r"line 2: annotator holds the control character '\\x1b' \(U\+001B\) at position"),
        ("T1,,push\x07,,,,ann,,,", r"line 2: labels holds the control character '\\x07'"),
        ("T1,,push,,,,ann,,a\x00b,", r"line 2: text 1 holds the control character '\\x00'"),
        ("T1,,push,,,,al\u202eice,,,", r"line 2: annotator holds the invisible or invalid character '\\u202e'"),
    ],
)  # fmt: skip
def test_an_invalid_row_imports_nothing_and_names_its_line(ws, tmp_path, row, message):
    f = _write(tmp_path / "bad.csv", HEADER + row + "\n" + "T2,,high_five,,,,ann,,,\n")
    with pytest.raises(WorkspaceError, match=message) as e:
        import_annotations(ws, f)
    assert "1 invalid row(s), nothing imported" in e.value.message and "--skip-invalid" in e.value.fix
    assert ws.annotations() == []
    res = import_annotations(ws, f, skip_invalid=True)  # the good row goes in, the bad one is listed
    assert res["imported"] == 1 and res["invalid"][0][0] == 2 and [a.take for a in ws.annotations()] == ["T2"]


def test_malformed_files_are_clear_errors(ws, tmp_path):
    bad_utf8 = _write(tmp_path / "a.csv", HEADER.encode() + b"T1,,hug,,,,ann,,caf\xe9,\n")
    with pytest.raises(WorkspaceError, match=r"not valid UTF-8 at byte \d+ \(line 2"):
        import_annotations(ws, bad_utf8)
    with pytest.raises(WorkspaceError, match=r"unknown CSV columns \['lables'\]"):
        import_annotations(ws, _write(tmp_path / "b.csv", "take,lables\nT1,hug\n"))
    with pytest.raises(WorkspaceError, match="use a .csv or .jsonl file name"):
        import_annotations(ws, _write(tmp_path / "c.xlsx", "x"))
    lines = '{"take": "T1", "labels": ["hug"], "annotator": "a"}\n{"take": "T1", "annotator": "b", "label": ["hug"]}\n[1]\n{oops\n'
    with pytest.raises(WorkspaceError, match=r"3 invalid row\(s\).*line 2: unknown keys \['label'\].*line 3: each line must be "
                                             r"a JSON object.*line 4: not JSON"):  # fmt: skip
        import_annotations(ws, _write(tmp_path / "d.jsonl", lines))
    dup = HEADER + "T1,,hug,,,,ann,,,\nT1,,push,,,,ann,,,\n"
    with pytest.raises(WorkspaceError, match="line 3: repeats line 2"):
        import_annotations(ws, _write(tmp_path / "e.csv", dup))


@pytest.mark.parametrize("fmt", ["csv", "jsonl"])
def test_export_then_import_round_trips_and_lists_blank_rows(ws, tmp_path, fmt):
    import_annotations(ws, _write(tmp_path / "in.csv", HEADER + (
        "T1,,push,bob,,,ann1,2026-11-01T10:00:00Z,Bob pushes Alice,\"He says \"\"sorry\"\"; then leaves\"\n"
        "T1,S1,handshake,,,,ann2,2026-11-02T10:00:00Z,,\n")))  # fmt: skip
    out = tmp_path / f"out.{fmt}"
    text, n = export_annotations(ws, out)
    assert n == 3 and out.read_text(encoding="utf-8") == text  # two stored + the blank row for take T2
    if fmt == "csv":
        assert text.splitlines()[0] == HEADER.strip().replace(",text_2", ",text_2,text_3")
        assert text.splitlines()[-1] == "T2,,,,,,,,,,"
    other = Workspace.init(tmp_path / "other")
    for name in ("alice", "bob", "carol"):
        other.add_actor(name, 1.7)
    other.add_take("T1", actors=["alice", "bob"])
    other.add_take("T2", actors=["bob", "carol"])
    other.add_sequence("T1", "S1", 0, 40)
    res = import_annotations(other, out)
    assert (res["imported"], res["blank"]) == (2, 1)
    strip = [a.__dict__ | {"source": None} for a in ws.annotations()]
    assert [a.__dict__ | {"source": None} for a in other.annotations()] == strip
    assert other.annotations()[0].texts == ("Bob pushes Alice", 'He says "sorry"; then leaves')
    other.close()


# ------------------------------------------------------------------------------ odd and hostile files
def test_a_cell_over_128_kib_is_one_invalid_row(ws, tmp_path):
    f = _write(tmp_path / "big.csv", HEADER + "T1,,hug,,,,ann,,\"" + "x" * 200_000 + "\",\nT2,,high_five,,,,ann,,,\n")
    with pytest.raises(WorkspaceError, match=r"nothing imported: line 2: text 1 is 200000 characters long, more than"):
        import_annotations(ws, f)
    res = import_annotations(ws, f, skip_invalid=True)
    assert (res["imported"], [n for n, _ in res["invalid"]]) == (1, [2])
    assert [a.take for a in ws.annotations()] == ["T2"]
    assert csv.field_size_limit() == 131072  # the csv module's limit is left as it was


def test_an_endless_file_is_refused_after_its_cap(ws, tmp_path):
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    with pytest.raises(WorkspaceError, match="more than 64 MiB"):
        import_annotations(ws, tmp_path / "zero.csv")


def test_deeply_nested_or_huge_json_lines_are_invalid_rows(ws, tmp_path):
    lines = ['{"take": "T2", "labels": ["high_five"], "annotator": "a"}',
             '{"take": ' + "[" * 100_000 + "]" * 100_000 + "}",
             '{"take": "T1", "symmetric": ' + "1" * 5000 + ', "annotator": "a"}',
             '{"take": "T1", "texts": [[[["x"]]]], "annotator": "a"}',
             '{"take": "T1", "labels": "hug", "annotator": "a\\ud800"}']
    f = _write(tmp_path / "deep.jsonl", "\n".join(lines) + "\n")
    with pytest.raises(WorkspaceError, match=r"4 invalid row\(s\).*line 2: not JSON this reader takes \(nested too "
                       r"deeply\).*line 3: not JSON this reader takes.*line 4: text 1 must be text, got a list.*"
                       r"line 5: annotator holds the invisible or invalid character '\\ud800'"):  # fmt: skip
        import_annotations(ws, f)
    res = import_annotations(ws, f, skip_invalid=True)
    assert res["imported"] == 1 and [n for n, _ in res["invalid"]] == [2, 3, 4, 5]


def test_formula_cells_are_escaped_in_csv_and_restored_on_import(ws, tmp_path):
    texts = ('=HYPERLINK("http://evil.example","click")', "+1 and more", "-2 degrees", "@SUM(A1:A2)",
             "'=quoted already", "'tis plain", "a = b", "two\nlines")
    ws.annotate([Annotation("T1", None, "=cmd|' /C calc'!A0", ("hug",), texts, annotated_at="2026-11-01T10:00:00Z")])
    text, _ = export_annotations(ws, tmp_path / "out.csv", blank=False)
    cells = [c for row in csv.reader(io.StringIO(text)) for c in row]
    assert not [c for c in cells if c and c[0] in FORMULA_START]  # no spreadsheet reads a formula
    assert {"'=HYPERLINK(\"http://evil.example\",\"click\")", "'+1 and more", "''=quoted already"} <= set(cells)
    assert "'tis plain" in cells
    assert "'=cmd|' /C calc'!A0" in cells
    other = _workspace(tmp_path / "other", labels=())
    import_annotations(other, tmp_path / "out.csv")
    (back,) = other.annotations()
    assert back.texts == texts and back.annotator == "=cmd|' /C calc'!A0"
    other.close()


@given(st.text(max_size=12))
def test_escaping_a_cell_is_undone_exactly(text):
    cell = escape_cell(text)
    assert unescape_cell(cell) == text and not (cell and cell[0] in FORMULA_START)


def test_cli_prints_the_file_s_text_as_text_not_markup(ws, tmp_path):
    f = _write(tmp_path / "a.csv", HEADER + "T1,,[/x];[bold]hug,,,,ann,,,\nT2,,high_five,,,,ann,,,\n")
    r = CliRunner().invoke(main, ["annotate", "import", str(ws.root), str(f), "--skip-invalid"])
    assert r.exit_code == 0, r.output
    assert "label '[/x]' is not in the interaction vocabulary" in r.output and "1 annotation(s) imported" in r.output


_CELL = st.text(max_size=8) | st.sampled_from(["T1", "T2", "S1", "S9", "hug", "push;hug", "alice", "bob", "carol", "ann",
                                                "true", "maybe", "", "2026-11-01T10:00:00Z", "noon", "=1+1", "'-x", '"',
                                                "\n", "\x1b", "\u202e", "\ud800", "x" * 140_000])  # fmt: skip
_JSON_VALUE = st.recursive(st.none() | st.booleans() | st.integers() | _CELL, lambda k: st.lists(k, max_size=3),
                           max_leaves=5)  # fmt: skip


@given(data=st.data(), skip=st.booleans())
def test_any_annotation_file_gives_a_clear_error_or_counted_rows(ws, tmp_path, data, skip):
    fmt = data.draw(st.sampled_from(["csv", "jsonl"]))
    if fmt == "csv":
        rows = data.draw(st.lists(st.lists(_CELL, max_size=11), max_size=4))
        buf = io.StringIO()
        csv.writer(buf).writerows(rows)
        body = data.draw(st.sampled_from([HEADER, "take,labels\n", ""])) + buf.getvalue()
    else:
        keys = st.sampled_from([*FIELDS, "texts", "label"])
        objs = data.draw(st.lists(st.dictionaries(keys, _JSON_VALUE, max_size=6) | _JSON_VALUE, max_size=4))
        body = "".join(json.dumps(o) + "\n" for o in objs)
        body += data.draw(st.sampled_from(["", "[" * 3000 + "]" * 3000 + "\n", '{"take": ' + "1" * 5000 + "}\n"]))
    raw = body.encode("utf-8", "surrogatepass") + data.draw(st.sampled_from([b"", b"\xff\n", b"{[\n", b'"a,\n']))
    f = tmp_path / f"in.{fmt}"
    f.write_bytes(raw)
    try:
        res = import_annotations(ws, f, skip_invalid=skip)
    except DualhumanError as e:
        assert e.message
        return
    assert res["rows"] == res["imported"] + res["blank"] + len(res["invalid"])  # every row accounted for
    assert skip or not res["invalid"]


# ------------------------------------------------------------------------------ into the export
def test_annotations_reach_the_export_as_multi_hot_roles_and_flag(ws, tmp_path, body_model):
    from dualhuman_builder.export.collect import run_export
    from dualhuman_builder.export.verify import verify_export
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    def fit(out):  # a fitted pair, as the fit stage leaves it
        T, J, P = 12, body_model.num_bones, len(body_model.shape_names)
        tracks = []
        for k, actor in enumerate(("alice", "bob")):
            pose = np.zeros((T, J, 3))
            pose[:, 0, 1] = np.pi * k
            transl = np.stack([np.full(T, 0.8 * k), np.full(T, 0.95), np.linspace(0, 0.2, T)], axis=1)
            tracks.append(BodyTrack.from_model(body_model, pose, transl, np.full(P, 0.5), 15.0, actor=actor))
        InteractionSequence(tuple(tracks), take="T1").save(out.path("bodies.npz"))
        return {}

    ws.run_stage("fit", fit, take="T1")
    import_annotations(ws, _write(tmp_path / "in.jsonl", json.dumps(
        {"take": "T1", "labels": "push", "actor": "bob", "annotator": "ann", "texts": ["Bob pushes Alice."]}) + "\n"))
    out = tmp_path / "export"
    manifest = run_export(ws, out, log=lambda _m: None)
    assert manifest["left_out"] == ["T2"] and manifest["vocabulary"]["size"] == 30
    text = json.loads((out / "sequences/T1/text.json").read_text(encoding="utf-8"))
    vocab = Vocabulary.from_dict(json.loads((out / "labels.json").read_text()))
    assert text["labels"] == ["hug", "push"]  # the sequence's own label, then the annotation's
    assert text["multi_hot"] == vocab.multi_hot(["hug", "push"]).tolist()
    assert text["roles"] == ["reactor", "actor"] and text["symmetric"] is False  # bob is person b and acts
    assert text["texts"] == ["Bob pushes Alice."] and text["annotations"][0]["annotator"] == "ann"
    assert verify_export(out) == []
    # the verifier notices a multi-hot vector that does not match its labels
    text["multi_hot"] = vocab.multi_hot(["hug"]).tolist()
    (out / "sequences/T1/text.json").write_text(json.dumps(text))
    assert "sequences/T1/text.json: multi_hot disagrees with its labels" in verify_export(out)
    # a label the vocabulary lost since it was imported (WS/labels.toml edited) stops the export, named
    ws.add_sequence("T1", "S2", 0, 5, labels=("tango_dip",))
    with pytest.raises(WorkspaceError, match="take 'T1': label 'tango_dip' is not in the interaction vocabulary"):
        run_export(ws, tmp_path / "export2", log=lambda _m: None)


def test_cli_annotate_vocabulary_export_import(ws, tmp_path):
    runner = CliRunner()
    r = runner.invoke(main, ["annotate", "vocabulary", "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["size"] == 30
    r = runner.invoke(main, ["annotate", "export", str(ws.root), str(tmp_path / "a.csv")])
    assert r.exit_code == 0 and "3 row(s) written" in r.output
    rows = (tmp_path / "a.csv").read_text().splitlines()
    assert rows[1:] == ["T1,,,,,,,,,,", "T1,S1,,,,,,,,,", "T2,,,,,,,,,,"]
    rows[1] = "T1,,hug,alice,,,,,Alice hugs Bob.,,"
    (tmp_path / "a.csv").write_text("\n".join(rows) + "\n")
    r = runner.invoke(main, ["annotate", "import", str(ws.root), str(tmp_path / "a.csv"), "--annotator", "zoe"])
    assert r.exit_code == 0, r.output
    assert "1 annotation(s) imported" in r.output and "2 blank" in r.output
    r = runner.invoke(main, ["annotate", "export", str(ws.root), "--no-blank"])
    rec = json.loads(r.output)
    assert (rec["annotator"], rec["labels"], rec["actor"], rec["reactor"]) == ("zoe", ["hug"], "alice", "bob")
    r = runner.invoke(main, ["annotate", "import", str(ws.root), str(tmp_path / "a.csv")])  # no annotator anywhere
    assert r.exit_code == 2 and "no annotator" in r.output
