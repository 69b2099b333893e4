"""The README's two commands: the idempotent set-up script and the demo."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dualhuman_builder.demo import DEMO_SEQUENCE, DEMO_TAKE, run_demo
from dualhuman_builder.sim.scenes import Scene, contract_failures, describe_scene
from dualhuman_builder.tracks import InteractionSequence
from dualhuman_builder.workspace import Workspace

REPO = Path(__file__).resolve().parents[2]


#: The whole demo, and the set-up script.
pytestmark = pytest.mark.slow


def test_setup_script_does_no_work_the_second_time():
    # the suite runs after scripts/setup.sh (the README's test command), so everything is in place
    proc = subprocess.run([str(REPO / "scripts/setup.sh")], capture_output=True, text=True, cwd="/")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "setup: nothing to do", proc.stdout


def test_demo_runs_the_pipeline_and_is_idempotent(tmp_path):
    ws_path = tmp_path / "demo"
    logs = []
    first = run_demo(ws_path, log=logs.append)
    stages = ["scene", "devices", "capture", "scene (CALIB)", "devices (CALIB)", "capture (CALIB)", "fit", "contacts",
              "render", "sheet", "gates", "export", "train", "refine", "train pose-estimator", "train temporal-refiner",
              "estimate", "review"]  # fmt: skip
    assert first.ran == stages and first.up_to_date == []
    out = first.outputs
    assert set(out) >= {"scene.npz", "sequence.npz", "preview.png", "strip.png", "preview.glb", "devices.json",
                        "take.mcap", "capture.json", "sync.npz", "sync.json", "fuse.json", "bodies.npz", "shapes.json",
                        "frames.npz", "report.html", "report.png",
                        *(f"{a}.{k}.npz" for a in ("sim-a", "sim-b") for k in ("skeleton", "trackers")),
                        *(f"meshes/{a}_{t}.ply" for a in ("sim-a", "sim-b") for t in ("first", "contact"))}  # fmt: skip
    scene = Scene.load(out["scene.npz"])
    seq = InteractionSequence.load(out["sequence.npz"])
    assert seq.num_frames == 120 and [t.actor for t in seq.actors] == ["sim-a", "sim-b"]
    assert scene.params.type == "handshake" and contract_failures(scene.stats) == []
    a, b = (t.vertices() for t in seq.actors)
    for v in (a, b):
        assert abs(v[:, :, 1].min()) < 0.02  # soles on the floor
    np.testing.assert_allclose(describe_scene(scene)["data"]["statures_m"], [1.68, 1.82], atol=2e-3)
    # they face each other: actor a's nose points at b, and b's at a
    noses = [t.coco()[0, 0] - t.joints()[0, 0] for t in seq.actors]
    assert noses[0][2] > 0.05 and noses[1][2] < -0.05
    # the hands meet: ground-truth contacts during the contact phase
    labels = scene.contact_labels()
    assert labels[0][scene.contact_phase_mask()].any(axis=1).all()
    img = np.asarray(Image.open(out["preview.png"]).convert("RGB"), dtype=float)
    assert img.shape == (320, 480, 3) and img.std() > 10  # a real picture, not a blank frame
    strip = Image.open(out["strip.png"])
    assert strip.size == (6 * 300, 360)
    devices = json.loads(out["devices.json"].read_text())
    assert devices["samples"]["suit/0"] == pytest.approx(240 * 4.0, rel=0.03)
    assert len(devices["trackers"]) == 12 and devices["clocks"]["trackers"]["offset_s"] == 0.25
    # the capture stage recorded the simulated studio through real transports, losslessly
    cap = json.loads(out["capture.json"].read_text())
    assert cap["complete"] and cap["replay_identical"]
    assert cap["lost"] == {"suits": 0, "trackers": 0, "prop-imu": 0, "floor-imu": 0}
    frames = cap["per_topic"]["suits/mvn/0/SuitFrame"]
    assert frames == devices["samples"]["suit/0"], "every suit frame sent was recorded"
    assert sum(n for t, n in cap["per_topic"].items() if t.endswith("TrackerSample")) == sum(
        v for k, v in devices["samples"].items() if k.startswith("vive/"))  # fmt: skip
    # sync -> fuse -> fit: both bodies fitted to the recorded take, close to the ground truth,
    # the collision term removing most of the penetration the skeleton pass leaves
    fitted = InteractionSequence.load(out["bodies.npz"])
    sync = json.loads(out["sync.json"].read_text())
    assert abs(sync["clocks"]["source:trackers"]["offset_s"] - 0.25) < 0.005
    # the studio day's calibration take (same devices, actors turning every segment) lent its mounts
    assert Scene.load(out["CALIB/scene.npz"]).params.type == "calibration" and "CALIB/take.mcap" in out
    assert sync["mounts_from"]["take"] == "CALIB"
    assert all(len(sync["mounts_from"][a]["carried"]) == 6 for a in ("sim-a", "sim-b")), sync["mounts_from"]
    err = np.mean([np.linalg.norm(f.joints() - g.joints()[: f.num_frames], axis=-1).mean() for f, g in zip(fitted.actors, seq.actors)])
    assert err < 0.03, f"mean joint error {err * 1000:.1f} mm"
    assert "<svg" in out["report.html"].read_text()
    with Workspace.open(ws_path) as ws:
        fit_row = ws.stage_record("fit", DEMO_TAKE)
        assert fit_row["status"] == "done"
        for stage in ("scene", "devices", "capture"):
            assert ws.stage_record(stage, DEMO_TAKE, DEMO_SEQUENCE)["status"] == "done"
        # every file a stage wrote is one its declaration names (the registry is the truth)
        from dualhuman_builder.pipeline import STAGES

        for st in STAGES:
            rec = st.record(ws, DEMO_TAKE, DEMO_SEQUENCE if st.per == "sequence" else None)
            assert rec is not None and rec["status"] == "done", st.name
            undeclared = [n for n in rec["artifacts"] if not st.declares(n)]
            assert not undeclared, f"{st.name} wrote undeclared artifacts {undeclared[:5]}"
        assert [a.shape_source for a in ws.actors()] == ["stature", "stature"]
    # contacts, renders with ground truth, the contact sheet, and a verified export
    from dualhuman_builder.contacts.compute import ContactResult
    from dualhuman_builder.export.verify import verify_export

    contacts = ContactResult.load(out["contacts.npz"])
    assert contacts.labels.shape == (2, fitted.num_frames, 13718) and contacts.frame_contact.any()
    assert any("hand" in (e["region_a"] + e["region_b"]).lower() for e in contacts.events)
    cams = json.loads(out["cameras.json"].read_text())
    assert len(cams["cameras"]) == 4
    rgb = [k for k in out if k.endswith(".png") and "/rgb/" in k]
    assert len(rgb) == 4 * len(range(0, fitted.num_frames, 10))
    mask = np.asarray(Image.open(out[rgb[0].replace("/rgb/", "/mask/")]))
    assert set(np.unique(mask)) == {0, 1, 2}
    sheet = Image.open(out["contact_sheet.png"])
    assert sheet.size[0] > 4 * 200 and np.asarray(sheet.convert("L")).std() > 10
    assert verify_export(out["export"]) == []
    text = json.loads((out["export"] / "sequences" / "DEMO" / "text.json").read_text())  # pre-labelled by the scene
    assert text["labels"] == ["handshake"] and text["symmetric"] is True and sum(text["multi_hot"]) == 1
    assert text["texts"] and text["annotations"][0]["annotator"] == "dualhuman-scene"
    # the quality gates ran and the review page lists the take; the models ran end to end
    page = out["review.html"].read_text()
    assert "DEMO" in page and "<table" in page
    with Workspace.open(ws_path) as ws:
        from dualhuman_builder.quality.gates import stored_flags

        assert "render_completeness" in stored_flags(ws, DEMO_TAKE)[DEMO_TAKE]["evaluated"]
    summary = json.loads((out["run"] / "summary.json").read_text())
    assert summary["status"] == "complete" and summary["global_step"] == summary["total_steps"] > 0
    assert verify_export(out["refined"]) == []
    refined = json.loads((out["refined"] / "manifest.json").read_text())
    assert refined["refinement"] and list(refined["sequences"]) == ["DEMO"]
    # both people estimated from the renders by the estimator, the temporal network and the prior
    assert verify_export(out["estimated"]) == []
    estimated = json.loads((out["estimated"] / "manifest.json").read_text())["estimation"]
    assert estimated["stages"] == ["estimate", "fill", "temporal", "prior"] and estimated["sequences"] == 1
    assert estimated["rendered_frames"] == len(range(0, fitted.num_frames, 10))
    runs = ("run", "estimator", "temporal", "refined", "estimated")
    mtimes = {p: p.stat().st_mtime_ns for p in out.values() if p.is_file()}
    mtimes.update({p: p.stat().st_mtime_ns for d in runs for p in out[d].rglob("*") if p.is_file()})
    second = run_demo(ws_path, log=logs.append)
    assert second.ran == [] and second.up_to_date == stages
    again = {p: p.stat().st_mtime_ns for p in second.outputs.values() if p.is_file()}
    again.update({p: p.stat().st_mtime_ns for d in runs for p in second.outputs[d].rglob("*") if p.is_file()})
    assert again == mtimes  # nothing rewritten
