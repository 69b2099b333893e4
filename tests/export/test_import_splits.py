"""An import keeps the source's split (``splits=`` of the export writer) and runs without the body model
(a joints-only import never imports anny)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from synthetic_pairs import face_to_face, write_export

from dualhuman_builder.cli.app import main
from dualhuman_builder.export.convert import to_humanml3d, to_interhuman
from dualhuman_builder.export.importers import (
    JointsTrack,
    import_humanml3d,
    import_interhuman,
)
from dualhuman_builder.export.items import ExportItem
from dualhuman_builder.export.verify import verify_export
from dualhuman_builder.export.writer import export_dataset
from dualhuman_builder.tracks import InteractionSequence

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """Four sequences, three of them in the export's train split, converted to both layouts."""
    tmp = tmp_path_factory.mktemp("splits")
    seqs = {f"s{k}": (*face_to_face(T=30, seed=k), "test" if k == 2 else "train") for k in range(4)}
    export = write_export(tmp / "ds", seqs)
    to_humanml3d(export, tmp / "hml")
    to_interhuman(export, tmp / "ih")
    return tmp


def _split(manifest: dict) -> dict[str, str]:
    return {sid: info["split"] for sid, info in manifest["sequences"].items()}


@pytest.mark.parametrize("layout, importer", [("hml", import_humanml3d), ("ih", import_interhuman)])
def test_import_keeps_the_source_split(converted, tmp_path, layout, importer):
    res = importer(converted / layout, tmp_path / "out", split_ratio=0.5, seed=3)
    assert _split(res["manifest"]) == {"s0": "train", "s1": "train", "s2": "test", "s3": "train"}
    assert res["split_from_source"] == 4 and res["manifest"]["split"]["given"] == 4 and not res["notes"]
    assert not verify_export(tmp_path / "out")
    drawn = importer(converted / layout, tmp_path / "drawn", split_ratio=0.5, seed=3, keep_split=False)
    assert drawn["split_from_source"] == 0
    assert sorted(_split(drawn["manifest"]).values()) == ["test", "test", "train", "train"]


def test_val_is_held_out_and_unlisted_sequences_are_drawn(converted, tmp_path):
    src = tmp_path / "ih"
    subprocess.run(["cp", "-r", str(converted / "ih"), str(src)], check=True)
    (src / "train.txt").write_text("s0\n")
    (src / "val.txt").write_text("s1\n")
    (src / "test.txt").write_text("")
    res = import_interhuman(src, tmp_path / "out", split_ratio=0.5, seed=0)
    split = _split(res["manifest"])
    assert split["s0"] == "train" and split["s1"] == "test" and res["split_from_source"] == 2
    assert {split["s2"], split["s3"]} == {"train", "test"}  # drawn: half of the two unplaced ones


def test_lists_without_train_fall_back_to_a_drawn_split(converted, tmp_path):
    src = tmp_path / "ih"
    subprocess.run(["cp", "-r", str(converted / "ih"), str(src)], check=True)
    (src / "train.txt").write_text("")
    (src / "test.txt").write_text("s0\ns1\ns2\ns3\n")
    (src / "val.txt").write_text("")
    res = import_interhuman(src, tmp_path / "out")
    assert res["split_from_source"] == 0 and "no imported sequence in train" in res["notes"][0]
    assert "train" in _split(res["manifest"]).values()
    r = CliRunner().invoke(main, ["export", "import-interhuman", str(src), str(tmp_path / "cli")])
    assert r.exit_code == 0 and "note:" in r.output and "0 split as the source lists them" in r.output


def test_writer_refuses_splits_it_cannot_use(tmp_path):
    a, b = face_to_face(T=12)
    seq = InteractionSequence((JointsTrack.from_joints(a, 10.0), JointsTrack.from_joints(b, 10.0)), take="t")
    items = [ExportItem("x", seq, subjects=("", "")), ExportItem("y", seq, subjects=("", ""))]
    with pytest.raises(ValueError, match="not exported"):
        export_dataset(items, tmp_path / "o", expect=("motion",), splits={"z": "train"})
    with pytest.raises(ValueError, match="'train' or 'test'"):
        export_dataset(items, tmp_path / "o", expect=("motion",), splits={"x": "val"})
    with pytest.raises(ValueError, match="train split is empty"):
        export_dataset(items, tmp_path / "o", expect=("motion",), splits={"x": "test", "y": "test"})
    m = export_dataset(items, tmp_path / "o", expect=("motion",), splits={"x": "test", "y": "train"})
    assert _split(m) == {"x": "test", "y": "train"} and m["body_model"]["num_vertices"] == 0


def test_import_does_not_load_the_body_model(converted, tmp_path):
    code = ("import sys; from dualhuman_builder.export.importers import import_interhuman, import_humanml3d; "
            f"import_interhuman({str(converted / 'ih')!r}, {str(tmp_path / 'a')!r}); "
            f"import_humanml3d({str(converted / 'hml')!r}, {str(tmp_path / 'b')!r}); "
            "print(sorted(m for m in sys.modules if m == 'anny' or m.startswith('anny.')))")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"
    assert not verify_export(tmp_path / "a") and not verify_export(tmp_path / "b")
