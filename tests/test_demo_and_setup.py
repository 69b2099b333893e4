"""The README's two commands: the idempotent set-up script and the demo."""

import subprocess
from pathlib import Path

import numpy as np
from PIL import Image

from dualhuman_builder.demo import DEMO_SEQUENCE, DEMO_TAKE, run_demo
from dualhuman_builder.tracks import InteractionSequence
from dualhuman_builder.workspace import Workspace

REPO = Path(__file__).resolve().parents[1]


def test_setup_script_does_no_work_the_second_time():
    # the suite runs after scripts/setup.sh (the README's test command), so everything is in place
    proc = subprocess.run([str(REPO / "scripts/setup.sh")], capture_output=True, text=True, cwd="/")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "setup: nothing to do", proc.stdout


def test_demo_runs_the_pipeline_and_is_idempotent(tmp_path):
    ws_path = tmp_path / "demo"
    logs = []
    first = run_demo(ws_path, log=logs.append)
    assert first.ran == ["scene"] and first.up_to_date == []
    out = first.outputs
    assert set(out) == {"sequence.npz", "preview.png", "preview.glb", "meshes/sim-a_first.ply", "meshes/sim-a_last.ply",
                        "meshes/sim-b_first.ply", "meshes/sim-b_last.ply"}  # fmt: skip
    seq = InteractionSequence.load(out["sequence.npz"])
    assert seq.num_frames == 60 and seq.take == DEMO_TAKE
    a, b = (t.vertices() for t in seq.actors)
    for v in (a, b):
        assert abs(v[:, :, 1].min()) < 2e-3  # soles on the floor
    statures = [v[0, :, 1].max() - v[0, :, 1].min() for v in (a, b)]
    np.testing.assert_allclose(statures, [1.68, 1.82], atol=2e-3)
    # they face each other: actor a's nose points at b, and b's at a
    noses = [t.coco()[0, 0] - t.joints()[0, 0] for t in seq.actors]
    assert noses[0][2] > 0.05 and noses[1][2] < -0.05
    assert np.linalg.norm(seq.actors[0].joints()[-1, 20] - seq.actors[0].joints()[-1, 16]) > 0.4  # arms out
    img = np.asarray(Image.open(out["preview.png"]).convert("RGB"), dtype=float)
    assert img.shape == (320, 480, 3) and img.std() > 10  # a real picture, not a blank frame
    with Workspace.open(ws_path) as ws:
        assert ws.stage_record("scene", DEMO_TAKE, DEMO_SEQUENCE)["status"] == "done"
        assert [a.shape_source for a in ws.actors()] == ["stature", "stature"]
    mtimes = {p: p.stat().st_mtime_ns for p in out.values()}
    second = run_demo(ws_path, log=logs.append)
    assert second.ran == [] and second.up_to_date == ["scene"]
    assert {p: p.stat().st_mtime_ns for p in second.outputs.values()} == mtimes  # nothing rewritten
