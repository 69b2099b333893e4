"""An MVNX export, the file a studio has most often, goes the whole way: ``dualhuman import`` of the file
(suit only, no trackers; MVN's full-body or upper-body configuration, 23 segments, calibration frames),
then sync, fuse and fit give bodies. What the file cannot give is flagged in the catalog and the reports,
not refused: no trackers, and the legs of an upper-body recording (a fixed pose MVN sets, not measured).

The MVNX files are written by the simulator (``sim.files.write_actor_mvnx``) from a small scene, and the
fitted bodies are scored against the scene's ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation as R

from dualhuman_builder import cli
from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS, SEGMENT_TPOSE_FRAME
from dualhuman_builder.capture.importers import (FLAG_NO_TRACKERS, FLAG_UNKNOWN_CONFIGURATION, FLAG_UPPER_BODY,
                                                 import_file, import_files, read_mvnx, suit_flags)  # fmt: skip
from dualhuman_builder.capture.importers.mvnx import CONFIGURATIONS, LEG_SEGMENTS, unmeasured_segments
from dualhuman_builder.errors import DualhumanError, FormatError, WorkspaceError
from dualhuman_builder.sim.files import UPPER_BODY_SENSORS, upper_body_track, write_actor_mvnx, write_bvh
from dualhuman_builder.tracks import SkeletonTrack
from dualhuman_builder.workspace import Workspace

FPS = 30.0
#: HumanML3D joints of the legs (hips, knees, ankles, feet); the others are the upper body's.
LEG_JOINTS = [1, 2, 4, 5, 7, 8, 10, 11]
UPPER_JOINTS = [j for j in range(22) if j not in LEG_JOINTS]


def run(*args, ok: bool = True):
    r = CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)
    if ok:
        assert r.exit_code == 0, r.output
    return r


def walking_skeleton(seconds: float = 1.0) -> SkeletonTrack:
    """A 23-segment MVN skeleton walking forward and turning, its legs swinging (no body model needed)."""
    offsets = {"Pelvis": (0, .95, 0), "RightUpperLeg": (-.09, -.02, 0), "LeftUpperLeg": (.09, -.02, 0),
               "RightLowerLeg": (0, -.42, 0), "LeftLowerLeg": (0, -.42, 0), "RightFoot": (0, -.42, 0),
               "LeftFoot": (0, -.42, 0), "RightToe": (0, -.07, .14), "LeftToe": (0, -.07, .14),
               "RightShoulder": (-.03, .1, 0), "LeftShoulder": (.03, .1, 0), "RightUpperArm": (-.15, 0, 0),
               "LeftUpperArm": (.15, 0, 0), "RightForeArm": (-.28, 0, 0), "LeftForeArm": (.28, 0, 0),
               "RightHand": (-.25, 0, 0), "LeftHand": (.25, 0, 0), "Neck": (0, .15, 0)}  # fmt: skip
    t = np.arange(int(round(seconds * FPS)) + 1) / FPS
    A, P = {}, {}
    for k, s in enumerate(MVN_SEGMENTS):
        parent = MVN_PARENTS[s]
        if parent is None:
            A[s] = R.from_rotvec(np.outer(0.6 * t, [0.0, 1.0, 0.0]))
            P[s] = np.asarray(offsets[s]) + np.outer(t, [0.2, 0.0, 0.5])
            continue
        axis = [0.0, 0.0, 1.0] if "Arm" in s else [1.0, 0.0, 0.0]
        A[s] = A[parent] * R.from_rotvec(np.outer(0.5 * np.sin(2 * np.pi * 0.8 * t + k), axis))
        P[s] = P[parent] + A[parent].apply(offsets.get(s, (0, .1, 0)))
    B = R.from_matrix(SEGMENT_TPOSE_FRAME)
    quat = np.stack([(A[s] * B).as_quat() for s in MVN_SEGMENTS], 1)
    pos = np.stack([P[s] for s in MVN_SEGMENTS], 1)
    ns = np.round(t * 1e9).astype(np.int64)
    return SkeletonTrack(MVN_SEGMENTS, quat, pos, ns, ns, actor="walker", fps=FPS)


# ------------------------------------------------------------------------------------ configurations
def test_mvn_configurations_name_the_segments_no_sensor_measures():
    assert unmeasured_segments("FullBody") == () and unmeasured_segments("fullbody") == ()
    assert unmeasured_segments("UpperBody") == LEG_SEGMENTS == unmeasured_segments("Upper_Body")
    assert set(unmeasured_segments("UpperBodyNoHands")) == {*LEG_SEGMENTS, "RightHand", "LeftHand"}
    assert unmeasured_segments("") is None and unmeasured_segments("Octopus") is None
    for segments in CONFIGURATIONS.values():
        assert set(segments) <= set(MVN_SEGMENTS) and "Pelvis" not in segments
    assert suit_flags("FullBody")["flags"] == [FLAG_NO_TRACKERS]
    assert suit_flags("UpperBodyNoSternum")["flags"] == [FLAG_NO_TRACKERS, FLAG_UPPER_BODY]
    assert suit_flags("LowerBody")["flags"] == [FLAG_NO_TRACKERS, "unmeasured segments"]
    assert suit_flags("?")["flags"] == [FLAG_NO_TRACKERS, FLAG_UNKNOWN_CONFIGURATION]


@given(st.text(max_size=40))
def test_any_configuration_text_gives_flags_never_an_error(text):
    got = suit_flags(text)
    assert got["flags"][0] == FLAG_NO_TRACKERS and len(got["flags"]) <= 2
    assert set(got["unmeasured_segments"]) <= set(MVN_SEGMENTS) and got["suit_configuration"] == text
    json.dumps(got)  # goes into the catalog as it is


@pytest.fixture(scope="module")
def tiny_mvnx(tmp_path_factory):
    path = tmp_path_factory.mktemp("tiny") / "tiny.mvnx"
    return write_actor_mvnx(path, walking_skeleton(0.1), rate_hz=FPS)[0].read_text()


@given(raw=st.text(max_size=30))
def test_any_configuration_attribute_reads_to_its_flags_or_a_format_error(tmp_path_factory, tiny_mvnx, raw):
    """Whatever bytes stand in the subject's ``configuration`` attribute (written as they are, unescaped),
    the reader gives the text and its flags, or a :class:`FormatError` (malformed XML); nothing else."""
    path = tmp_path_factory.mktemp("cfg", numbered=True) / "c.mvnx"
    path.write_text(tiny_mvnx.replace('configuration="FullBody"', f'configuration="{raw}"'), encoding="utf-8",
                    errors="surrogatepass")  # fmt: skip
    try:
        mf = read_mvnx(path)
    except FormatError:
        return
    got = suit_flags(mf.configuration)
    assert got["flags"][0] == FLAG_NO_TRACKERS and mf.num_frames == 4
    assert (FLAG_UPPER_BODY in got["flags"]) == (set(LEG_SEGMENTS) <= set(got["unmeasured_segments"]) and
                                                 "T8" not in got["unmeasured_segments"])  # fmt: skip


def test_an_upper_body_mvnx_holds_what_mvn_writes_in_that_configuration(tmp_path):
    """Upper body: 23 segments still, the legs in the first frame's pose under the pelvis, turning with the
    pelvis's heading and never bending; 11 sensors (none on the legs) with their arrays; no foot contacts;
    the configuration in the subject's attributes; calibration frames."""
    walk = walking_skeleton()
    path, _, track = write_actor_mvnx(tmp_path / "upper.mvnx", walk, configuration="UpperBody", rate_hz=FPS)
    mf = read_mvnx(path)
    assert mf.configuration == "UpperBody" and mf.num_frames == track.num_frames and len(mf.segment_names) == 23
    assert mf.sensors == UPPER_BODY_SENSORS and list(mf.calibration) == ["identity", "tpose"]
    assert mf.arrays["sensorOrientation"].shape[1] == 11 and "footContacts" not in mf.arrays and not mf.foot_contacts
    q, p = mf.track.orientations, mf.track.positions
    thigh, knee = MVN_SEGMENTS.index("LeftUpperLeg"), MVN_SEGMENTS.index("LeftLowerLeg")

    def bend(q):
        return (R.from_quat(q[:, thigh]).inv() * R.from_quat(q[:, knee])).magnitude()

    assert np.ptp(bend(q)) < 1e-5  # the knee never bends...
    turn = (R.from_quat(q[:, knee]) * R.from_quat(q[0, knee]).inv()).as_rotvec()
    assert np.abs(turn[:, [0, 2]]).max() < 1e-5 and np.ptp(turn[:, 1]) > 0.3  # ...the leg turns about the vertical only
    lever = np.linalg.norm(p[:, knee] - p[:, 0], axis=1)  # and the pelvis carries it along
    assert np.ptp(lever) < 1e-5
    full = read_mvnx(write_actor_mvnx(tmp_path / "full.mvnx", walk, rate_hz=FPS)[0])
    assert full.configuration == "FullBody" and len(full.sensors) == 17 and full.arrays["footContacts"].shape[1] == 4
    assert np.ptp(bend(full.track.orientations)) > 0.2  # the full body's knee bends
    # the upper body is MVN's measurement, unchanged
    upper = [MVN_SEGMENTS.index(s) for s in MVN_SEGMENTS if s not in LEG_SEGMENTS]
    np.testing.assert_allclose(q[:, upper], full.track.orientations[:, upper], atol=1e-6)
    with pytest.raises(ValueError, match="23 MVN segments"):
        upper_body_track(SkeletonTrack(("Pelvis",), q[:, :1], p[:, :1], mf.track.device_time_ns, mf.track.device_time_ns))


# ------------------------------------------------------------------------------------ import and sync
def test_sync_reads_an_imported_mvnx_take_as_its_suit_on_the_files_own_times(tmp_path):
    """``dualhuman import`` then ``dualhuman sync`` of an MVNX file: one suit on the timeline at the file's
    own times (the host clock is the file's: nothing to fit), no trackers, the flags in the catalog's take and
    stage records and in the sync report."""
    path, _, track = write_actor_mvnx(tmp_path / "walk.mvnx", walking_skeleton(), configuration="UpperBody",
                                      rate_hz=FPS)  # fmt: skip
    ws = tmp_path / "ws"
    run("init", ws)
    r = run("import", ws, path)
    assert "no trackers" in r.output and "upper body" in r.output
    r = run("sync", ws, "--take", "walk", "--fps", 15)
    assert "WARNING" in r.output and "upper body" in r.output
    with Workspace.open(ws, readonly=True) as w:
        take = w.take("walk")
        assert take.meta["flags"] == [FLAG_NO_TRACKERS, FLAG_UPPER_BODY]
        assert take.meta["suit_configuration"] == "UpperBody" and take.meta["unmeasured_segments"] == list(LEG_SEGMENTS)
        rec = w.stage_record("sync", "walk")
        assert rec["summary"]["flags"] == {"walker": [FLAG_NO_TRACKERS, FLAG_UPPER_BODY]}
        assert rec["summary"]["trackers"] == {"walker": 0}
        from dualhuman_builder.sync.stage import load_sync

        sync = load_sync(w, "walk")
    (a,) = sync.actors
    assert a.actor == "walker" and not a.serials and a.suit_valid.all()
    assert len(sync.times_s) == 16 and sync.times_s[-1] == pytest.approx(1.0)
    clock = sync.report["clocks"]["suits/mvnx/0/SuitFrame"]
    assert abs(clock["offset_s"]) < 1e-4 and abs(clock["drift_ppm"]) < 1000  # the whole-ms times, smoothed
    assert abs(clock["host_fit"]["intercept_host_ns"]) < 1e6 and abs(clock["host_fit"]["drift_ppm"]) < 1000
    # frame k of the timeline is the file's frame at k / 15 s (whole milliseconds in the file)
    np.testing.assert_allclose(a.suit_pos[:, 0], track.positions[::2, 0], atol=2e-3)
    assert sync.report["imported"]["walker"]["suit_configuration"] == "UpperBody"
    assert any("upper body" in w for w in sync.report["warnings"])


def test_takes_sync_cannot_read_get_a_clear_error(tmp_path):
    """A BVH import is no suit stream; a take of one actor has no pair of bodies; files of one take must
    be MVNX, named once, worn by different actors."""
    walk = walking_skeleton(0.5)
    bvh = write_bvh(tmp_path / "walk.bvh", walk)
    mvnx = write_actor_mvnx(tmp_path / "walk.mvnx", walk, rate_hz=FPS)[0]
    with Workspace.init(tmp_path / "ws") as ws:
        import_file(ws, bvh)
        from dualhuman_builder.sync.stage import run_sync

        with pytest.raises(WorkspaceError, match="BVH") as e:
            run_sync(ws, "walk", log=lambda m: None)
        assert e.value.fix and "MVNX" in e.value.fix
        with pytest.raises(FormatError, match="only MVNX"):
            import_files(ws, [mvnx, bvh], take="t")
        with pytest.raises(FormatError, match="same name"):
            import_files(ws, [mvnx, mvnx], take="t")
        ws.add_actor("alice", 1.7)
        with pytest.raises(WorkspaceError, match="two suits"):
            import_files(ws, [mvnx, tmp_path / "other.mvnx"], take="t", actors=["alice", "alice"])
        assert ws.takes() == ["walk"]
    bad = CliRunner().invoke(cli.main, ["import", str(tmp_path / "ws"), str(mvnx), str(bvh)])
    assert bad.exit_code == 2 and "every one is an .mvnx" in bad.output
    bad = CliRunner().invoke(cli.main, ["import", str(tmp_path / "ws"), str(mvnx), "--actor", "a", "--actor", "b"])
    assert bad.exit_code == 2 and "one per file" in bad.output


# ------------------------------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def scene(body_model):
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    return make_scene(SceneParams(type="handshake", seed=1, fps=15.0), model=body_model)


@pytest.fixture(scope="module")
def exports(scene, tmp_path_factory):
    """The MVNX files MVN would export of the scene's two actors: actor0 in the full-body configuration,
    actor1 in the upper-body one (30 Hz suits)."""
    out = tmp_path_factory.mktemp("mvnx")
    return [write_actor_mvnx(out / f"{name}.mvnx", scene.sequence.actors[i], configuration=cfg, rate_hz=30.0, seed=1,
                             character=i, label=name)[0]
            for i, (name, cfg) in enumerate((("alice", "FullBody"), ("bob", "UpperBody")))]  # fmt: skip


def joint_errors_mm(body, truth, step: int = 1) -> np.ndarray:
    """``(T, 22)`` joint errors (mm) of a fitted body against the scene's, frame ``k`` of the fit at scene
    frame ``k * step`` (the suit's first sample is the scene's first frame)."""
    T = body.num_frames
    return np.linalg.norm(body.joints() - truth.joints()[: T * step : step], axis=-1) * 1000


def test_dualhuman_import_sync_fuse_fit_of_one_mvnx_gives_a_body_and_flags(tmp_path, scene, exports):
    """The commands a user runs on one MVNX export (the upper-body one; the full-body one fits in the pair
    below): a fitted body, flagged "no trackers" and "upper body" (legs not to be trusted: weight 0 in the fit's input)
    in the catalog, the fit's summary and the top of its report; the body's joints within a few cm of the
    scene's."""
    which = 1
    ws = tmp_path / "ws"
    run("init", ws)
    run("import", ws, exports[which])
    take = exports[which].stem
    for stage in ("sync", "fuse", "fit"):
        run(stage, ws, "--take", take, "--fps", 7.5)  # every other frame of the scene's 15 fps
    from dualhuman_builder.fit.stage import fitted_bodies, load_body

    with Workspace.open(ws, readonly=True) as w:
        body = load_body(w, take)
        assert body.actor == take
        rec = w.stage_record("fit", take)
        report = (ws / rec["artifacts"]["report.html"]["path"]).read_text()
        meta = w.take(take).meta
        with pytest.raises(WorkspaceError, match="one actor"):
            fitted_bodies(w, take)
    expected = [FLAG_NO_TRACKERS, FLAG_UPPER_BODY]
    assert meta["flags"] == expected and meta["suits"][0]["suit_configuration"] == "UpperBody"
    summary = rec["summary"]
    assert summary["flags"] == {take: expected} and summary["fitted_without_trackers"] == [take]
    assert summary["unmeasured_segments"] == {take: list(LEG_SEGMENTS)}
    limits = report[report.index("Data limits") : report.index("<h2>Summary")]
    assert "no trackers" in limits and "upper body" in limits and "not to be trusted" in limits
    err = joint_errors_mm(body, scene.sequence.actors[which], step=2)
    assert body.num_frames == 30 and np.isfinite(err).all()
    print(f"{take} (upper body, alone): MPJPE {err.mean():.1f} mm, upper body {err[:, UPPER_JOINTS].mean():.1f} mm, "
          f"legs {err[:, LEG_JOINTS].mean():.1f} mm")  # fmt: skip
    assert err[:, UPPER_JOINTS].mean() < 40.0 and err.mean() < 50.0


def test_the_mvnx_files_of_a_pair_fit_as_one_take(tmp_path, scene, exports):
    """Both actors' exports imported as one take (one suit per file, in order; alice full body, bob upper
    body): sync puts them on one timeline, the fit gives the pair of bodies, each actor flagged as its file
    says. Without the collision term, to keep the test small (it is the pair's usual fit otherwise)."""
    with Workspace.init(tmp_path / "ws") as w:
        w.add_actor("alice")  # no stature: the shape comes from the suit's segments
    out = run("import", tmp_path / "ws", *exports, "--take", "pair", "--actor", "alice")
    assert out.output.count("as take 'pair'") == 2
    with Workspace.open(tmp_path / "ws", readonly=True) as w:
        assert w.take("pair").actors == ("alice",)
        assert w.take("pair").meta["flags"] == [FLAG_NO_TRACKERS, FLAG_UPPER_BODY]
    run("fit", tmp_path / "ws", "--take", "pair", "--fps", 7.5, "--no-collision")
    from dualhuman_builder.fit.stage import load_bodies

    with Workspace.open(tmp_path / "ws", readonly=True) as w:
        seq = load_bodies(w, "pair")
        summary = w.stage_record("fit", "pair")["summary"]
    assert [b.actor for b in seq.actors] == ["alice", "bob"]
    assert summary["flags"] == {"alice": [FLAG_NO_TRACKERS], "bob": [FLAG_NO_TRACKERS, FLAG_UPPER_BODY]}
    assert summary["unmeasured_segments"] == {"bob": list(LEG_SEGMENTS)} and summary["actors"] == 2
    for k, body in enumerate(seq.actors):
        err = joint_errors_mm(body, scene.sequence.actors[k], step=2)
        print(f"pair, {body.actor}: MPJPE {err.mean():.1f} mm, upper body {err[:, UPPER_JOINTS].mean():.1f} mm, "
              f"legs {err[:, LEG_JOINTS].mean():.1f} mm")  # fmt: skip
        assert np.isfinite(err).all() and err[:, UPPER_JOINTS].mean() < 40.0 and err.mean() < 50.0


def test_a_bad_configuration_in_a_file_is_flagged_not_refused(tmp_path):
    """A configuration this toolkit does not know reads as a full body, flagged."""
    path = write_actor_mvnx(tmp_path / "w.mvnx", walking_skeleton(0.3), rate_hz=FPS)[0]
    text = path.read_text().replace('configuration="FullBody"', 'configuration="Octopus &amp; friends"')
    path.write_text(text)
    with Workspace.init(tmp_path / "ws") as ws:
        r = import_file(ws, path)
        assert ws.take("w").meta["flags"] == [FLAG_NO_TRACKERS, FLAG_UNKNOWN_CONFIGURATION]
        assert any("suit configuration 'Octopus & friends' is not one MVN names" in n for n in r.notes)
    assert issubclass(FormatError, DualhumanError)
