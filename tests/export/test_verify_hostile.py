"""`export verify` on damaged and hostile exports: zip bombs, paths out of the export, symbolic links,
FIFOs, extra files and malformed manifest or schema entries give clear problems, never a crash, a
hang or unbounded memory. Every hostile export is built from one real small export."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import struct
import tracemalloc
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dualhuman_builder.export.files import read_npz
from dualhuman_builder.export.items import ExportItem
from dualhuman_builder.export.verify import verify_export
from dualhuman_builder.export.writer import export_dataset
from dualhuman_builder.tracks import BodyTrack, InteractionSequence

T = 8


def _track(model, seed: int, x: float, actor: str) -> BodyTrack:
    rng = np.random.default_rng(seed)
    pose = np.cumsum(rng.normal(0.0, 0.01, (T, model.num_bones, 3)), axis=0)
    transl = np.stack([np.full(T, x), np.full(T, 0.95), np.linspace(0.0, 0.1, T)], axis=1)
    return BodyTrack.from_model(model, pose, transl, rng.uniform(0.3, 0.7, len(model.shape_names)), 20.0, actor=actor)


@pytest.fixture(scope="module")
def export(body_model, tmp_path_factory):
    """A real export of two short sequences, one with contacts."""
    V = body_model.num_vertices
    labels = np.zeros((2, T, V), bool)
    labels[:, 2:5, :40] = True
    dist = np.full((2, T, V), np.nan, np.float16)
    dist[labels] = -0.002
    contacts = {"labels": labels, "distances": dist, "frame_contact": labels.any(axis=(0, 2)), "events": []}
    items = []
    for k, sid in enumerate(("s0", "s1")):
        a, b = _track(body_model, 2 * k, 0.0, f"p{2 * k}"), _track(body_model, 2 * k + 1, 0.9, f"p{2 * k + 1}")
        seq = InteractionSequence((a, b), take=f"take{k}", labels=("push",), text=("One pushes the other.",))
        items.append(ExportItem(sid, seq, contacts=contacts if k == 0 else None))
    out = tmp_path_factory.mktemp("export") / "ds"
    export_dataset(items, out, split_ratio=0.5, seed=0)
    assert verify_export(out) == []
    return out


@pytest.fixture
def ds(export, tmp_path):
    """A fresh copy of the export to damage."""
    dst = tmp_path / "ds"
    shutil.copytree(export, dst)
    return dst


def _manifest(ds) -> dict:
    return json.loads((ds / "manifest.json").read_text())


def _write_manifest(ds, manifest: dict) -> None:
    (ds / "manifest.json").write_text(json.dumps(manifest))


def _relist(ds, manifest: dict, rel: str) -> None:
    """Record ``rel``'s present bytes in ``manifest``: what a forger who rewrites the manifest does."""
    data = (ds / rel).read_bytes()
    manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}


def _text(problems: list[str]) -> str:
    assert isinstance(problems, list) and all(isinstance(p, str) for p in problems)
    return "\n".join(problems)


def _peak(fn):
    """``(result, peak bytes allocated)`` of ``fn()``, numpy's buffers included (numpy reports them to tracemalloc)."""
    tracemalloc.start()
    try:
        return fn(), tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _bomb(n_floats: int, header_shape=None) -> bytes:
    """An .npz whose one member ``a.pose`` inflates to ``n_floats`` float32 zeros (~1000:1 compressed)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False,
                                               "shape": header_shape or (n_floats,)})  # fmt: skip
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("a.pose.npy", "w", force_zip64=True) as f:
            f.write(buf.getvalue())
            zeros = bytes(1 << 20)
            for _ in range(n_floats * 4 // len(zeros)):
                f.write(zeros)
            f.write(bytes(n_floats * 4 % len(zeros)))
    return out.getvalue()


# ------------------------------------------------------------------------------------ decompression
def test_a_file_whose_checksum_failed_is_never_decompressed(ds):
    (ds / "sequences/s0/motion.npz").write_bytes(_bomb(16 << 20))  # 64 MiB of zeros in ~64 KiB, manifest untouched
    problems, peak = _peak(lambda: verify_export(ds))
    assert "sequences/s0/motion.npz: " in _text(problems) and "manifest says" in _text(problems)
    assert peak < 16 << 20


def test_a_forged_member_is_refused_before_decompressing(ds):
    manifest = _manifest(ds)
    # the forger rewrote the manifest too: the member's header claims 64 MiB, not the schema's (T, J, 3)
    (ds / "sequences/s0/motion.npz").write_bytes(_bomb(16 << 20))
    _relist(ds, manifest, "sequences/s0/motion.npz")
    _write_manifest(ds, manifest)
    problems, peak = _peak(lambda: verify_export(ds))
    assert "sequences/s0/motion.npz: a.pose has shape (16777216,), schema says ['T', 'J', 3]" in _text(problems)
    assert peak < 16 << 20
    # a size record that disagrees with the member's header, and one that deflate cannot reach from the bytes present
    pose = read_npz(ds / "sequences/s1/motion.npz")["a.pose"]
    cases = ((pose.shape, "its header claims"), ((T * 2000, *pose.shape[1:]), "more than deflate can expand"))
    for claim, message in cases:
        head = io.BytesIO()
        np.lib.format.write_array_header_1_0(head, {"descr": "<f4", "fortran_order": False, "shape": claim})
        z = io.BytesIO()
        with zipfile.ZipFile(z, "w", zipfile.ZIP_DEFLATED) as zf:
            zf.writestr("a.pose.npy", head.getvalue() + pose.tobytes())
        data = bytearray(z.getvalue())
        cd = data.rindex(b"PK\x01\x02")  # the central directory's record of the uncompressed size, at +24
        claimed = len(head.getvalue()) + 4 * int(np.prod(claim)) + (1000 if claim == pose.shape else 0)
        struct.pack_into("<I", data, cd + 24, claimed)
        (ds / "sequences/s1/motion.npz").write_bytes(bytes(data))
        _relist(ds, manifest, "sequences/s1/motion.npz")
        _write_manifest(ds, manifest)
        problems, peak = _peak(lambda: verify_export(ds))
        assert "sequences/s1/motion.npz: array a.pose: " in _text(problems) and message in _text(problems)
        assert peak < 16 << 20


def test_decompression_stays_within_the_claimed_size_and_the_budget(ds):
    manifest = _manifest(ds)
    frames = 8192  # the manifest claims a long sequence, the member agrees: about 16 MB, over a budget of 8 MiB
    manifest["sequences"]["s0"]["frames"] = frames
    J = read_npz(ds / "sequences/s0/motion.npz")["a.pose"].shape[1]
    (ds / "sequences/s0/motion.npz").write_bytes(_bomb(frames * J * 3, header_shape=(frames, J, 3)))
    _relist(ds, manifest, "sequences/s0/motion.npz")
    _write_manifest(ds, manifest)
    problems, peak = _peak(lambda: verify_export(ds, max_array_bytes=8 << 20))
    assert "sequences/s0/motion.npz: array a.pose: " in _text(problems)
    assert "more than verify decompresses" in _text(problems)
    assert peak < 16 << 20


# ------------------------------------------------------------------------------------ paths
def test_paths_in_the_manifest_stay_inside_the_export(ds, tmp_path):
    (tmp_path / "outside.txt").write_text("secret-outside\n")
    manifest = _manifest(ds)
    manifest["split"]["files"] = {"train": "/etc/passwd", "test": "../outside.txt", "val": "/dev/zero"}
    manifest["stats"] = {"mean": "/dev/zero", "std": "../outside.txt"}
    manifest["vocabulary"]["file"] = "/etc/hostname"
    _write_manifest(ds, manifest)
    passwd = []
    if os.path.isfile("/etc/passwd"):
        with open("/etc/passwd") as f:
            passwd = [line for line in f.read().splitlines() if line.strip()]
    text = _text(verify_export(ds))
    assert not any(line in text for line in passwd) and "secret-outside" not in text
    assert "/etc/passwd: named by the manifest's split.files but not in its file list" in text
    assert "../outside.txt: named by the manifest's stats but not in its file list" in text
    # listed, too: still refused, and nothing outside is read
    manifest["files"]["../outside.txt"] = manifest["files"]["/etc/passwd"] = {"sha256": "0" * 64, "bytes": 15}
    _write_manifest(ds, manifest)
    text = _text(verify_export(ds))
    assert "../outside.txt: not a relative path inside the folder" in text
    assert "/etc/passwd: not a relative path inside the folder" in text
    assert not any(line in text for line in passwd) and "secret-outside" not in text


def test_a_listed_symlink_to_an_identical_file_outside_fails(ds, tmp_path):
    copy = tmp_path / "motion.npz"
    shutil.copyfile(ds / "sequences/s0/motion.npz", copy)
    (ds / "sequences/s0/motion.npz").unlink()
    (ds / "sequences/s0/motion.npz").symlink_to(copy)
    assert "sequences/s0/motion.npz: leads out of the folder" in _text(verify_export(ds))
    # a whole own folder linked out of the export
    shutil.move(ds / "stats", tmp_path / "stats")
    (ds / "stats").symlink_to(tmp_path / "stats")
    text = _text(verify_export(ds))
    assert "stats: a symbolic link (the manifest does not list it)" in text and "stats/mean.npy: leads out" in text


def test_extra_files_at_the_top_level_fail(ds):
    (ds / "notes.txt").write_text("mine")
    (ds / "extra").mkdir()
    assert _text(verify_export(ds)).splitlines() == [
        "extra: not part of the export (the manifest does not list it); move it out of the export folder",
        "notes.txt: not part of the export (the manifest does not list it); move it out of the export folder",
    ]


def test_fifos_and_symlink_loops_do_not_hang(ds):
    os.unlink(ds / "splits/test.txt")
    os.mkfifo(ds / "splits/test.txt")
    (ds / "sequences/s1/loop").symlink_to(ds / "sequences/s1/loop")
    text = _text(verify_export(ds))
    assert "splits/test.txt: not a regular file" in text and "sequences/s1/loop: not listed in the manifest" in text
    os.unlink(ds / "manifest.json")
    os.mkfifo(ds / "manifest.json")
    assert "manifest.json: not a regular file" in _text(verify_export(ds))


# ------------------------------------------------------------------------------------ malformed entries
MANIFEST_CASES = [
    (lambda m: m.update(vocabulary="labels.json"), "manifest.json: 'vocabulary' must be an object"),
    (lambda m: m.update(split=[]), "manifest.json: 'split' must be an object"),
    (lambda m: m.update(stats=5), "manifest.json: 'stats' must be an object"),
    (lambda m: m.update(counts="many"), "manifest.json: 'counts' must be an object"),
    (lambda m: m.update(fps="fast"), "manifest.json: 'fps' must be a number"),
    (lambda m: m["files"].update({"README.md": "abc"}), "manifest.json: files[README.md] needs 'bytes'"),
    (lambda m: m["sequences"].update(s0=[]), "manifest.json: sequences['s0']: must be an object"),
    (lambda m: m["sequences"]["s0"].update(render_views=5), "sequences['s0']: 'render_views' must be a list"),
    (lambda m: m["sequences"]["s0"].update(has=[1]), "sequences['s0']: 'has' must be an object"),
    (lambda m: m["sequences"]["s0"].update(frames=[[]]), "sequences/s0: manifest gives a list frames"),
    (lambda m: m["split"].update(files={"train": ["x"]}), "manifest.json: split.files[train] must be a path"),
    (lambda m: m["stats"].update(mean={"a": 1}), "manifest.json: stats[mean] must be a path"),
    (lambda m: m["sequences"].update({"../x": {}}), "invalid seq_id '../x'"),
]  # fmt: skip
SCHEMA_CASES = [
    (lambda s: s["arrays"].__setitem__(0, {}), "schema.json: arrays[0]: 'file' must be text"),
    (lambda s: s["arrays"][0].update(file="{seq_id.__class__}"), "schema.json: arrays[0]: 'file'"),
    (lambda s: s["arrays"][0].update(file="{0}"), "schema.json: arrays[0]: 'file'"),
    (lambda s: s["arrays"][0].update(shape=[[1]]), "schema.json: arrays[0]: 'shape' must be a list of sizes"),
    (lambda s: s["arrays"][0].update(dtype="nonsense"), "arrays[0]: 'dtype' 'nonsense' is not a numpy dtype"),
    (lambda s: s["arrays"][0].update(dtype="O"), "schema.json: arrays[0]: 'dtype' 'O' is not a plain number"),
    (lambda s: s.update(arrays={"a": 1}), "schema.json: 'arrays' must be a list"),
    (lambda s: s.update(dims=[]), "schema.json: 'dims' must be an object"),
]  # fmt: skip


@pytest.mark.parametrize("mutate, message", MANIFEST_CASES)
def test_malformed_manifest_entries_are_named(ds, mutate, message):
    manifest = _manifest(ds)
    mutate(manifest)
    _write_manifest(ds, manifest)
    assert message in _text(verify_export(ds))


@pytest.mark.parametrize("mutate, message", SCHEMA_CASES)
def test_malformed_schema_entries_are_named(ds, mutate, message):
    schema = json.loads((ds / "schema.json").read_text())
    mutate(schema)
    (ds / "schema.json").write_text(json.dumps(schema))
    manifest = _manifest(ds)
    _relist(ds, manifest, "schema.json")
    _write_manifest(ds, manifest)
    assert message in _text(verify_export(ds))


def test_deeply_nested_json_is_a_problem_not_a_recursion_error(ds):
    (ds / "schema.json").write_text("[" * 100_000 + "]" * 100_000)
    assert "schema.json: not valid JSON (nested too deeply)" in _text(verify_export(ds))
    (ds / "manifest.json").write_text('{"format": ' + "[" * 100_000 + "]" * 100_000 + "}")
    assert "manifest.json is not valid JSON (nested too deeply)" in _text(verify_export(ds))


# ------------------------------------------------------------------------------------ random damage
_SCALAR = st.none() | st.booleans() | st.integers(-3, 1 << 40) | st.floats(allow_nan=False) | st.text(max_size=12)
_JSON = st.recursive(_SCALAR, lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=8), kids, max_size=3),
                     max_leaves=8)  # fmt: skip


def _paths(doc, prefix=()):
    """Every key path in a JSON document (the root included)."""
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:4]):  # the first entries stand for the rest
            yield from _paths(v, (*prefix, i))


def _mutated(doc, data) -> object:
    doc = json.loads(json.dumps(doc))
    paths = [p for p in _paths(doc) if not (len(p) > 2 and p[0] == "arrays" and p[2] == "fields")]
    path = data.draw(st.sampled_from(paths))
    value = data.draw(_JSON | st.sampled_from(["/etc/passwd", "../x", "{seq_id}/../../x", "T", "T-1", "float16"]))
    if not path:
        return value
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if isinstance(parent, dict) and data.draw(st.booleans()):
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return doc


@settings(max_examples=50)  # each example verifies a whole export (~25 ms); the long run is the fuzz script's
@given(data=st.data())
def test_randomly_damaged_manifests_and_schemas_give_problems_not_crashes(ds, data):
    manifest, schema = _manifest(ds), json.loads((ds / "schema.json").read_text())
    try:
        if data.draw(st.booleans()):
            (ds / "schema.json").write_text(json.dumps(_mutated(schema, data)))
            _relist(ds, manifest, "schema.json")
            _write_manifest(ds, manifest)
        else:
            _write_manifest(ds, _mutated(manifest, data))
        problems = verify_export(ds, check_features=False)
        _text(problems)
    finally:
        (ds / "schema.json").write_text(json.dumps(schema))
        _relist(ds, manifest, "schema.json")
        _write_manifest(ds, manifest)


@settings(max_examples=50)
@given(edits=st.lists(st.tuples(st.integers(0, 1 << 16), st.integers(0, 255)), max_size=6), cut=st.integers(0, 1 << 16))
def test_randomly_damaged_npz_files_with_matching_checksums_give_problems_not_crashes(ds, edits, cut):
    rel = "sequences/s0/contacts.npz"
    manifest, original = _manifest(ds), (ds / rel).read_bytes()
    data = bytearray(original)
    for pos, byte in edits:
        data[pos % len(data)] = byte
    try:
        (ds / rel).write_bytes(bytes(data[: len(data) - cut % 64]))  # relisted below: only the contents are wrong
        _relist(ds, manifest, rel)
        _write_manifest(ds, manifest)
        _text(verify_export(ds, check_features=False))
    finally:
        (ds / rel).write_bytes(original)
        _relist(ds, manifest, rel)
        _write_manifest(ds, manifest)


def test_cli_prints_names_from_the_export_as_text(ds):
    from click.testing import CliRunner

    from dualhuman_builder.cli import main

    (ds / "sequences" / "[").mkdir()
    (ds / "sequences" / "[" / "x]").write_text("markup")  # sequences/[/x]: a closing tag to rich
    (ds / "sequences" / "\x1b[2Jclear").write_text("a terminal escape")
    r = CliRunner().invoke(main, ["export", "verify", str(ds)])
    assert r.exit_code == 1, r.output
    assert "sequences/[/x]: not listed in the manifest" in r.output
    assert "'sequences/\\x1b[2Jclear': not listed in the manifest" in r.output and "\x1b" not in r.output


def test_loaders_and_shards_read_only_inside_the_export(ds, tmp_path):
    from dualhuman_builder.errors import FormatError
    from dualhuman_builder.export.loader import MotionWindows
    from dualhuman_builder.export.shards import write_shards

    (tmp_path / "outside.txt").write_text("s0\n")
    manifest = _manifest(ds)
    manifest["split"]["files"]["train"] = "../outside.txt"
    _write_manifest(ds, manifest)
    with pytest.raises(FormatError, match="split file '../outside.txt'.*not a relative path inside the folder"):
        MotionWindows(ds, window=4, split="train")
    with pytest.raises(FormatError, match="split file '../outside.txt'.*not a relative path inside the folder"):
        write_shards(ds, tmp_path / "shards", split="train")
    # a sequence id that is a path, named by the manifest and a split file
    shutil.copytree(ds / "sequences/s0", tmp_path / "elsewhere")
    manifest["sequences"]["../../elsewhere"] = manifest["sequences"]["s0"]
    (ds / "splits/evil.txt").write_text("../../elsewhere\n")
    manifest["split"]["files"]["evil"] = "splits/evil.txt"
    _write_manifest(ds, manifest)
    with pytest.raises(ValueError, match="invalid seq_id '../../elsewhere'"):
        MotionWindows(ds, window=4, split="evil")
    with pytest.raises(ValueError, match="invalid seq_id '../../elsewhere'"):
        write_shards(ds, tmp_path / "shards", split="evil")


def test_a_format_version_1_export_is_not_failed_for_its_older_rotation_convention(ds):
    """Format version 1 defined the 6D rotations (dims 67:193) otherwise: verify compares the rest."""
    import io

    import numpy as np

    from dualhuman_builder.export.features import FeatureLayout

    rel = "sequences/s0/motion.npz"
    manifest = _manifest(ds)
    with np.load(ds / rel) as z:
        arrays = {k: z[k] for k in z.files}
    for key in [k for k in arrays if k.endswith(".features")]:
        arrays[key] = arrays[key].copy()
        arrays[key][:, FeatureLayout.ROTATIONS] += np.float32(0.5)  # the older convention's values
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    (ds / rel).write_bytes(buf.getvalue())
    _relist(ds, manifest, rel)
    _write_manifest(ds, manifest)
    assert any("features differ" in p for p in verify_export(ds))  # the current version: a real difference
    manifest["format_version"] = 1
    _write_manifest(ds, manifest)
    assert not any("features differ" in p for p in verify_export(ds)), verify_export(ds)
    arrays[next(k for k in arrays if k.endswith(".features"))][:, 0] += np.float32(0.5)  # outside the rotations
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    (ds / rel).write_bytes(buf.getvalue())
    _relist(ds, manifest, rel)
    _write_manifest(ds, manifest)
    assert any("features differ" in p for p in verify_export(ds))
