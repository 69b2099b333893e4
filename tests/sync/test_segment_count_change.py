"""A take whose MVN segment count changes: a prop added mid-take (23 -> 24 segments) or a stray pose
with another count. ``read_columns`` merges the suit channel by segment name, sync takes the body's
23 segments by name and counts what it set aside or left out, and such a take flows through
``replay --verify``, sync, fuse and fit."""

from __future__ import annotations

import numpy as np
import pytest

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.log.reader import check_take, read_columns
from dualhuman_builder.capture.log.writer import TakeWriter
from dualhuman_builder.capture.samples import JointAngles, SuitFrame, SuitMeta

BODY = tuple(MVN_SEGMENTS)
SOURCES = [("suits", "mvn+udp://127.0.0.1:9763", "mvn"), ("trackers", "vive+udp://127.0.0.1:8051", "vive")]


def _frame(k: int, names: tuple, g) -> SuitFrame:
    q = g.normal(size=(len(names), 4))
    return SuitFrame(0, k, 4 * k, 4_000_000 * k, 1_000_000_000 + 4_166_667 * k, names,
                     q / np.linalg.norm(q, axis=1, keepdims=True), g.normal(size=(len(names), 3)))  # fmt: skip


def _with_prop(f: SuitFrame) -> SuitFrame:
    """``f`` with a prop (MVN's segment 24, after the body's 23) in the hand."""
    return SuitFrame(f.character, f.sample_counter, f.time_code_ms, f.device_time_ns, f.host_time_ns,
                     (*f.segment_names, "Prop1"), np.vstack([f.orientations, [[0.0, 0.0, 0.0, 1.0]]]),
                     np.vstack([f.positions, f.positions[-1:] + 0.1]))  # fmt: skip


def _write(path, samples, chunk_size: int = 8 << 10) -> None:
    w = TakeWriter(path, take="t", sources=SOURCES[:1], chunk_size=chunk_size, foxglove_hz=0)
    for s in samples:
        w.add_sample(0, s)
    w.close()


def test_read_columns_merges_a_suit_channel_whose_segments_change_by_name(tmp_path):
    """30 frames of the body's 23 segments, 29 with a prop (24), one stray of 10 segments and one
    whose last segment has another name: the channel reads back with the union of the names (the
    body's first, in MVN order), each value under its own name, NaN where a frame had no such
    segment, and the same through the index and from a cut-off copy."""
    g = np.random.default_rng(0)
    stray_names = (*BODY[:22], "Segment40")
    frames = [_frame(k, BODY, g) for k in range(30)] + [_with_prop(_frame(k, BODY, g)) for k in range(30, 59)]
    frames.insert(40, _frame(59, BODY[:10], g))
    frames.insert(50, _frame(60, stray_names, g))
    path = tmp_path / "prop.mcap"
    _write(path, frames)
    assert check_take(path).ok
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size - 200])  # no index: every record scanned
    for take, n in ((path, len(frames)), (cut, None)):
        problems: list[str] = []
        c = read_columns(take, problems)["suits/mvn/0/SuitFrame"]
        n = n or c.count
        assert 50 < n <= len(frames) and c.count == n
        names = c.columns["segment_names"]
        assert names == (*BODY, "Prop1", "Segment40")
        present = c.columns["segment_names__present"]
        assert present.shape == (n, 25) and c.columns["orientations"].shape == (n, 25, 4)
        assert c.odd == n - 30  # all but the 23-segment frames, the most common layout
        for i, f in enumerate(frames[:n]):
            cols = [names.index(s) if s != "Segment40" else 24 for s in f.segment_names]
            np.testing.assert_array_equal(present[i], np.isin(np.arange(25), cols))
            np.testing.assert_array_equal(c.columns["orientations"][i, cols], f.orientations)
            np.testing.assert_array_equal(c.columns["positions"][i, cols], f.positions)
            assert np.isnan(c.columns["positions"][i, ~present[i]]).all()
        np.testing.assert_array_equal(c.columns["host_time_ns"], [f.host_time_ns for f in frames[:n]])
        np.testing.assert_array_equal(c.columns["sample_counter"], [f.sample_counter for f in frames[:n]])


def test_read_columns_pads_other_arrays_and_keeps_string_lists_that_change(tmp_path):
    """Arrays with no names to align by are padded to the widest shape, with each sample's own
    shape beside them; a string list that indexes no array becomes one tuple per sample."""
    g = np.random.default_rng(1)
    samples = []
    for k, n in enumerate((3, 3, 5, 2)):
        samples.append(JointAngles(0, k, k, k, 10 + k, np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64) + 100,
                                   g.normal(size=(n, 3))))  # fmt: skip
        tags = ("name", "xmid") if k != 2 else ("name",)
        samples.append(SuitMeta(0, k, k, k, 10 + k, "a", "b", "c", tags, tags))
    path = tmp_path / "t.mcap"
    _write(path, samples)
    cols = read_columns(path)
    j = cols["suits/mvn/0/JointAngles"]
    assert j.count == 4 and j.odd == 2
    np.testing.assert_array_equal(j.columns["angles__shape"], [[3, 3], [3, 3], [5, 3], [2, 3]])
    assert j.columns["angles"].shape == (4, 5, 3)
    np.testing.assert_array_equal(j.columns["angles"][3, :2], samples[6].angles)
    assert np.isnan(j.columns["angles"][3, 2:]).all()
    np.testing.assert_array_equal(j.columns["parent_point_ids"][2], np.arange(5))
    assert j.columns["parent_point_ids"][3, 2:].tolist() == [0, 0, 0]
    m = cols["suits/mvn/0/SuitMeta"]
    assert m.count == 4 and m.columns["name"] == "a"
    assert list(m.columns["tags"]) == [("name", "xmid"), ("name", "xmid"), ("name",), ("name", "xmid")]


def test_a_channel_whose_every_sample_names_other_segments_stays_within_bounded_memory(tmp_path):
    """Aligning by name cannot be made to grow with the square of a channel's length (a forged take
    whose every frame names 23 segments of its own): the merged columns stay within a few times the
    channel's bytes, and the samples beyond are counted as skipped."""
    import tracemalloc

    g = np.random.default_rng(3)
    frames = [_frame(k, tuple(f"S{k}-{j}" for j in range(23)), g) for k in range(2000)]
    path = tmp_path / "t.mcap"
    _write(path, frames, chunk_size=1 << 20)
    tracemalloc.start()
    try:
        c = read_columns(path)["suits/mvn/0/SuitFrame"]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 << 20, f"{peak / 2**20:.0f} MiB"
    assert 0 < c.count < 2000 and c.count + c.skipped == 2000
    assert c.columns["segment_names"][:23] == frames[0].segment_names
    np.testing.assert_array_equal(c.columns["orientations"][0, :23], frames[0].orientations)


def test_sync_takes_the_body_segments_by_name_and_counts_the_rest(tmp_path):
    """The suit columns sync works on: the body's 23 segments in MVN order, picked by name from the
    merged channel; a frame that lacks one is left out, a prop set aside, both counted."""
    from dualhuman_builder.sync.timeline import _body_columns

    g = np.random.default_rng(2)
    order = (*BODY[5:], *BODY[:5])  # names in another order than MVN's
    frames = [_frame(k, BODY, g) for k in range(10)] + [_with_prop(_frame(k, order, g)) for k in range(10, 16)]
    frames.insert(3, _frame(16, BODY[:10], g))
    path = tmp_path / "t.mcap"
    _write(path, frames)
    cols, counts = _body_columns("suit", read_columns(path)["suits/mvn/0/SuitFrame"].columns)
    assert counts == {"segments_set_aside": ["Prop1"], "samples_with_them": 6, "samples_left_out": 1}
    kept = frames[:3] + frames[4:]
    assert cols["segment_names"] == BODY and cols["orientations"].shape == (16, 23, 4)
    assert "segment_names__present" not in cols
    for i, f in enumerate(kept):
        idx = [f.segment_names.index(s) for s in BODY]
        np.testing.assert_array_equal(cols["orientations"][i], f.orientations[idx])
        np.testing.assert_array_equal(cols["positions"][i], f.positions[idx])
    np.testing.assert_array_equal(cols["host_time_ns"], [f.host_time_ns for f in kept])


# ---------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def studio(body_model):
    """A short simulated handshake: two suits and twelve trackers at 60 Hz."""
    from dualhuman_builder.sim.scenes import SceneParams, make_scene
    from dualhuman_builder.sim.studio import StudioConfig, simulate_studio

    scene = make_scene(SceneParams(type="handshake", seed=1, fps=15.0), model=body_model)
    return scene, simulate_studio(scene.sequence, seed=1, config=StudioConfig(suit_hz=60.0, tracker_hz=60.0))


def record(path, studio, prop_from: float | None = None):
    """Record ``studio`` as the recorder does without its sockets: every datagram encoded by the
    MVN and tracker encoders, written raw, decoded by the real decoders and written as samples. With
    ``prop_from``, actor 0's suit carries a prop from that fraction of the take on."""
    from dualhuman_builder.capture.recorder import rig_bindings
    from dualhuman_builder.capture.sources import RawPacket, make_decoder
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.rig import RigActor, load_rig
    from dualhuman_builder.sim.devices import merge, mvn_packets, tracker_packets

    frames = []
    for suit in studio.suits:
        for k, f in enumerate(suit):
            prop = prop_from is not None and suit.character == 0 and k >= prop_from * len(suit)
            frames.append(_with_prop(f) if prop else f)
    frames.sort(key=lambda f: f.host_time_ns)
    trackers = [s for tr in studio.trackers for s in tr]
    packets = merge(mvn_packets(frames, clock="host", stream="suits"),
                    tracker_packets(trackers, clock="host", stream="trackers"))  # fmt: skip
    actors = [RigActor(a.name, "suits", a.character, dict(a.trackers)) for a in load_rig(RIGS_DIR / "sim.toml").actors]
    w = TakeWriter(path, take="prop", sources=SOURCES, bindings=rig_bindings(actors))
    decoders = [make_decoder(url) for _, url, _ in SOURCES]
    for p in packets:
        i = 0 if p.stream == "suits" else 1
        w.add_raw(i, RawPacket(p.time_ns, p.data))
        for s in decoders[i].feed(RawPacket(p.time_ns, p.data)):
            w.add_sample(i, s)
    for i, dec in enumerate(decoders):
        for s in dec.finish():
            w.add_sample(i, s)
    w.close()
    return path


@pytest.fixture(scope="module")
def takes(studio, tmp_path_factory):
    _, st = studio
    d = tmp_path_factory.mktemp("takes")
    return record(d / "plain.mcap", st), record(d / "prop.mcap", st, prop_from=0.5)


def _assert_same_sync(a, b) -> None:
    np.testing.assert_array_equal(a.times_s, b.times_s)
    for x, y in zip(a.actors, b.actors, strict=True):
        assert x.actor == y.actor and x.serials == y.serials
        for k in ("suit_rot", "suit_pos", "suit_valid", "trk_rot", "trk_pos", "trk_valid"):
            np.testing.assert_array_equal(getattr(x, k), getattr(y, k))


@pytest.mark.slow
def test_a_prop_added_mid_take_replays_and_syncs_on_the_body_segments(takes):
    """The prop take is complete, replays bit for bit (exit 0), and its sync is the sync of the same
    take without the prop, the prop's segment set aside and counted."""
    from click.testing import CliRunner

    from dualhuman_builder.cli import main
    from dualhuman_builder.sync.timeline import synchronise

    plain, prop = takes
    assert check_take(prop).ok
    r = CliRunner().invoke(main, ["replay", str(prop), "--verify"])
    assert r.exit_code == 0 and "bit for bit" in r.output and "Prop1" in r.output, r.output
    with_prop = synchronise(read_columns(prop), fps=15.0)
    n = read_columns(prop)["suits/mvn/0/SuitFrame"].odd
    assert n > 100
    assert with_prop.report["suit_segments"] == {"suits/mvn/0/SuitFrame": {"segments_set_aside": ["Prop1"],
                                                                           "samples_with_them": n}}  # fmt: skip
    assert any("Prop1" in w for w in with_prop.report["warnings"])
    _assert_same_sync(with_prop, synchronise(read_columns(plain), fps=15.0))


@pytest.mark.slow
def test_a_stray_pose_with_another_segment_count_is_left_out_of_sync(takes, tmp_path):
    """A take that holds one pose of 10 segments among the suit's (as a decoder that let it through
    wrote it): sync leaves that sample out, counts it, and gives the sync of the take without it."""
    from dualhuman_builder.capture.log.reader import TakeReader
    from dualhuman_builder.sync.timeline import synchronise

    plain, _ = takes
    samples = list(TakeReader(plain).samples())
    i = [k for k, (_, s) in enumerate(samples) if isinstance(s, SuitFrame) and s.character == 0][100]
    f = samples[i][1]
    stray = SuitFrame(0, f.sample_counter, f.time_code_ms, f.device_time_ns, f.host_time_ns + 1, BODY[:10],
                      f.orientations[:10], f.positions[:10])  # fmt: skip
    path = tmp_path / "stray.mcap"
    w = TakeWriter(path, take="stray", sources=SOURCES, bindings=_bindings(plain))
    index = {name: k for k, (name, _, _) in enumerate(SOURCES)}
    for k, (name, s) in enumerate(samples):
        w.add_sample(index[name], s)
        if k == i:
            w.add_sample(0, stray)
    w.close()
    sync = synchronise(read_columns(path), fps=15.0)
    assert sync.report["suit_segments"] == {"suits/mvn/0/SuitFrame": {"samples_left_out": 1}}
    assert any("1 samples lack body segments" in w for w in sync.report["warnings"])
    _assert_same_sync(sync, synchronise(read_columns(plain), fps=15.0))


def _bindings(take) -> dict:
    from dualhuman_builder.capture.log.reader import TakeReader

    r = TakeReader(take)
    r.load_header()
    return r.take_meta()["bindings"]


@pytest.mark.slow
def test_a_prop_added_mid_take_flows_through_fuse_and_fit(takes, studio, body_model):
    """``process_take`` (sync, fuse, shape calibration, the joint fit) on the prop take: every actor
    fitted on every frame, close to the ground truth."""
    from dualhuman_builder.fit.process import process_take

    scene, _ = studio
    _, prop = takes
    tf = process_take(prop, fps=15.0, model=body_model)
    seq = tf.fit.sequence
    assert [t.actor for t in seq.actors] == ["sim-a", "sim-b"] and seq.num_frames == len(tf.sync.times_s) > 40
    assert all(f.fused_with_trackers for f in tf.fused)
    idx = np.round(tf.sync.times_s * scene.sequence.fps).astype(int)
    for fit, truth in zip(seq.actors, scene.sequence.actors):
        err = np.linalg.norm(fit.joints() - truth.joints()[idx], axis=-1)
        assert np.isfinite(err).all() and err.mean() < 0.03, err.mean()
