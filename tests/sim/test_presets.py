"""Device error presets: ``ideal`` is today's simulator bit for bit, ``realistic`` draws its errors
per take, and the preset reaches the streams through ``simulate_studio``, ``sim://...&preset=``,
the stage helpers and the CLI. The realistic errors' statistics are checked in
``test_suit_realistic.py`` (suit) and the trackers' tests."""

from __future__ import annotations

import json
import socket
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dualhuman_builder import cli
from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.samples import SuitFrame
from dualhuman_builder.capture.sources import SourceError, open_source
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.sim.presets import PRESETS, PresetError, draw_device_errors
from dualhuman_builder.sim.suit import SuitErrorModel, segment_loads

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_sim_devices import greeting_sequence  # noqa: E402
from stream_digest import stream_digest  # noqa: E402

SUIT = ("sample_counter", "time_code_ms", "device_time_ns", "host_time_ns", "orientations", "positions", "sensor_acc",
        "sensor_gyro", "sensor_mag")  # fmt: skip
TRACKERS = ("device_time_ns", "host_time_ns", "valid", "position", "orientation", "velocity", "angular_velocity")
#: Digests of the studio of the 30-frame greeting sequence with device seed 4, recorded from the simulators
#: before presets existed (same numpy/scipy on this machine): suits 0 and 1, trackers of actors 0 and 1, the IMUs.
IDEAL_DIGESTS = {"suit0": "e4bb85ea0e6d2998", "suit1": "5936512cd6ff6e61", "trackers0": "f37fb14c7596694b",
                 "trackers1": "d098349004ef6f9b", "mti-xbus": "b9e6f35e827a9873", "mti-can": "54ef0be161af0e1a"}  # fmt: skip


def digest(obj, names) -> str:
    return stream_digest(obj, names)


def studio_digests(studio) -> dict:
    out = {f"suit{i}": digest(s, SUIT) for i, s in enumerate(studio.suits)}
    out.update({f"trackers{i}": digest(t, TRACKERS) for i, t in enumerate(studio.trackers)})
    out.update({k: digest(v, ("host_time_ns", "acceleration")) for k, v in studio.imus.items()})
    return out


@pytest.fixture(scope="module")
def greeting(body_model):
    return greeting_sequence(body_model, [None, None], frames=30)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory, greeting, body_model):
    """The greeting saved as a scene file, with a contact on actor 0's left hand in frames 10-19."""
    from dualhuman_builder.sim.scenes import Scene, SceneParams

    T, V = greeting.num_frames, body_model.vertex_bone().shape[0]
    distances = [np.full((T, V), np.nan, dtype=np.float16) for _ in range(2)]
    hand = body_model.vertex_bone() == body_model.bone_index("wrist.L")
    distances[0][10:20, hand] = 0.0
    stance = [{s: np.ones(T, dtype=bool) for s in ("L", "R")} for _ in range(2)]
    scene = Scene(SceneParams(type="handshake", seed=0, fps=greeting.fps), greeting, tuple(distances), stance,
                  {"greet": (0.0, 1.0)}, [(10 / greeting.fps, 19 / greeting.fps)])  # fmt: skip
    return scene.save(tmp_path_factory.mktemp("scene") / "greeting.npz")


def test_presets_agree_with_the_cli():
    assert cli.sim.PRESETS == PRESETS == ("ideal", "realistic")


def test_ideal_is_the_simulators_defaults():
    from dualhuman_builder.sim.trackers import DEFAULT_TRACKER_CLOCK, TrackerErrorModel

    dev = draw_device_errors("ideal", 3)
    assert dev.preset == "ideal" and dev.suit == SuitErrorModel() and dev.trackers == TrackerErrorModel()
    assert dev.tracker_clock == DEFAULT_TRACKER_CLOCK
    assert json.loads(json.dumps(dev.drawn))["suit"]["orientation_noise_deg"] == 1.0


def test_ideal_studio_is_bit_identical_to_the_simulators_before_presets(greeting):
    from dualhuman_builder.sim.studio import simulate_studio

    studio = simulate_studio(greeting, seed=4)
    assert studio_digests(studio) == IDEAL_DIGESTS
    assert studio_digests(simulate_studio(greeting, seed=4, preset="ideal")) == IDEAL_DIGESTS
    assert studio.devices.preset == "ideal"


def test_unknown_presets_are_refused_with_the_choices(tmp_path, greeting):
    from dualhuman_builder.evaluation.fit import record_simulated_take
    from dualhuman_builder.sim.stage import simulate_take
    from dualhuman_builder.sim.studio import simulate_studio

    with pytest.raises(PresetError, match="unknown device error preset 'realstic'") as e:
        draw_device_errors("realstic", 0)
    assert isinstance(e.value, DualhumanError) and "ideal, realistic" in e.value.fix
    with pytest.raises(PresetError):
        simulate_studio(greeting, preset="noisy")
    with pytest.raises(PresetError):  # before any scene is generated
        record_simulated_take("handshake", 0, tmp_path, preset="noisy")
    with pytest.raises(PresetError):
        simulate_take(None, "T", "s", {"type": "handshake", "seed": 0, "fps": 30.0}, (), (), preset="noisy")
    with pytest.raises(SourceError, match="unknown device error preset 'noisy'") as e:
        open_source("sim://handshake?seed=0&preset=noisy")
    assert "preset=ideal or preset=realistic" in e.value.fix
    run = lambda *a: CliRunner().invoke(cli.main, [str(x) for x in a])  # noqa: E731
    r = run("sim", "take", tmp_path / "ws", "--take", "T1", "--preset", "noisy")
    assert r.exit_code == 2 and "'noisy' is not one of 'ideal', 'realistic'" in r.output
    r = run("sim", "play", "sim://handshake?seed=0&preset=ideal", "--preset", "realistic")
    assert r.exit_code == 2 and "already says preset=ideal" in r.output
    r = run("sim", "play", "mvn+udp://127.0.0.1:9763", "--preset", "realistic")
    assert r.exit_code == 2 and "applies to sim:// sources" in r.output


def test_realistic_parameters_are_drawn_per_take():
    a, b, again = (draw_device_errors("realistic", s) for s in (1, 2, 1))
    assert a.preset == "realistic" and a.suit.realistic_errors_on
    assert a.suit == again.suit and a.trackers == again.trackers and a.tracker_clock == again.tracker_clock
    assert a.suit != b.suit and a.trackers != b.trackers and a.tracker_clock != b.tracker_clock
    drawn = json.loads(json.dumps(a.drawn))
    assert drawn["preset"] == "realistic" and drawn["seed"] == 1
    assert drawn["suit"]["soft_tissue_deg"] == a.suit.soft_tissue_deg
    assert drawn["tracker_clock"]["drift_ppm"] == a.tracker_clock.drift_ppm
    assert set(drawn["trackers"]) == set(a.trackers.__dataclass_fields__)


def test_segment_loads_map_vertex_contacts_to_mvn_segments(body_model):
    V = body_model.vertex_bone().shape[0]
    contact = np.zeros((3, V), dtype=bool)
    contact[1, body_model.vertex_bone() == body_model.bone_index("wrist.L")] = True
    contact[2, body_model.vertex_bone() == body_model.bone_index("finger2-2.L")] = True
    loads = segment_loads(contact, body_model)
    assert loads.shape == (3, 23) and loads[0].sum() == 0
    assert loads[1, MVN_SEGMENTS.index("LeftHand")] == 1 and loads[1].sum() == 1
    assert loads[2, MVN_SEGMENTS.index("LeftHand")] == 1 and loads[2].sum() == 1  # a finger belongs to the hand
    distances = np.where(contact, 0.005, np.nan).astype(np.float16)  # a scene's signed distances, NaN far
    distances[0, :5] = 0.03  # near, not touching
    np.testing.assert_array_equal(segment_loads(distances, body_model), loads)


def test_the_url_preset_reaches_the_streams(scene_file):
    from dualhuman_builder.sim.stage import studio_summary

    with open_source(f"sim://{scene_file}?devices=4") as ideal:
        assert ideal.studio.devices.preset == "ideal"
        assert studio_digests(ideal.studio) == IDEAL_DIGESTS
    with open_source(f"sim://{scene_file}?devices=4&preset=realistic") as real:
        studio = real.studio
        dev = studio.devices
        assert dev.preset == "realistic" and dev.drawn["seed"] == 4 and dev == draw_device_errors("realistic", 4)
        assert all(s.errors == dev.suit for s in studio.suits)
        assert all(t.errors == dev.trackers and t.clock == dev.tracker_clock for t in studio.trackers)
        for suit, ideal_suit in zip(studio.suits, ideal.studio.suits):
            host = np.diff(suit.host_time_ns)
            assert np.mean(host == 0) > 0.5  # frames arrive in bursts
            bone = np.linalg.norm(suit.positions[:, 6] - suit.positions[:, 5], axis=-1)  # Head - Neck
            true = np.linalg.norm(suit.truth.positions[:, 6] - suit.truth.positions[:, 5], axis=-1)
            assert abs(bone - true).max() > 1e-4  # its own skeleton
            assert not np.array_equal(suit.orientations[:5], ideal_suit.orientations[:5])
        frames = [s for s in real if isinstance(s, SuitFrame)]
        assert len(frames) == sum(len(s) for s in studio.suits)
        summary = json.loads(json.dumps(studio_summary(studio)))
        assert summary["preset"] == "realistic" and summary["drawn"] == json.loads(json.dumps(dev.drawn))
        assert {"dropouts", "dropout_s"} <= set(summary["suits"]["suit/0"])


def test_stage_parameters_keep_ideal_takes_up_to_date(tmp_path):
    from dualhuman_builder.sim.stage import _device_params, device_url

    assert _device_params(3, "ideal", speed=1.0) == {"seed": 3, "speed": 1.0}  # as before presets existed
    assert _device_params(3, "realistic") == {"seed": 3, "preset": "realistic"}
    path = tmp_path / "s.npz"
    assert device_url(path, 3) == f"sim://{path.resolve()}?devices=3"
    assert device_url(path, 3, "realistic") == f"sim://{path.resolve()}?devices=3&preset=realistic"


def _sink():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)
    return sock


def _play(scene_file, *more) -> list[bytes]:
    sock, got = _sink(), []
    try:
        r = CliRunner().invoke(cli.main, ["sim", "play", f"sim://{scene_file}?devices=4", "--mvn",
                                          f"127.0.0.1:{sock.getsockname()[1]}", "--trackers", "", "--speed", "0", *more])  # fmt: skip
        assert r.exit_code == 0, r.output
        try:
            while True:
                got.append(sock.recv(65536))
        except socket.timeout:
            pass
    finally:
        sock.close()
    return got


def test_sim_play_preset_option_reaches_the_datagrams(scene_file):
    ideal, realistic = _play(scene_file), _play(scene_file, "--preset", "realistic")
    assert ideal and realistic
    assert _play(scene_file, "--preset", "ideal") == ideal  # the same as no preset
    assert set(realistic) != set(ideal)  # other poses on the wire


def test_devices_stage_records_the_preset_and_its_draws(ws, scene_file):
    """``run_devices`` with a preset: ``devices.json`` holds it and the drawn parameters; the
    stage parameters name the preset, so another preset runs the stage again."""
    import shutil

    from dualhuman_builder.sim.stage import DEVICES, DEVICES_FILE, SCENE, SCENE_FILE, run_devices

    ws.add_take("T1", actors=[])
    ws.add_sequence("T1", "greet", 0, 30)
    ws.run_stage(SCENE, lambda out: shutil.copy(scene_file, out.path(SCENE_FILE)) and None, take="T1",
                 sequence="greet", params={"scene": "greeting"})  # fmt: skip
    res = run_devices(ws, "T1", "greet", 4, log=lambda m: None, preset="realistic")
    assert not res.skipped
    saved = json.loads(DEVICES.artifact(ws, "T1", DEVICES_FILE, "greet").read_text())
    assert saved["preset"] == "realistic"
    assert saved["drawn"] == json.loads(json.dumps(draw_device_errors("realistic", 4).drawn))
    assert run_devices(ws, "T1", "greet", 4, log=lambda m: None, preset="realistic").skipped
    assert not run_devices(ws, "T1", "greet", 4, log=lambda m: None).skipped  # ideal: another run
    saved = json.loads(DEVICES.artifact(ws, "T1", DEVICES_FILE, "greet").read_text())
    assert saved["preset"] == "ideal" and saved["drawn"]["suit"]["soft_tissue_deg"] == 0.0
