"""``dualhuman demo``: every stage of the pipeline on two simulated actors, in one workspace.

Each step is a workspace stage (:data:`dualhuman_builder.pipeline.STAGES`), so a second run finds
everything up to date and does nothing:

1. creates (or reuses) the workspace, registers the simulated rig ``sim.toml`` and two actors of
   different statures whose anny shapes are solved from stature;
2. take ``DEMO``, sequence ``handshake``: the ``scene``, ``devices`` and ``capture`` stages
   (:func:`~dualhuman_builder.sim.stage.simulate_take`): a generated ground-truth handshake, its
   simulated suits, trackers and IMUs, recorded through real loopback transports;
3. take ``CALIB``, sequence ``calibration``: the same for the calibration take of the same studio
   day (the two actors apart bow, bend, twist, squat, raise their arms and turn on the spot);
4. the handshake's labels from its scene, as an annotation;
5. ``sync`` (tracker mounts and lags carried from ``CALIB``), ``fuse`` and ``fit`` of ``DEMO``;
6. ``contacts``, ``render`` (:data:`DEMO_RENDER`) and ``sheet``;
7. the quality gates checked on ``DEMO`` (flags stored in the catalog);
8. the dataset exported to ``WS/export/`` and verified (the calibration take has no fit and is
   left out; the demo exports ``DEMO`` even when a gate flags it, and says so);
9. the reaction prior trained briefly on the export (:data:`DEMO_TRAIN`, run folder
   ``WS/models/reaction-prior``), and the export's reactor refined with it into ``WS/refined/``
   (verified);
10. the two-person pose estimator and the temporal network trained briefly on the export's renders
    (:data:`DEMO_IMAGE_MODELS`, under ``WS/models/``), and both people estimated from one view of
    the renders by the paper's pipeline (estimator, temporal network, the reaction prior's
    test-time optimisation) into ``WS/estimated/`` (verified): the models run end to end, not to
    a useful accuracy;
11. the review page ``WS/review.html`` of the workspace's takes.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from dualhuman_builder.sim.stage import DEFAULT_ACTORS

DEMO_TAKE = "DEMO"
DEMO_SEQUENCE = "handshake"
DEMO_SCENE = {"type": "handshake", "seed": 3, "fps": 30.0}
DEMO_ACTORS = DEFAULT_ACTORS
#: The calibration take: the same actors and simulated devices (seed), another motion.
CALIB_TAKE = "CALIB"
CALIB_SEQUENCE = "calibration"
CALIB_SCENE = {"type": "calibration", "seed": DEMO_SCENE["seed"], "fps": DEMO_SCENE["fps"]}
#: The simulated devices play in real time while recorded, well under the highest multiple a
#: 2-core machine records without loss (``benchmarks/bench_capture.py``).
DEMO_CAPTURE_SPEED = 1.0
#: The demo's render: four views of every 10th frame, small and quick on a CPU.
DEMO_RENDER = {"views": 4, "size": 192, "spp": 8, "every": 10}
#: The demo's training: the reaction prior's CPU-sized model for a few steps per phase (a few seconds),
#: on every window of the one exported sequence.
DEMO_TRAIN = {"model": "reaction-prior", "steps_scale": 0.01, "batch_size": 4, "seed": 0}
DEMO_RUN_DIR = "models/reaction-prior"
DEMO_REFINED_DIR = "refined"
#: The image models, as briefly (:data:`DEMO_TRAIN`'s steps, batch and seed): run folder under ``WS/`` -> model.
DEMO_IMAGE_MODELS = {"models/pose-estimator": "pose-estimator", "models/temporal-refiner": "temporal-refiner"}
DEMO_ESTIMATED_DIR = "estimated"


@dataclass
class DemoResult:
    workspace: Path
    outputs: dict[str, Path] = field(default_factory=dict)
    ran: list[str] = field(default_factory=list)
    up_to_date: list[str] = field(default_factory=list)
    seconds: float = 0.0


def run_demo(workspace: str | Path = "demo-workspace", log: Callable[[str], None] = print) -> DemoResult:
    """Run the demo pipeline into ``workspace`` (created if missing); returns what it wrote."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.sim.stage import ensure_actors, simulate_take
    from dualhuman_builder.workspace import Workspace

    t0 = time.perf_counter()
    result = DemoResult(Path(workspace))
    with Workspace.init(workspace) as ws:
        log(f"workspace {ws.root}")
        ws.add_rig(RIGS_DIR / "sim.toml")
        model = get_body_model()
        shapes = ensure_actors(ws, DEMO_ACTORS, model, log)
        for take, seq, scene_params in ((DEMO_TAKE, DEMO_SEQUENCE, DEMO_SCENE), (CALIB_TAKE, CALIB_SEQUENCE, CALIB_SCENE)):
            ran = simulate_take(ws, take, seq, scene_params, DEMO_ACTORS, shapes, speed=DEMO_CAPTURE_SPEED, model=model, log=log)
            prefix, tag = ("", "") if take == DEMO_TAKE else (f"{take}/", f" ({take})")
            for stage, res in ran.items():
                _note(result, log, stage + tag, res, prefix)
        if not ws.annotations(DEMO_TAKE):
            _annotate_from_scene(ws, DEMO_TAKE, DEMO_SEQUENCE)

        from dualhuman_builder.contacts.stage import run_contacts
        from dualhuman_builder.fit.stage import run_fit
        from dualhuman_builder.render.sheet import run_sheet
        from dualhuman_builder.render.stage import run_render

        res = run_fit(ws, DEMO_TAKE, log=log, fps=DEMO_SCENE["fps"], mounts_from=CALIB_TAKE)
        for stage in ("sync", "fuse"):
            result.outputs.update(ws.artifacts(stage, DEMO_TAKE))
        _note(result, log, "fit", res)
        _note(result, log, "contacts", run_contacts(ws, DEMO_TAKE, log=log))
        _note(result, log, "render", run_render(ws, DEMO_TAKE, log=log, **DEMO_RENDER))
        _note(result, log, "sheet", run_sheet(ws, DEMO_TAKE, log=log))
        _gates(ws, result, log)
        _export(ws, result, log)
        _train_and_refine(ws, result, log)
        _estimate(ws, result, log)
        _review(ws, result, log)
    result.seconds = time.perf_counter() - t0
    return result


def _annotate_from_scene(ws, take: str, sequence: str) -> None:
    """A scene-generated sequence comes labelled with its type and text: store that as an annotation."""
    from dualhuman_builder.labels import Annotation, check_annotation, load_vocabulary
    from dualhuman_builder.sim.stage import SCENE, SCENE_ANNOTATOR, SEQUENCE_FILE
    from dualhuman_builder.tracks import InteractionSequence

    gt = InteractionSequence.load(SCENE.artifact(ws, take, SEQUENCE_FILE, sequence))
    ann = Annotation(take, sequence, SCENE_ANNOTATOR, tuple(gt.labels), tuple(gt.text))
    ws.annotate([check_annotation(ann, load_vocabulary(ws.root), ws.take(take).actors)])


def _export(ws, result: DemoResult, log) -> None:
    """Export the workspace to ``WS/export`` and verify it."""
    from dualhuman_builder.errors import DualhumanError
    from dualhuman_builder.export.collect import run_export
    from dualhuman_builder.export.verify import verify_export

    export_dir = ws.root / "export"
    manifest = export_dir / "manifest.json"
    before = manifest.read_bytes() if manifest.exists() else None
    run_export(ws, export_dir, log=log, include_flagged=True)
    problems = verify_export(export_dir)
    if problems:
        raise DualhumanError(f"the demo's export does not verify: {problems[:5]}")
    changed = before != manifest.read_bytes()
    (result.ran if changed else result.up_to_date).append("export")
    log(f"export: {export_dir} ({'written' if changed else 'up to date'}; verified)")
    result.outputs["export"] = export_dir


def _gates(ws, result: DemoResult, log) -> None:
    """Check ``DEMO`` against the quality gates (again only when a stage ran since the last check)."""
    from dualhuman_builder.quality.gates import check_take, evaluate_take, stored_flags

    before = stored_flags(ws, DEMO_TAKE).get(DEMO_TAKE)
    flags, check = evaluate_take(ws, DEMO_TAKE)
    if before is not None and before.get("stages") == check["stages"]:
        result.up_to_date.append("gates")
        flags_now = before.get("flags", [])
    else:
        flags_now = [f.as_dict() for f in check_take(ws, DEMO_TAKE)]
        result.ran.append("gates")
    log(f"quality gates: {DEMO_TAKE} " + ("clean" if not flags_now else
        f"{len(flags_now)} flag(s): " + "; ".join(f["message"] for f in flags_now)))  # fmt: skip


def _review(ws, result: DemoResult, log) -> None:
    """Write the review page when its content changed (it reads the catalog: written last)."""
    from dualhuman_builder.quality.review import REVIEW_NAME, render_page

    page_path = ws.root / REVIEW_NAME
    page = render_page(ws, page_path.parent).encode("utf-8")
    undated = re.compile(rb", written \S+ by ")  # the page says when it was written: not a change
    if page_path.is_file() and undated.sub(b"", page_path.read_bytes()) == undated.sub(b"", page):
        result.up_to_date.append("review")
    else:
        from dualhuman_builder.fileio import atomic_open

        with atomic_open(page_path, "wb") as f:
            f.write(page)
        result.ran.append("review")
    log(f"review page: {page_path}")
    result.outputs["review.html"] = page_path


def _train_and_refine(ws, result: DemoResult, log) -> None:
    """Train the reaction prior briefly on the demo's export and refine the export's reactor with it."""
    from dualhuman_builder.models.reaction_prior.refine import refine_export

    run_dir, export_dir, refined = ws.root / DEMO_RUN_DIR, ws.root / "export", ws.root / DEMO_REFINED_DIR
    _trained(DEMO_TRAIN["model"], export_dir, run_dir, "train", result, log)
    _derived("refine", refined, result, lambda: refine_export(run_dir, export_dir, refined, progress=False))
    log(f"refine: the reactor refined with the prior -> {refined} (verified)")
    result.outputs.update({"run": run_dir, "refined": refined})


def _estimate(ws, result: DemoResult, log) -> None:
    """Train the image models briefly on the demo's export and estimate both people from its renders
    with them and the reaction prior (run by :func:`_train_and_refine`)."""
    from dualhuman_builder.models.estimate import estimate_export

    export_dir, out = ws.root / "export", ws.root / DEMO_ESTIMATED_DIR
    for rel, model in DEMO_IMAGE_MODELS.items():
        _trained(model, export_dir, ws.root / rel, f"train {model}", result, log)
    estimator, temporal = (ws.root / rel for rel in DEMO_IMAGE_MODELS)
    _derived("estimate", out, result, lambda: estimate_export(estimator, export_dir, out, temporal_run=temporal,
                                                            prior_run=ws.root / DEMO_RUN_DIR, progress=False))  # fmt: skip
    log(f"estimate: both people from the renders -> {out} (verified)")
    result.outputs.update({"estimator": estimator, "temporal": temporal, "estimated": out})


def _trained(model: str, export_dir: Path, run_dir: Path, step: str, result: DemoResult, log) -> None:
    """Train ``model`` on ``export_dir`` into ``run_dir`` as :data:`DEMO_TRAIN` says (a finished run is
    kept), counting ``step`` as run or up to date by whether its summary changed."""
    from dualhuman_builder.models.training import train

    summary = run_dir / "summary.json"
    before = summary.read_bytes() if summary.is_file() else None
    o = DEMO_TRAIN
    train(model, export_dir, run_dir, steps_scale=o["steps_scale"], batch_size=o["batch_size"], seed=o["seed"],
          progress=lambda rec: None)  # fmt: skip
    (result.up_to_date if before == summary.read_bytes() else result.ran).append(step)
    log(f"train: {model} -> {run_dir}")


def _derived(step: str, out: Path, result: DemoResult, write: Callable[[], object]) -> None:
    """Write a model's export into ``out`` (``write()``), verify it, and count ``step`` as run or up
    to date by whether its manifest changed."""
    from dualhuman_builder.errors import DualhumanError
    from dualhuman_builder.export.verify import verify_export

    manifest = out / "manifest.json"
    before = manifest.read_bytes() if manifest.is_file() else None
    write()
    problems = verify_export(out)
    if problems:
        raise DualhumanError(f"the demo's {step} export {out} does not verify: {problems[:5]}")
    (result.up_to_date if before == manifest.read_bytes() else result.ran).append(step)


def _note(result: DemoResult, log, stage: str, res, prefix: str = "") -> None:
    """Count a stage as run or up to date, and keep its artifacts (names prefixed by ``prefix``)."""
    (result.up_to_date if res.skipped else result.ran).append(stage)
    log(f"stage {stage}: {'up to date' if res.skipped else 'done'}")
    result.outputs.update({prefix + k: v for k, v in res.artifacts.items()})
