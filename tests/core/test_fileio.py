import io
import os
import zipfile

import numpy as np
import pytest

from dualhuman_builder.errors import FormatError, FormatVersionError
from dualhuman_builder.fileio import atomic_open, atomic_path, load_npz, remove_partials, save_npz


def test_atomic_write_replaces_only_on_success(tmp_path):
    target = tmp_path / "a.bin"
    with atomic_open(target) as f:
        f.write(b"first")
    assert target.read_bytes() == b"first"
    with pytest.raises(RuntimeError):
        with atomic_open(target) as f:
            f.write(b"half of the second vers")
            raise RuntimeError("crash")
    assert target.read_bytes() == b"first"  # the complete older version survives
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]  # no temporary left behind


def test_partial_files_are_hidden_and_swept(tmp_path):
    with pytest.raises(KeyError):
        with atomic_path(tmp_path / "x.npz") as tmp:
            # what a kill -9 mid-write leaves behind: a hidden name ending in .partial
            assert tmp.parent == tmp_path and tmp.name.startswith(".x.npz.") and tmp.name.endswith(".partial")
            tmp.write_bytes(b"partial")
            raise KeyError
    assert not (tmp_path / "x.npz").exists()
    (tmp_path / ".y.npz.99-abcd.partial").write_bytes(b"left by a killed writer")
    (tmp_path / "keep.npz").write_bytes(b"complete")
    removed = remove_partials(tmp_path)
    assert [p.name for p in removed] == [".y.npz.99-abcd.partial"]
    assert [p.name for p in tmp_path.iterdir()] == ["keep.npz"]


def test_npz_round_trip_and_metadata(tmp_path):
    arrays = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array([True, False])}
    save_npz(tmp_path / "t.npz", "Thing", 2, arrays, {"fps": 30.0, "names": ["x", "y"]})
    got, meta = load_npz(tmp_path / "t.npz", "Thing", 2)
    assert set(got) == {"a", "b"}
    np.testing.assert_array_equal(got["a"], arrays["a"])
    assert got["a"].dtype == np.float32
    assert meta["fps"] == 30.0 and meta["names"] == ["x", "y"] and meta["_format_version"] == 2


def test_npz_errors_are_specific(tmp_path):
    save_npz(tmp_path / "t.npz", "Thing", 3, {"a": np.zeros(2)})
    with pytest.raises(FormatVersionError, match=r"version 3 .* reads versions up to 2"):
        load_npz(tmp_path / "t.npz", "Thing", 2)
    with pytest.raises(FormatError, match="holds a 'Thing', expected a 'Other'"):
        load_npz(tmp_path / "t.npz", "Other", 5)
    with pytest.raises(FormatError, match=r"lacks arrays \['zz'\]"):
        load_npz(tmp_path / "t.npz", "Thing", 5, required=("a", "zz"))
    data = (tmp_path / "t.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="truncated or corrupt"):
        load_npz(tmp_path / "cut.npz", "Thing", 5)
    np.savez(tmp_path / "plain.npz", a=np.zeros(3))
    with pytest.raises(FormatError, match="no __meta__"):
        load_npz(tmp_path / "plain.npz", "Thing", 5)
    with pytest.raises(FormatError, match="no such file"):
        load_npz(tmp_path / "missing.npz", "Thing", 5)


def test_npz_never_unpickles(tmp_path):
    # a pickled object array inside an otherwise valid-looking container must not be loaded
    buf = io.BytesIO()
    np.save(buf, np.array([{"evil": 1}], dtype=object), allow_pickle=True)
    save_npz(tmp_path / "t.npz", "Thing", 1, {"a": np.zeros(1)})
    with zipfile.ZipFile(tmp_path / "t.npz", "a") as z:
        z.writestr("obj.npy", buf.getvalue())
    with pytest.raises(FormatError):
        load_npz(tmp_path / "t.npz", "Thing", 1)
    with pytest.raises(TypeError, match="dtype object"):
        save_npz(tmp_path / "o.npz", "Thing", 1, {"o": np.array([object()], dtype=object)})


def test_corrupt_deflate_streams_are_format_errors_not_zlib_errors(tmp_path):
    """A flipped byte inside a compressed member fails in zlib (not zipfile): still a clear error."""
    from dualhuman_builder.export.files import npz_bytes, read_npz

    good = npz_bytes({"x": np.sin(np.arange(4000.0)).astype(np.float32)})  # the export's compressed writer
    save_npz(tmp_path / "c.npz", "Thing", 1, {"x": np.zeros(2)})
    kinds = set()
    for off in range(60, len(good) - 120, 7):
        bad = bytearray(good)
        bad[off] ^= 0xFF
        try:
            read_npz(bytes(bad))
            kinds.add("read")
        except ValueError as e:
            assert "not a readable .npz" in str(e)
            kinds.add("zlib" if "decompress" in str(e) else "other")
        (tmp_path / "c.npz").write_bytes(bytes(bad))
        with pytest.raises(FormatError, match="truncated or corrupt|no __meta__"):
            load_npz(tmp_path / "c.npz", "Thing", 1)
    assert "zlib" in kinds  # the case this test is about did occur


# ------------------------------------------------------------------------------------ confined paths
def test_paths_read_from_a_file_stay_inside_its_folder(tmp_path):
    from dualhuman_builder.fileio import confined_path, open_confined, read_confined

    root = tmp_path / "export"
    (root / "sub").mkdir(parents=True)
    (root / "sub" / "a.txt").write_text("inside")
    (tmp_path / "secret.txt").write_text("outside")
    (root / "link_in").symlink_to(root / "sub" / "a.txt")
    (root / "link_out").symlink_to(tmp_path / "secret.txt")
    (root / "dir_out").symlink_to(tmp_path)
    (root / "loop").symlink_to(root / "loop")
    os.mkfifo(root / "fifo")
    assert confined_path(root, "sub/a.txt") == (root / "sub" / "a.txt").resolve()
    assert read_confined(root, "./sub//a.txt", 100) == b"inside" == read_confined(root, "link_in", 6)
    cases = [("/etc/passwd", "not a relative path inside the folder"), ("../secret.txt", "not a relative path"),
             ("sub/../../secret.txt", "not a relative path"), ("sub\\a.txt", "backslash"), ("", "not a relative"),
             (".", "not a relative"), ("a\x00b", "not a relative"), (["sub"], r"must be a relative path \(text\)"),
             ("link_out", "leads out of the folder"), ("dir_out/secret.txt", "leads out of the folder"),
             ("loop", "loop"), ("fifo", "not a regular file"), ("sub", "not a regular file"), ("missing.txt", "missing")]
    for rel, message in cases:
        with pytest.raises(FormatError, match=message) as e:
            read_confined(root, rel, 100, what=f"split file {rel!r}")
        assert e.value.message.startswith(f"split file {rel!r}: ")
    with pytest.raises(FormatError, match=r"'sub/a.txt': 6 bytes, more than the 5 allowed"):
        read_confined(root, "sub/a.txt", 5)
    with open_confined(root, "sub/a.txt") as f:
        assert f.read() == b"inside"
