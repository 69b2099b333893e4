"""File importers: MVNX and BVH read back what the writers of ``sim.files`` wrote from a simulated
suit stream, malformed files fail with specific messages, MVNX is read in flat memory, and
``import_file`` / ``dualhuman import`` make a catalogued take."""

from __future__ import annotations

import logging
import re
import tracemalloc
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import snapshot
from scipy.spatial.transform import Rotation as R

from dualhuman_builder import cli
from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.capture.importers import import_file, read_bvh, read_mvnx
from dualhuman_builder.capture.importers.bvh import parse_bvh
from dualhuman_builder.capture.importers.mvnx import (quat_file_to_ours, quat_ours_to_file, vec_file_to_ours,
                                                      vec_ours_to_file)  # fmt: skip
from dualhuman_builder.errors import FormatError, WorkspaceError
from dualhuman_builder.fileio import load_npz, sha256_file
from dualhuman_builder.sim.files import (ERGONOMIC_JOINTS, MVN_JOINT_LABELS, identity_pose, mvnx_arrays_from_suit,
                                         write_bvh, write_mvnx)  # fmt: skip
from dualhuman_builder.body.mapping import SEGMENT_TPOSE_FRAME
from dualhuman_builder.sim.suit import MVN_SENSOR_SEGMENTS, simulate_suit
from dualhuman_builder.tracks import SkeletonTrack
from dualhuman_builder.workspace import Workspace

FPS = 60.0
# Segment origin relative to the parent's, body at identity orientation (+X left, +Y up, +Z forward), m.
OFFSETS = {
    "Pelvis": (0.0, 0.95, 0.0), "L5": (0, .1, 0), "L3": (0, .1, 0), "T12": (0, .1, 0), "T8": (0, .1, 0),
    "Neck": (0, .15, 0), "Head": (0, .1, 0), "RightShoulder": (-.03, .1, 0), "RightUpperArm": (-.15, 0, 0),
    "RightForeArm": (-.28, 0, 0), "RightHand": (-.25, 0, 0), "LeftShoulder": (.03, .1, 0),
    "LeftUpperArm": (.15, 0, 0), "LeftForeArm": (.28, 0, 0), "LeftHand": (.25, 0, 0),
    "RightUpperLeg": (-.09, -.02, 0), "RightLowerLeg": (0, -.42, 0), "RightFoot": (0, -.42, 0),
    "RightToe": (0, -.07, .14), "LeftUpperLeg": (.09, -.02, 0), "LeftLowerLeg": (0, -.42, 0),
    "LeftFoot": (0, -.42, 0), "LeftToe": (0, -.07, .14),
}  # fmt: skip


def ground_truth(duration_s: float = 2.0) -> SkeletonTrack:
    """A rigid 23-segment skeleton walking forward, turning, every joint swinging."""
    t = np.arange(int(round(duration_s * FPS)) + 1) / FPS
    A, P = {}, {}
    for k, s in enumerate(MVN_SEGMENTS):
        parent = MVN_PARENTS[s]
        if parent is None:
            A[s] = R.from_rotvec(np.outer(0.6 * t, [0.0, 1.0, 0.0]))
            P[s] = np.asarray(OFFSETS[s]) + np.outer(t, [0.2, 0.0, 0.5])
            continue
        axis = [0.0, 0.0, 1.0] if "Arm" in s else [1.0, 0.0, 0.0]
        A[s] = A[parent] * R.from_rotvec(np.outer(0.5 * np.sin(2 * np.pi * 0.8 * t + k), axis))
        P[s] = P[parent] + A[parent].apply(OFFSETS[s])
    B = R.from_matrix(SEGMENT_TPOSE_FRAME)
    quat = np.stack([(A[s] * B).as_quat() for s in MVN_SEGMENTS], 1)
    pos = np.stack([P[s] for s in MVN_SEGMENTS], 1)
    ns = np.round(t * 1e9).astype(np.int64)
    return SkeletonTrack(MVN_SEGMENTS, quat, pos, ns, ns, actor="truth", fps=FPS)


@pytest.fixture(scope="module")
def suit():
    return simulate_suit(ground_truth(), rate_hz=FPS, seed=4)


@pytest.fixture(scope="module")
def calibration(suit):
    tr = suit.to_track()
    return {"identity": identity_pose(tr), "tpose": (tr.orientations[0], tr.positions[0]),
            "tpose-isb": (tr.orientations[30], tr.positions[30])}  # fmt: skip


@pytest.fixture(scope="module")
def mvnx_file(tmp_path_factory, suit, calibration):
    path = tmp_path_factory.mktemp("mvnx") / "take 1.mvnx"
    write_mvnx(path, suit.to_track(), arrays=mvnx_arrays_from_suit(suit), calibration=calibration,
               ergonomic_joints=ERGONOMIC_JOINTS, start_epoch_ms=1_700_000_000_000, subject={"label": "alice"})  # fmt: skip
    return path


def assert_float32_equal(actual, expected):
    """Equal at float32 precision: each value within one float32 ulp of the largest component of
    its item (last axis: a quaternion, a vector); the file holds values in its own frame, so a
    component that is tiny in ours mixes file values of the item's size."""
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape
    scale = np.abs(expected).max(axis=-1, keepdims=True)
    tol = np.spacing(scale.astype(np.float32)).astype(np.float64) + 1e-15
    err = np.abs(actual - expected)
    assert np.all(err <= tol), f"worst excess over one float32 ulp: {np.max(err - tol):.3g}"


def angle_between(q1, q2) -> np.ndarray:
    return (R.from_quat(np.reshape(q1, (-1, 4))).inv() * R.from_quat(np.reshape(q2, (-1, 4)))).magnitude()


def tiled_track(suit, frames: int) -> SkeletonTrack:
    tr = suit.to_track()
    reps = -(-frames // tr.num_frames)
    ns = np.arange(frames, dtype=np.int64) * 16_666_667
    return SkeletonTrack(tr.segment_names, np.tile(tr.orientations, (reps, 1, 1))[:frames],
                         np.tile(tr.positions, (reps, 1, 1))[:frames], ns, ns, fps=FPS)  # fmt: skip


# --------------------------------------------------------------------------------------------- MVNX
def test_zup_conversion_is_the_conventions_rotation():
    from dualhuman_builder.conventions import ZUP_TO_YUP, zup_to_yup_points

    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3))
    np.testing.assert_array_equal(vec_file_to_ours(v), zup_to_yup_points(v))
    np.testing.assert_allclose(vec_file_to_ours(v), v @ ZUP_TO_YUP.T, atol=1e-15)
    np.testing.assert_array_equal(vec_ours_to_file(vec_file_to_ours(v)), v)
    q_file = R.random(50, random_state=1).as_quat()[:, [3, 0, 1, 2]]  # w x y z, Z-up
    ours = quat_file_to_ours(q_file)
    np.testing.assert_allclose(R.from_quat(ours).as_matrix(), ZUP_TO_YUP @ R.from_quat(q_file[:, [1, 2, 3, 0]]).as_matrix(),
                               atol=1e-14)  # fmt: skip
    np.testing.assert_allclose(quat_ours_to_file(ours), q_file, atol=1e-15)


def test_mvnx_round_trip_of_a_simulated_suit(mvnx_file, suit, calibration):
    mf = read_mvnx(mvnx_file)
    tr = suit.to_track()
    # normal frames only: the three calibration frames before them are kept apart
    assert mf.num_frames == len(suit) == 121
    assert list(mf.calibration) == ["identity", "tpose", "tpose-isb"]
    for kind, (q, p) in calibration.items():
        assert_float32_equal(mf.calibration[kind].orientations, q)
        assert_float32_equal(mf.calibration[kind].positions, p)
    assert mf.track.segment_names == MVN_SEGMENTS and mf.fps == FPS and mf.label == "alice"
    assert_float32_equal(mf.track.orientations, tr.orientations)
    assert_float32_equal(mf.track.positions, tr.positions)
    assert mf.track.orientation_valid.all() and mf.track.position_valid.all()
    # MVN writes whole milliseconds; there is no host clock in a file
    assert np.abs(mf.track.device_time_ns - tr.device_time_ns).max() <= 500_000
    np.testing.assert_array_equal(mf.track.host_time_ns, mf.track.device_time_ns)
    assert "no host receive clock" in mf.track.meta["host_time"]
    np.testing.assert_array_equal(mf.frame_index, np.arange(121))
    np.testing.assert_array_equal(mf.epoch_ms - 1_700_000_000_000, mf.track.device_time_ns // 1_000_000)
    arrays = mvnx_arrays_from_suit(suit)
    assert set(mf.arrays) == set(arrays)
    for name, a in arrays.items():
        assert_float32_equal(mf.arrays[name], a)
    assert mf.arrays["sensorOrientation"].shape == (121, 17, 4) and mf.arrays["jointAngle"].shape == (121, 22, 3)
    assert mf.arrays["centerOfMass"].shape == (121, 9) and mf.arrays["footContacts"].shape == (121, 4)
    # the header: sensors, joints, and bone offsets as joint points of the parent segment
    assert mf.sensors == MVN_SENSOR_SEGMENTS and mf.ergonomic_joints == ERGONOMIC_JOINTS
    assert len(mf.joints) == 22 and mf.joints[0].connector1 == "Pelvis/jL5S1" and mf.joints[0].connector2 == "L5/jL5S1"
    pelvis = mf.segments[0]
    assert pelvis.label == "Pelvis" and pelvis.id == 1
    rot0 = R.from_quat(tr.orientations[0, 0])
    expected = rot0.apply(tr.positions[0, MVN_SEGMENTS.index("LeftUpperLeg")] - tr.positions[0, 0], inverse=True)
    np.testing.assert_allclose(pelvis.points[MVN_JOINT_LABELS["LeftUpperLeg"]], expected, atol=1e-9)


def test_mvnx_without_namespace_reads_the_same(tmp_path, suit):
    tr = suit.to_track()
    a = write_mvnx(tmp_path / "ns.mvnx", tr)
    b = write_mvnx(tmp_path / "plain.mvnx", tr, namespace=False)
    assert "xmlns=" in a.read_text()[:300] and "xmlns=" not in b.read_text()[:300]
    ra, rb = read_mvnx(a), read_mvnx(b)
    np.testing.assert_array_equal(ra.track.orientations, rb.track.orientations)
    np.testing.assert_array_equal(ra.track.positions, rb.track.positions)
    assert list(ra.calibration) == list(rb.calibration) == ["identity"] and ra.arrays == rb.arrays == {}


def test_mvnx_truncated_mid_frame_names_line_and_what_was_read(tmp_path, mvnx_file):
    text = mvnx_file.read_text()
    start = text.index('<frame time="667" index="40"')
    cut = text.index("<orientation>", start) + 200  # inside frame 40's orientation values
    bad = tmp_path / "cut.mvnx"
    bad.write_text(text[:cut])
    with pytest.raises(FormatError) as e:
        read_mvnx(bad)
    msg = str(e.value)
    assert str(bad) in msg
    assert f"the file ends before its XML is complete: line {text[:cut].count(chr(10)) + 1}," in msg
    assert "inside mvnx > subject > frames > frame > orientation" in msg
    assert "read so far: 23 segments, calibration poses: identity, tpose, tpose-isb, 40 complete normal frames" in msg


def test_mvnx_malformed_xml_reports_the_position(tmp_path, mvnx_file):
    lines = mvnx_file.read_text().split("\n")
    k = next(i for i, line in enumerate(lines) if line.startswith('<frame time="200"'))
    lines[k + 2] = lines[k + 2].replace("</position>", "</positon>")
    bad = tmp_path / "tag.mvnx"
    bad.write_text("\n".join(lines))
    with pytest.raises(FormatError, match=rf"malformed XML: line {k + 3}, column \d+ \(mismatched tag\)"):
        read_mvnx(bad)


def _edit_frame(src, dst, index: int, element: str, edit) -> None:
    lines = src.read_text().split("\n")
    k = next(i for i, line in enumerate(lines) if line.startswith("<frame ") and f' index="{index}" ' in line)
    j = next(i for i in range(k, len(lines)) if lines[i].startswith(f"<{element}>"))
    lines[j] = edit(lines[j])
    dst.write_text("\n".join(lines))


def test_mvnx_wrong_value_count_names_the_frame(tmp_path, mvnx_file):
    bad = tmp_path / "count.mvnx"
    _edit_frame(mvnx_file, bad, 37, "position", lambda line: re.sub(r" \S+</position>", "</position>", line))
    with pytest.raises(FormatError) as e:
        read_mvnx(bad)
    assert ("frame 37 (index='37', time='617' ms): <position> holds 68 values, expected 69 "
            "(3 per segment x 23 segments)") in str(e.value)  # fmt: skip
    _edit_frame(mvnx_file, bad, 5, "sensorOrientation", lambda line: line.replace("<sensorOrientation>", "<sensorOrientation>1 "))
    with pytest.raises(FormatError, match=r"frame 5 .*<sensorOrientation> holds 69 values, expected 68 \(4 per sensor x 17 sensors\)"):
        read_mvnx(bad)


def test_mvnx_non_number_and_missing_element(tmp_path, mvnx_file):
    bad = tmp_path / "nan.mvnx"
    _edit_frame(mvnx_file, bad, 3, "velocity", lambda line: re.sub(r"^(<velocity>(\S+ ){3})\S+", r"\1abc", line))
    with pytest.raises(FormatError, match=r"frame 3 \(index='3', time='50' ms\): <velocity> value 3 is not a number: 'abc'"):
        read_mvnx(bad)
    _edit_frame(mvnx_file, bad, 9, "jointAngle", lambda line: "")
    with pytest.raises(FormatError, match=r"frame 9 .* holds elements \[.*'sensorOrientation', 'jointAngleXZY'"):
        read_mvnx(bad)


def test_mvnx_not_an_mvnx_file(tmp_path):
    bad = tmp_path / "other.mvnx"
    bad.write_text('<?xml version="1.0"?>\n<svg><g/></svg>\n')
    with pytest.raises(FormatError, match="not an MVNX file: the root element is <svg>, not <mvnx>"):
        read_mvnx(bad)
    with pytest.raises(FormatError, match="no such file"):
        read_mvnx(tmp_path / "missing.mvnx")


def refused(read, path) -> tuple[str, int]:
    """The message of the FormatError ``read(path)`` raises, and the peak traced memory meanwhile (bytes)."""
    tracemalloc.start()
    try:
        with pytest.raises(FormatError) as e:
            read(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return str(e.value), peak


@pytest.mark.parametrize(
    "old, new, message",
    [
        ('sensorCount="17"', 'sensorCount="100000000"',
         "<frames> claims 100,000,000 items per frame (sensorCount); more than any MVN setup has (at most 1000)"),
        ('jointCount="22"', 'jointCount="1000000"', "<frames> claims 1,000,000 items per frame (jointCount)"),
        ('jointCount="22"', 'jointCount="-5"', "<frames jointCount='-5'> is not a whole number of items"),
        ('sensorCount="17"', 'sensorCount="1e9"', "<frames sensorCount='1e9'> is not a whole number of items"),
        ('sensorCount="17"', 'sensorCount="999"', ("frame 0 (index='0', time='0' ms): <sensorFreeAcceleration> "
                                                   "holds 51 values, expected 2997 (3 per sensor x 999 sensors)")),
    ],
)  # fmt: skip
def test_mvnx_counts_are_checked_before_they_size_anything(tmp_path, mvnx_file, old, new, message):
    """A count in <frames> sizes no array until it is plausible and the first normal frame holds the
    values it implies: a bad claim is a FormatError, read in little memory from this 1.2 MB file."""
    text = mvnx_file.read_text()
    assert text.count(old) == 1
    bad = tmp_path / "claims.mvnx"
    bad.write_text(text.replace(old, new))
    msg, peak = refused(read_mvnx, bad)
    assert message in msg and "(fix: " in msg
    assert peak < 16 << 20, peak


def test_cli_import_of_a_false_count_is_a_clear_error(tmp_path, mvnx_file):
    bad = tmp_path / "bomb.mvnx"
    bad.write_text(mvnx_file.read_text().replace('sensorCount="17"', 'sensorCount="400000000"'))
    ws = tmp_path / "ws"
    run("init", ws)
    before = snapshot(ws)
    r = run("import", ws, bad)
    assert r.exit_code == 2 and "error: " in r.output and "claims 400,000,000 items per frame" in r.output
    assert snapshot(ws) == before


LAUGHS = ('<!DOCTYPE mvnx [<!ENTITY lol "lol">' + "".join(f'<!ENTITY lol{i} "{("&lol%s;" % (i - 1 or "")) * 10}">'
                                                        for i in range(1, 10)) + "]>", "&lol9;")  # fmt: skip
# 2 KB declaring 1 MB: within expat's own amplification limits, so only defusedxml's refusal stops it
QUIET_EXPANSION = ('<!DOCTYPE mvnx [<!ENTITY a "' + "a" * 1000 + '"><!ENTITY b "' + "&a;" * 1000 + '">]>', "&b;")


@pytest.mark.parametrize("doctype, ref, message", [
    (*LAUGHS, "declares an XML entity ('lol'); refused: MVN never writes entities"),
    (*QUIET_EXPANSION, "declares an XML entity ('a'); refused"),
    ('<!DOCTYPE mvnx [<!ENTITY xxe SYSTEM "file://{secret}">]>', "&xxe;",
     "declares an XML entity ('xxe', external: 'file://{secret}'); refused"),
    ('<!DOCTYPE mvnx [<!ENTITY % xxe SYSTEM "file://{secret}"> %xxe;]>', "",
     "declares an XML entity ('xxe', external: 'file://{secret}'); refused"),
])  # fmt: skip
def test_mvnx_entities_are_refused_not_expanded(tmp_path, mvnx_file, doctype, ref, message):
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET")
    text = mvnx_file.read_text().replace("<mvnx ", doctype.format(secret=secret) + "\n<mvnx ", 1)
    bad = tmp_path / "entities.mvnx"
    bad.write_text(text.replace("<comment></comment>", f"<comment>{ref}</comment>", 1))
    msg, peak = refused(read_mvnx, bad)
    assert message.format(secret=secret) in msg and "TOP-SECRET" not in msg
    assert peak < 16 << 20, peak


def test_mvnx_doctype_without_entities_reads_and_fetches_nothing(tmp_path, mvnx_file):
    text = mvnx_file.read_text().replace("<mvnx ", f'<!DOCTYPE mvnx SYSTEM "file://{tmp_path}/absent.dtd">\n<mvnx ', 1)
    path = tmp_path / "doctype.mvnx"
    path.write_text(text)
    assert read_mvnx(path).num_frames == 121


def test_mvnx_nesting_and_element_floods_are_bounded(tmp_path, mvnx_file):
    """Elements nest at most 32 deep; a frame holds at most 100,000 elements; elements outside frames and
    <subject> sections are dropped as soon as they close, so 50,000 of them take no more memory than 3
    (beyond the parser's queue of one 64 KiB chunk)."""
    text = mvnx_file.read_text()
    bad = tmp_path / "deep.mvnx"
    bad.write_text(text.replace("<comment></comment>", "<comment>" + "<a>" * 40 + "</a>" * 40 + "</comment>", 1))
    with pytest.raises(FormatError, match=r"elements nested more than 32 deep \(<a> inside mvnx > comment > a > a"):
        read_mvnx(bad)
    bad.write_text(text.replace('ms="1700000000000" type="normal">', 'ms="1700000000000" type="normal">'
                                + "<x/>" * 100_001, 1))  # fmt: skip
    with pytest.raises(FormatError, match="more than 100,000 elements inside mvnx > subject > frames > frame"):
        read_mvnx(bad)
    peaks = []
    for n in (3, 50_000):
        path = tmp_path / f"flood{n}.mvnx"
        path.write_text(text.replace("<comment></comment>", "<comment>" + "<x/>" * n + "</comment>", 1))
        tracemalloc.start()
        try:
            assert read_mvnx(path).num_frames == 121
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
    assert peaks[1] < peaks[0] + (3 << 20), peaks


def test_mvnx_times_and_clocks_out_of_range(tmp_path, mvnx_file):
    """A time whose nanoseconds do not fit int64 is a FormatError; an index or wall clock out of range
    reads as absent (-1), and an import keeps the take without a start time."""
    text = mvnx_file.read_text()
    bad = tmp_path / "time.mvnx"
    bad.write_text(text.replace('time="667" index="40"', 'time="1e300" index="40"'))
    msg, _ = refused(read_mvnx, bad)
    assert "frame 40 (index='40', time='1e300' ms) has a time that is not finite or beyond 9.2e+12 ms" in msg
    bad.write_text(text.replace('time="667" index="40"', 'time="nan" index="40"'))
    assert "frame 40 (index='40', time='nan' ms) has a time that is not finite" in refused(read_mvnx, bad)[0]
    odd = tmp_path / "clocks.mvnx"
    odd.write_text(text.replace(' index="40" ', ' index="99999999999999999999" ')
                   .replace('ms="1700000000000"', 'ms="9000000000000000"'))  # fmt: skip
    mf = read_mvnx(odd)
    assert mf.frame_index[40] == -1 and mf.frame_index[41] == 41 and mf.epoch_ms[0] == 9_000_000_000_000_000
    with Workspace.init(tmp_path / "ws") as ws:
        r = import_file(ws, odd)
        assert ws.take(r.take).start_time is None
        assert "the first frame's wall clock (ms=9000000000000000) is not a date; no start time" in r.notes


@pytest.mark.slow
def test_mvnx_reading_streams_in_flat_memory(tmp_path, suit):
    """What parsing holds beyond its preallocated output (sampled after every chunk) stays the
    same for a 2x longer file, and is a small part of what the whole tree (``ET.parse``) takes.
    (The overall peak also holds SkeletonTrack's validated copies, which grow with the result.)"""
    stats = {}
    for frames in (1500, 3000):
        path = write_mvnx(tmp_path / f"{frames}.mvnx", tiled_track(suit, frames))
        samples, reads = [], []

        def progress(n, done, total, samples=samples, reads=reads):
            samples.append(tracemalloc.get_traced_memory()[0])
            reads.append((done, total))

        tracemalloc.start()
        try:
            mf = read_mvnx(path, progress=progress)
        finally:
            tracemalloc.stop()
        assert mf.num_frames == frames and reads[-1][0] == reads[-1][1] == path.stat().st_size
        output = mf.track.orientations.nbytes + mf.track.positions.nbytes + 3 * 8 * frames
        stats[frames] = (max(samples) - output, path)
    (extra1, _), (extra2, path2) = stats[1500], stats[3000]
    assert extra2 < extra1 + 300_000, (extra1, extra2)
    tracemalloc.start()
    try:
        tree = ET.parse(path2)
        tree_bytes = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    del tree
    assert extra2 < 0.25 * tree_bytes, (extra2, tree_bytes)


# --------------------------------------------------------------------------------------------- BVH
def _assert_bvh_round_trip(track: SkeletonTrack, back: SkeletonTrack) -> None:
    assert back.segment_names[0] == "Pelvis" and set(back.segment_names) == set(track.segment_names)
    order = [back.segment_index(s) for s in track.segment_names]
    assert angle_between(back.orientations[:, order], track.orientations).max() < 1e-5
    assert np.abs(back.positions[:, order] - track.positions).max() < 1e-6
    assert back.fps == track.fps and back.num_frames == track.num_frames


def test_bvh_round_trip_centimetres_detected(tmp_path, suit):
    tr = suit.to_track()
    path = write_bvh(tmp_path / "take.bvh", tr)
    text = path.read_text()
    assert "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" in text and "End Site" in text
    back = read_bvh(path)
    _assert_bvh_round_trip(tr, back)
    assert back.meta["units"] == "cm" and back.meta["scale"] == 0.01
    assert "read as cm" in back.meta["scale_note"]
    np.testing.assert_array_equal(back.device_time_ns, np.round(np.arange(121) * 1e9 / FPS).astype(np.int64))
    # metres detected as well, and an explicit scale wins
    _assert_bvh_round_trip(tr, read_bvh(write_bvh(tmp_path / "m.bvh", tr, units_per_metre=1.0)))
    assert read_bvh(tmp_path / "m.bvh").meta["units"] == "m"
    wrong = read_bvh(path, scale=0.001)
    np.testing.assert_allclose(wrong.positions, back.positions / 10, atol=1e-9)


def test_bvh_round_trip_all_position_channels_and_xyz_order(tmp_path, suit):
    tr = suit.to_track()
    path = write_bvh(tmp_path / "all.bvh", tr, order="XYZ", positions="all", units_per_metre=1000.0)
    assert path.read_text().count("CHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation") == 23
    back = read_bvh(path)
    assert back.meta["units"] == "mm"
    _assert_bvh_round_trip(tr, back)


HAND_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 1 2 3
  CHANNELS 6 Yrotation Xposition Yposition Zposition Xrotation Zrotation
  JOINT Chest {
    OFFSET 0 10 0
    CHANNELS 2 Xrotation Zrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
0 0 0 0 0 0 0 0
30 10 20 30 45 60 90 -15
"""


def test_bvh_kinematics_by_hand(tmp_path):
    path = tmp_path / "hand.bvh"
    path.write_text(HAND_BVH)
    tr = read_bvh(path, scale=0.01)
    assert tr.segment_names == ("Hips", "Chest") and tr.fps == 25.0 and tr.num_frames == 2
    hips = R.from_euler("YXZ", [30, 45, 60], degrees=True)  # channel order, intrinsic
    chest = hips * R.from_euler("XZ", [90, -15], degrees=True)
    assert angle_between(tr.orientations[1], np.stack([hips.as_quat(), chest.as_quat()])).max() < 1e-12
    hips_pos = np.array([1 + 10, 2 + 20, 3 + 30]) * 0.01  # OFFSET + position channels
    np.testing.assert_allclose(tr.positions[1], [hips_pos, hips_pos + hips.apply([0, 0.1, 0])], atol=1e-12)
    np.testing.assert_allclose(tr.positions[0], [[0.01, 0.02, 0.03], [0.01, 0.12, 0.03]], atol=1e-12)
    assert tr.meta["end_sites_m"] == {"Chest": [0.0, 0.05, 0.0]} and tr.meta["parents"] == [None, "Hips"]
    # a Z-up file: positions and orientations rotated into our Y-up world
    z = read_bvh(path, scale=0.01, up="z")
    np.testing.assert_allclose(z.positions[1], tr.positions[1][:, [0, 2, 1]] * [1, 1, -1], atol=1e-12)
    zy = R.from_matrix([[1, 0, 0], [0, 0, 1], [0, -1, 0]])
    assert angle_between(z.orientations[1], (zy * R.from_quat(tr.orientations[1])).as_quat()).max() < 1e-12


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("JOINT Chest {", "JOINT Chest"), "line 7: expected '{' after JOINT Chest, found 'OFFSET'"),
        (lambda t: t.replace("  }\n}\nMOTION", "  }\nMOTION"),
         "line 14: 1 block(s) not closed before MOTION: joint 'Hips' opened at line 2 has no matching '}'"),
        (lambda t: t.replace("}\nMOTION", "}\n}\nMOTION"), "line 15: '}' without a matching '{'"),
        (lambda t: t.replace("CHANNELS 2 Xrotation Zrotation", "CHANNELS 3 Xrotation Zrotation"),
         "line 8: CHANNELS declares 3 channels but lists 2: Xrotation Zrotation"),
        (lambda t: t.replace("CHANNELS 2 Xrotation", "CHANNELS 2 Xrot"), "line 8: unknown channel 'Xrot'"),
        (lambda t: t.replace("90 -15", "90"), "line 19: frame 1 holds 7 values, expected 8 (the CHANNELS of 2 joints)"),
        (lambda t: t.replace("Frames: 2", "Frames: 5"),
         "line 19: Frames: declares 5 frames but the file holds 2 frame lines (truncated?)"),
        (lambda t: t + "1 2 3 4 5 6 7 8\n", "line 20: more frame lines than the 2 that Frames: declares"),
        (lambda t: t.replace("45 60", "45 sixty"), "line 19: frame 1, value 5: 'sixty' is not a number"),
        (lambda t: t.replace("Frame Time: 0.04", "Frame Time: 0"), "line 17: Frame Time must be a positive number"),
        (lambda t: t.replace("HIERARCHY", "HIERARCHIE"), "line 1: expected HIERARCHY, found 'HIERARCHIE'"),
        # counts as ASCII digits (Python's int() takes other digits, or refuses over 4300 of them)
        (lambda t: t.replace("Frames: 2", "Frames: \u00b2"), "line 16: Frames must be a whole number, got '\u00b2'"),
        (lambda t: t.replace("Frames: 2", "Frames: " + "9" * 5000), "line 16: Frames must be a whole number"),
        (lambda t: t.replace("CHANNELS 2 Xrotation", "CHANNELS \u00b2 Xrotation"),
         "line 8: CHANNELS needs a count (a whole number), got ['\u00b2']"),
        (lambda t: t.replace("Frame Time: 0.04", "Frame Time: 0.000000001"),
         "line 17: Frame Time 1e-09 s is not a plausible frame interval (1e-06 to 3600 s)"),
    ],
)
def test_bvh_malformed_files(tmp_path, edit, message):
    path = tmp_path / "bad.bvh"
    path.write_text(edit(HAND_BVH))
    with pytest.raises(FormatError) as e:
        parse_bvh(path)
    assert message in str(e.value) and str(path) in str(e.value)


def test_bvh_non_finite_values_are_marked_invalid_counted_and_warned(tmp_path, caplog):
    """As in MVNX files: a NaN or infinite motion value makes the joint's orientation (and so its
    descendants') or position invalid in that frame, counted in ``meta`` and logged; the rest reads as usual."""
    clean = tmp_path / "clean.bvh"
    clean.write_text(HAND_BVH)
    ref = read_bvh(clean, scale=0.01)
    path = tmp_path / "nan.bvh"
    path.write_text(HAND_BVH.replace("30 10 20 30 45 60 90 -15", "nan 10 20 30 45 60 90 -15"))  # the root's Yrotation
    with caplog.at_level(logging.WARNING):
        tr = read_bvh(path, scale=0.01)
    np.testing.assert_array_equal(tr.orientation_valid, [[True, True], [False, False]])
    np.testing.assert_array_equal(tr.position_valid, [[True, True], [True, False]])
    assert (tr.meta["invalid_orientations"], tr.meta["invalid_positions"], tr.meta["nonfinite_values"]) == (2, 1, 1)
    assert "2 orientations and 1 positions not finite marked invalid (NaN or infinite motion values: 1)" in caplog.text
    np.testing.assert_array_equal(tr.orientations[0], ref.orientations[0])
    np.testing.assert_array_equal(tr.positions[0], ref.positions[0])
    np.testing.assert_array_equal(tr.positions[1, 0], ref.positions[1, 0])
    assert np.isnan(tr.orientations[1]).all() and np.isnan(tr.positions[1, 1]).all()
    path.write_text(HAND_BVH.replace("90 -15", "inf -15"))  # a leaf's rotation: its orientation only
    tr = read_bvh(path, scale=0.01)
    np.testing.assert_array_equal(tr.orientation_valid, [[True, True], [True, False]])
    assert tr.position_valid.all() and (tr.meta["invalid_orientations"], tr.meta["invalid_positions"]) == (1, 0)
    with Workspace.init(tmp_path / "ws") as ws:
        r = import_file(ws, path, scale=0.01)
        assert "1 orientations and 0 positions were not valid and are marked invalid" in r.notes
        assert SkeletonTrack.load(r.track_path).orientation_valid.sum() == 3


def test_bvh_poses_beyond_what_the_file_holds_are_refused(tmp_path):
    """Joints without channels cost track memory without bytes: 1001 joints x 20,000 frames from 80 KB
    would be 20 million poses (over 2 GB computed); refused before anything is sized."""
    joints = "".join(f"JOINT j{k}\n{{\nOFFSET 0 1 0\n}}\n" for k in range(1000))
    path = tmp_path / "bare.bvh"
    path.write_text("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 1 Yrotation\n" + joints + "}\nMOTION\n"
                    "Frames: 20000\nFrame Time: 0.01\n" + "0\n" * 20000)  # fmt: skip
    msg, peak = refused(read_bvh, path)
    size = path.stat().st_size
    assert (f"1001 joints x 20000 frames = 20,020,000 poses from a {size:,}-byte file: more than 1 per byte "
            "(1000 joints have no channels)") in msg  # fmt: skip
    assert peak < 32 << 20, peak


def test_bvh_deep_hierarchy_reads_without_recursion(tmp_path):
    depth = 1500
    text = ["HIERARCHY", "ROOT r", "{", "OFFSET 0 0 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    for k in range(depth):
        text += [f"JOINT j{k}", "{", "OFFSET 0 1 0", "CHANNELS 3 Zrotation Xrotation Yrotation"]
    text += ["}"] * (depth + 1) + ["MOTION", "Frames: 1", "Frame Time: 0.01", " ".join(["0"] * (3 * depth + 3))]
    path = tmp_path / "deep.bvh"
    path.write_text("\n".join(text) + "\n")
    tr = read_bvh(path, scale=0.01)
    assert len(tr.segment_names) == depth + 1 and tr.meta["parents"][-1] == f"j{depth - 2}"
    np.testing.assert_allclose(tr.positions[0, -1], [0.0, depth * 0.01, 0.0], atol=1e-9)


# --------------------------------------------------------------------------------------------- import
def test_import_file_makes_a_catalogued_take(tmp_path, mvnx_file, suit):
    with Workspace.init(tmp_path / "ws") as ws:
        ws.add_actor("alice", 1.7)
        r = import_file(ws, mvnx_file, actor="alice")
        assert r.take == "take_1" and r.frames == 121 and r.fps == FPS and r.segments == 23
        assert r.calibration_poses == ("identity", "tpose", "tpose-isb") and r.subject == "alice"
        take = ws.take("take_1")
        assert take.actors == ("alice",) and take.sample_counts == {"skeleton": 121, "calibration": 3}
        assert take.duration_s == pytest.approx(121 / FPS)
        assert take.start_time == "2023-11-14T22:13:20+00:00"
        assert take.meta["source_format"] == "mvnx" and take.meta["segment_count"] == 23
        assert take.meta["fps"] == FPS and take.meta["subject_label"] == "alice"
        assert take.meta["calibration_poses"] == ["identity", "tpose", "tpose-isb"]
        files = {f["path"]: f for f in take.files}
        folder = "takes/take_1/"
        assert set(files) == {folder + "take 1.mvnx", folder + "skeleton.npz", folder + "mvnx_extras.npz"}
        assert files[folder + "take 1.mvnx"]["sha256"] == sha256_file(mvnx_file)
        assert ws.verify_take_files("take_1") == []
        saved = SkeletonTrack.load(r.track_path)
        np.testing.assert_array_equal(saved.orientations, r.track.orientations)
        assert saved.actor == "alice" and saved.fps == FPS
        arrays, meta = load_npz(r.extras_path, "MvnxExtras", 1)
        np.testing.assert_array_equal(arrays["frame.jointAngle"], read_mvnx(mvnx_file).arrays["jointAngle"])
        assert arrays["calibration.tpose.orientations"].shape == (23, 4) and meta["sensors"][0] == "Pelvis"
        with pytest.raises(WorkspaceError, match="take 'take_1' already exists"):
            import_file(ws, mvnx_file)
        with pytest.raises(WorkspaceError, match="no actor 'bob'"):
            import_file(ws, mvnx_file, take="other", actor="bob")


def run(*args):
    return CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)


def test_cli_import_mvnx_and_bvh(tmp_path, mvnx_file, suit):
    ws = tmp_path / "ws"
    run("init", ws)
    r = run("import", ws, mvnx_file, "--take", "t1")
    assert r.exit_code == 0, r.output
    assert "imported take 1.mvnx as take 't1': 121 frames at 60 fps (2.02 s), 23 segments" in r.output
    assert "calibration poses: identity, tpose, tpose-isb" in r.output and "jointAngleErgo" in r.output
    bvh = write_bvh(tmp_path / "walk.bvh", suit.to_track())
    r = run("import", ws, bvh)
    assert r.exit_code == 0, r.output
    assert "as take 'walk': 121 frames at 60 fps" in r.output and "read as cm" in r.output
    with Workspace.open(ws, readonly=True) as w:
        assert w.takes() == ["t1", "walk"]
        assert w.take("walk").meta["units"] == "cm" and w.take("t1").sample_counts["skeleton"] == 121
    before = snapshot(ws)
    r = run("import", ws, mvnx_file, "--take", "t1")
    assert r.exit_code == 2 and "take 't1' already exists" in r.output
    bad = tmp_path / "bad.mvnx"
    bad.write_text(mvnx_file.read_text()[:5000])
    r = run("import", ws, bad)
    assert r.exit_code == 2 and "error: the file ends before its XML is complete" in r.output
    other = tmp_path / "notes.txt"
    other.write_text("x")
    r = run("import", ws, other)
    assert r.exit_code == 2 and "unknown file type '.txt'" in r.output
    assert snapshot(ws) == before
