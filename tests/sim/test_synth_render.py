"""Rendered ground truth (`dualhuman synth WS --path ground-truth --render`): each scene's bodies rendered by
the render stage into the export exactly as a fitted take's renders are, with the image targets; a second
call renders nothing again; the settings are recorded and checked. One tiny take (7.5 fps, one 48 px view,
every 10th frame, 2 spp)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from dualhuman_builder.sim.synth import RENDERS_DIR, SynthError, SynthOptions, load_plan, make_synthetic, plan_synthetic

FPS = 7.5
GT = SynthOptions(takes=1, seed=3, types=("high_five",), fps=FPS, long_share=0.0, actors=2, render=True,
                  render_size=48, render_views=1, render_every=10, render_spp=2)  # fmt: skip


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, body_model) -> tuple[Path, Path, object, list[str]]:
    root = tmp_path_factory.mktemp("gt-render")
    lines: list[str] = []
    result = make_synthetic(root / "ws", GT, path="ground-truth", export=root / "out", model=body_model,
                            log=lambda m: None, progress=lines.append)  # fmt: skip
    return root / "ws", root / "out", result, lines


def test_rendered_ground_truth_exports_like_a_fitted_render_and_verifies(rendered):
    from dualhuman_builder.export.verify import verify_export
    from dualhuman_builder.models.images import ImageFrames

    ws, out, result, lines = rendered
    assert result.made == ["S0001"] and not result.failed and "rendered in" in lines[0]
    assert verify_export(out) == []
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["expect"] == ["motion", "contacts", "text", "renders"] and not manifest["incomplete"]
    has = manifest["sequences"]["S0001"]["has"]
    assert all(has[k] for k in ("motion", "contacts", "cameras", "renders", "keypoints", "targets"))
    assert manifest["sequences"]["S0001"]["render_views"] == ["view00"]
    settings = manifest["synth"]["render"]
    assert {k: settings[k] for k in ("size", "views", "every", "spp")} == {"size": 48, "views": 1, "every": 10, "spp": 2}
    assert settings["radius_m"] == 3.0 and settings["fov_deg"] == 50.0
    seq = out / "sequences/S0001"
    doc = json.loads((seq / "sequence.json").read_text())
    assert doc["meta"]["render"]["jitter_seed"] == load_plan(ws)["takes"][0]["seed"]
    render = json.loads((seq / "renders/render.json").read_text())
    frames = doc["frames"]
    assert render["frames"] == list(range(0, frames, 10)) and render["size"] == [48, 48] and render["spp"] == 2
    cams = json.loads((seq / "cameras.json").read_text())["cameras"]
    assert [c["name"] for c in cams] == ["view00"] and (cams[0]["width"], cams[0]["height"]) == (48, 48)
    for f in render["frames"]:
        for kind, ext in (("rgb", "png"), ("depth", "exr"), ("mask", "png")):
            assert (seq / f"renders/views/view00/{kind}/{f:05d}.{ext}").is_file()
    assert not any(p.name.startswith(".") for p in seq.rglob("*"))  # the resume record stays in the workspace
    frames_ds = ImageFrames(out, "all", size=32)
    b = frames_ds.batch(range(len(frames_ds)))
    assert len(frames_ds) == len(render["frames"]) and b["image"].shape[1:] == (3, 32, 32)


def test_a_second_call_renders_nothing_again(rendered, body_model):
    ws, out, _, _ = rendered
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION

    folder = ws / RENDERS_DIR / f"S0001-g{GENERATOR_VERSION}"
    stamps = {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}
    plan_before = (ws / "synth.json").read_bytes()
    lines: list[str] = []
    again = make_synthetic(ws, GT, path="ground-truth", export=out, model=body_model, log=lambda m: None,
                           progress=lines.append)  # fmt: skip
    assert again.skipped == ["S0001"] and "made before, rendered before" in lines[0]
    assert {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()} == stamps
    assert (ws / "synth.json").read_bytes() == plan_before
    # the plan does not depend on the renders: the same workspace without --render is the same plan
    assert plan_synthetic(SynthOptions(**{**GT.__dict__, "render": False})) == plan_synthetic(GT)


def test_cli_render_options(rendered):
    import dualhuman_builder.cli.synth  # noqa: F401  (registers the command)
    from dualhuman_builder.cli import main

    ws, out, _, _ = rendered
    args = ["synth", str(ws), "--takes", "1", "--seed", "3", "--types", "high_five", "--fps", str(FPS), "--actors", "2",
            "--long-share", "0", "--path", "ground-truth", "--export", str(out), "--render", "--render-size", "48",
            "--render-views", "1", "--render-every", "10", "--render-spp", "2"]  # fmt: skip
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 0, r.output
    assert "renders: 1 views of 48 px, every 10 frame(s), 2 spp" in r.output and "rendered before" in r.output
    r = CliRunner().invoke(main, [*args[:-8], "--render-size", "8"])
    assert r.exit_code == 2 and "render size 8 is out of range" in r.output and "--render-size from 16" in r.output
    r = CliRunner().invoke(main, ["synth", "--help"], terminal_width=80)
    assert "--render-every" in r.output and max(map(len, r.output.splitlines())) <= 80


def test_render_needs_the_ground_truth_path(tmp_path):
    with pytest.raises(SynthError, match="full path renders its fitted takes") as e:
        make_synthetic(tmp_path / "ws", GT, path="full")
    assert "--path ground-truth" in e.value.fix and not (tmp_path / "ws").exists()
    with pytest.raises(SynthError, match="render views 0"):
        SynthOptions(takes=1, render=True, render_views=0).render_settings()
    assert SynthOptions(takes=1, render_views=0).render_settings() is None
