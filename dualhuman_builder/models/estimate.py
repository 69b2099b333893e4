"""The whole pose pipeline of the Dual-Human paper (§3.2) on a rendered export: the image estimator, the
temporal refinement network and the reaction prior's test-time optimisation, each after the one before,
written as an export of both people's tracks (`dualhuman estimate RUN DATASET --out OUT`).

:func:`estimate_export`, per sequence of the export that has renders:

1. **Estimate**: every rendered frame of one camera (``camera``, or the sequence's first rendered view)
   goes through the trained estimator (``pose-estimator``: :func:`~.pose_estimator.predict`; the
   ``lifting-baseline`` works too, from the render's 2D keypoints), frame after frame, in
   :class:`~.images.ImageFrames`' crop (the sequences in lockstep: frame k of every sequence in one
   batch). The ground-truth targets of the frames are never given to it.
2. **Link**: the previous frame's estimated roots are the track input (``prev_root``, normalised in the
   current crop); on top of it, each frame's two people are assigned to the previous frame's by the
   smaller total root distance, so an identity switch of the network does not swap the tracks.
   **Identity** at the first rendered frame: the two estimates are matched to the export's persons a and
   b by root distance to the ground truth, the evaluation convention (the image alone cannot tell which
   person the dataset calls a); the ground truth is used for nothing else.
3. **World**: camera-frame joints ``X_c`` to the world by the camera's ``R``, ``t`` (``cameras.json``,
   world-to-camera, OpenCV): ``X_w = R^T (X_c - t)``.
4. **Fill**: frames that were not rendered are linearly interpolated per joint coordinate between the
   rendered frames around them (held constant before the first and after the last); their number is
   recorded (``filled_frames``).
5. Optionally **temporal** refinement of each person (:func:`~.temporal.refine_motion`, a
   ``temporal-refiner`` run) and then the **reaction prior**'s test-time optimisation of the reactor given
   the estimated actor (:func:`~.reaction_prior.refine.refine_sequence`, a ``reaction-prior`` run; roles
   from ``text.json``).

The written export (`dualhuman export verify` accepts it) has the input's sequences, splits, labels,
texts and roles. Per person: ``joints`` are the estimate, ``features`` are computed from them, ``transl``
is the input's moved by the estimated pelvis's displacement from the input's pelvis; ``pose`` and
``shape`` are the input's, carried over unchanged (not estimated: they do not reproduce the estimated
joints). Contacts, renders and cameras are not carried over. Each ``sequence.json``'s ``meta.estimation``
and the manifest's ``estimation`` say all this, with the errors of every stage against the input's
joints (MPJPE, PA-MPJPE, translation error in mm: on the rendered frames, and on all frames).
Sequences without renders (or without the asked camera) are left out and listed (``not_estimated``).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dualhuman_builder.errors import DualhumanError

#: Models whose runs can be the estimator.
ESTIMATORS = ("pose-estimator", "lifting-baseline")
#: What each sequence's ``meta.estimation`` says besides its summary entry (``per_sequence``).
SEQUENCE_NOTES = ("stages", "estimated", "carried_over", "identity", "unrendered_frames")


def _predictor(spec) -> tuple[Callable[[torch.nn.Module, dict[str, Any]], dict[str, torch.Tensor]], tuple[str, ...]]:
    """``(predict, keys)``: the prediction function of an estimator's spec and the batch keys it may see."""
    name = getattr(spec, "name", "?")
    if name == "pose-estimator":
        from dualhuman_builder.models.pose_estimator import predict

        return predict, ("image", "K", "prev_root", "has_prev")
    if name == "lifting-baseline":
        from dualhuman_builder.models.lifting import predict

        return predict, ("keypoints2d", "K")
    own = getattr(spec, "predict", None)
    if callable(own):  # a model of one's own with the same prediction contract
        return own, tuple(getattr(spec, "predict_keys", ("image", "K", "prev_root", "has_prev")))
    raise DualhumanError(f"a run of {name!r} cannot estimate poses from images",
                         fix=f"pass a run of one of: {', '.join(ESTIMATORS)} (`dualhuman train pose-estimator DATASET`)")


def _read_json(folder: Path, rel: str) -> Any:
    from dualhuman_builder.fileio import read_confined

    try:
        return json.loads(read_confined(folder, rel, 64 * 2**20, f"{rel} of {folder}").decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise DualhumanError(f"{folder}/{rel} is not valid JSON ({e})", fix="run `dualhuman export verify` on it") from None


def _camera(folder: Path, sid: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R (3, 3), t (3,))`` of camera ``name`` of sequence ``sid``."""
    doc = _read_json(folder, f"sequences/{sid}/cameras.json")
    for c in doc.get("cameras", []) if isinstance(doc, dict) else []:
        if isinstance(c, dict) and c.get("name") == name:
            try:
                R, t = np.asarray(c["R"], np.float64).reshape(3, 3), np.asarray(c["t"], np.float64).reshape(3)
            except (KeyError, TypeError, ValueError) as e:
                raise DualhumanError(f"{folder}/sequences/{sid}/cameras.json: camera {name!r} has no usable R, t ({e})",
                                     fix="re-export the dataset") from None  # fmt: skip
            if np.isfinite(R).all() and np.isfinite(t).all():
                return R, t
    raise DualhumanError(f"{folder}/sequences/{sid}/cameras.json has no camera {name!r} with R and t", fix="re-export the dataset")


def _link(roots: np.ndarray, previous: np.ndarray) -> bool:
    """True when the two people of ``roots (2, 3)`` are better assigned to ``previous (2, 3)`` swapped."""
    straight = np.linalg.norm(roots - previous, axis=-1).sum()
    crossed = np.linalg.norm(roots[::-1] - previous, axis=-1).sum()
    return bool(crossed < straight)


def fill_frames(frames: np.ndarray, values: np.ndarray, T: int) -> np.ndarray:
    """``(T, ...)`` float32: ``values (R, ...)`` known at the sorted frame indices ``frames (R,)``, linearly
    interpolated in between and held constant before the first and after the last."""
    v = np.asarray(values, np.float64)
    flat = v.reshape(len(v), -1)
    t = np.arange(T, dtype=np.float64)
    out = np.stack([np.interp(t, frames.astype(np.float64), flat[:, k]) for k in range(flat.shape[1])], axis=-1)
    return out.reshape((T,) + v.shape[1:]).astype(np.float32)


def _errors(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    from dualhuman_builder.models.metrics import pose_errors

    return {k: float(v) for k, v in pose_errors(pred, truth).items()}


#: Images the estimator sees at once: the sequences' frames go through it in lockstep, frame k of
#: every sequence together, since a frame's track input is the same sequence's previous estimate.
ESTIMATE_BATCH = 64


def _estimate_views(ds, jobs: list[tuple[np.ndarray, np.ndarray]], predict, keys: tuple[str, ...], module,
                    device: torch.device, batch_size: int = ESTIMATE_BATCH) -> list[tuple[np.ndarray, np.ndarray, bool]]:  # fmt: skip
    """Per job ``(rows, truth_cam0)``, ``(frames (R,), joints_cam (R, 2, 22, 3), first_swapped)``: the
    estimates of one camera's rendered frames ``rows`` (items of ``ds`` in frame order), persons in the
    export's order (module docstring). The jobs' k-th frames are estimated together, in batches of
    ``batch_size``; each item's result depends only on its own image and track input."""
    from dualhuman_builder.export.writer import normalised_root

    S = ds.size
    prev: list[np.ndarray | None] = [None] * len(jobs)
    swapped = [False] * len(jobs)
    frames: list[list[int]] = [[] for _ in jobs]
    outs: list[list[np.ndarray]] = [[] for _ in jobs]
    for step in range(max((len(rows) for rows, _ in jobs), default=0)):
        active = [i for i, (rows, _) in enumerate(jobs) if step < len(rows)]
        for c0 in range(0, len(active), int(batch_size)):
            part = active[c0 : c0 + int(batch_size)]
            b = ds.batch([int(jobs[i][0][step]) for i in part])
            inp = {k: b[k] for k in keys if k in b}
            if "prev_root" in keys:
                K = b["K"].numpy().astype(np.float64)
                pr = np.zeros((len(part), 2, 3))
                has = np.array([prev[i] is not None for i in part])
                for q, i in enumerate(part):
                    if prev[i] is not None:
                        pr[q] = normalised_root(prev[i][:, 0], K[q], S, S)
                inp["prev_root"] = torch.from_numpy(pr.astype(np.float32))
                inp["has_prev"] = torch.from_numpy(has)
            inp = {k: (v.to(device) if torch.is_tensor(v) else v) for k, v in inp.items()}
            with torch.no_grad():
                out = predict(module, inp)["joints_cam"].detach().float().cpu().numpy().astype(np.float64)
            for q, i in enumerate(part):
                j = out[q]
                if prev[i] is None:
                    swapped[i] = _link(j[:, 0], jobs[i][1][:, 0])
                    if swapped[i]:
                        j = j[::-1].copy()
                elif _link(j[:, 0], prev[i][:, 0]):
                    j = j[::-1].copy()
                prev[i] = j
                frames[i].append(int(b["frame"][q]))
                outs[i].append(j)
    return [(np.asarray(f, np.int64), np.stack(o), sw) for f, o, sw in zip(frames, outs, swapped)]


def estimate_export(estimator_run: str | Path, dataset_export: str | Path, out_dir: str | Path, *,
                    temporal_run: str | Path | None = None, prior_run: str | Path | None = None,
                    camera: str | None = None, device: str = "cpu", prior_window: int = 64,
                    prior_iterations: int | None = None, prior_lambda: float | None = None, progress: bool = True,
                    say: Callable[[str], None] | None = None, force: bool = False) -> dict[str, Any]:  # fmt: skip
    """Estimate both people of every rendered sequence of ``dataset_export`` with the estimator of the run
    ``estimator_run`` (then ``temporal_run``'s refinement and ``prior_run``'s test-time optimisation, when
    given) and write the result as an export under ``out_dir``; returns a summary (module docstring).

    ``camera``: the view to estimate from (default: each sequence's first rendered view). ``device``:
    ``cpu`` or ``cuda``. ``prior_window``, ``prior_iterations``: the reaction prior's windows (frames) and
    optimiser steps per window (default: the run's ``refine_iterations``). ``prior_lambda``: the prior
    term's weight (default: the run's ``lambda_prior``; choose it on a validation split). ``progress``: one line per
    sequence to ``say`` (default print). When ``out_dir`` already holds the estimate of the same runs
    (their config and last weights), the same input export and the same settings (``inputs_sha256`` in
    its manifest's ``estimation``), its summary is read back instead (``up_to_date`` true), unless
    ``force``: benches and the demo ask for the same estimate again, and a stopped bench goes on.
    DualhumanError for a run that is not an estimator (or not a
    temporal refiner / reaction prior where those are asked), an export without renders, an unknown
    camera, or ``out_dir`` equal to the input.
    """
    from dualhuman_builder.export.files import load_motion, read_manifest
    from dualhuman_builder.models.derived import derived_item, write_derived_export
    from dualhuman_builder.fileio import open_confined
    from dualhuman_builder.labels import Vocabulary
    from dualhuman_builder.models.data import actor_is_b
    from dualhuman_builder.models.images import ImageFrames
    from dualhuman_builder.models.training import load_run, resolve_device
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    for name in ("dualhuman_builder.models.lifting", "dualhuman_builder.models.temporal"):
        importlib.import_module(name)  # they register lifting-baseline and temporal-refiner
    say = say or print
    src, dst = Path(dataset_export), Path(out_dir)
    if dst.exists() and src.resolve() == dst.resolve():
        raise DualhumanError(f"refusing to write the estimate of {src} into itself", fix="give another --out folder")
    dev = resolve_device(device)
    spec, config, module = load_run(estimator_run, device=str(dev))
    predict, keys = _predictor(spec)
    module.eval()
    temporal = prior = None
    if temporal_run is not None:
        tspec, _, temporal = load_run(temporal_run, device=str(dev))
        if tspec.name != "temporal-refiner":
            raise DualhumanError(f"{temporal_run} is a run of {tspec.name!r}, not of the temporal refiner",
                                 fix="pass a run of `dualhuman train temporal-refiner` to --temporal")  # fmt: skip
    if prior_run is not None:
        pspec, _, prior = load_run(prior_run, device=str(dev))
        if pspec.name != "reaction-prior":
            raise DualhumanError(f"{prior_run} is a run of {pspec.name!r}, not of the reaction prior",
                                 fix="pass a run of `dualhuman train reaction-prior` to --prior")  # fmt: skip
        if not prior.config["use_vae"] and int(prior_window) != int(prior.config["window"]):
            raise DualhumanError(f"this prior run (without the motion VAE) codes windows of {prior.config['window']} frames",
                                 fix=f"use a prior window of {prior.config['window']}")  # fmt: skip
    p_iters = int(prior.config["refine_iterations"] if prior is not None and prior_iterations is None else prior_iterations or 0)
    if prior_lambda is not None and not (math.isfinite(prior_lambda) and prior_lambda >= 0):
        raise DualhumanError(f"the prior's weight must be a finite number >= 0, got {prior_lambda!r}", fix="use e.g. --prior-lambda 1")
    p_lambda = float(prior.config["lambda_prior"] if prior is not None and prior_lambda is None else prior_lambda or 0.0)
    key = _inputs_key(src, dev, {"estimator": estimator_run, "temporal": temporal_run, "prior": prior_run},
                      {"camera": camera, "prior_window": int(prior_window), "prior_iterations": p_iters, "prior_lambda": p_lambda})
    kept = None if force or key is None else _kept(dst, key)
    if kept is not None:
        if progress:
            say(f"{dst}: up to date (the same runs, input and settings); --force estimates again")
        return kept
    size = int(config.get("size", 64))
    ds = ImageFrames(src, "all", size=size, augment=False, views=[camera] if camera else None, cache_mb=0)
    manifest = read_manifest(src)
    fps = float(manifest["fps"])
    if prior is not None:
        from dualhuman_builder.models.reaction_prior.representation import check_fps

        check_fps(prior.config, fps, str(src))
    body = manifest.get("body_model", {})
    vocabulary = Vocabulary.from_dict(_read_json(src, manifest.get("vocabulary", {}).get("file", "labels.json")))
    stages = ["estimate", "fill"] + (["temporal"] if temporal is not None else []) + (["prior"] if prior is not None else [])
    how = {
        "estimator": str(Path(estimator_run)), "estimator_model": spec.name, "input": str(src), "image_size": size,
        "camera": camera or "each sequence's first rendered view",
        "temporal": None if temporal_run is None else str(Path(temporal_run)),
        "prior": None if prior_run is None else {"run": str(Path(prior_run)), "window": int(prior_window),
                                                   "iterations": p_iters, "lambda_prior": p_lambda,
                                                   "refined": "the reactor, given the estimated actor"},
        "stages": stages,
        "linking": "track input from the previous frame's estimated roots, then the two people assigned to the previous "
                   "frame's by the smaller total root distance",
        "identity": "the first rendered frame's estimates matched to the input's persons a and b by root distance to "
                    "the ground truth (the evaluation convention); the ground truth is used for nothing else",
        "unrendered_frames": "linearly interpolated per joint coordinate between rendered frames, held at the ends",
        "estimated": ["joints of both people", "features (from the estimated joints)",
                      "transl (the input's moved by the estimated pelvis displacement)"],
        "carried_over": ["pose and shape of both people (not estimated; they do not reproduce the estimated joints)",
                         "labels, texts, roles, subjects, splits"],
        "not_carried": ["contacts", "renders", "cameras"],
        "inputs_sha256": key,
    }  # fmt: skip
    sids = list(ds.ids)
    how["not_estimated"] = sorted(set(manifest.get("sequences", {})) - set(sids))  # no renders (of this camera)
    items, splits, per_seq = [], {}, {}
    totals: dict[str, list] = {}
    def motion(sid: str) -> dict[str, np.ndarray]:
        rel = f"sequences/{sid}/motion.npz"
        with open_confined(src, rel, f"{rel} of {src}") as f:
            return load_motion(f)

    plan = []  # per sequence: rows of its view in frame order, camera name, R, t, the first frame's truth in it
    for sid in sids:
        k = ds.ids.index(sid)
        rows = np.flatnonzero(ds.index[:, 0] == k)
        view = int(ds.index[rows, 1].min())
        rows = rows[ds.index[rows, 1] == view]
        rows = rows[np.argsort(ds.index[rows, 2], kind="stable")]
        first = ds.batch([int(rows[0])])
        cam_name = first["camera"][0]
        R, t = _camera(src, sid, cam_name)
        m = motion(sid)
        truth0 = np.stack([m["a.joints"], m["b.joints"]], axis=1)[int(first["frame"][0])].astype(np.float64)
        plan.append((rows, cam_name, R, t, truth0 @ R.T + t))
    if progress:
        say(f"estimating {sum(len(p[0]) for p in plan)} rendered frames of {len(sids)} sequences")
    views = _estimate_views(ds, [(p[0], p[4]) for p in plan], predict, keys, module, dev)
    for n, (sid, (rows, cam_name, R, t, _), (frames, est_cam, swapped)) in enumerate(zip(sids, plan, views), 1):
        m = motion(sid)  # read again: holding every sequence's motion through the batched pass would cost memory
        text = _read_json(src, f"sequences/{sid}/text.json")
        seq_doc = _read_json(src, f"sequences/{sid}/sequence.json")
        truth = np.stack([m["a.joints"], m["b.joints"]], axis=1).astype(np.float64)  # (T, 2, 22, 3)
        T = len(truth)
        est_world = (est_cam - t) @ R  # R^T (X_c - t), row vectors
        if np.any(frames < 0) or np.any(frames >= T):
            raise DualhumanError(f"{src}/sequences/{sid}: rendered frames outside the motion's {T} frames",
                                 fix="re-export the dataset")  # fmt: skip
        order = np.argsort(frames, kind="stable")
        frames, est_world = frames[order], est_world[order]
        joints = fill_frames(frames, est_world, T)  # (T, 2, 22, 3)
        rec: dict[str, Any] = {"camera": cam_name, "rendered_frames": len(frames), "filled_frames": T - len(np.unique(frames)),
                               "first_frame_swapped": swapped, "errors": {}}  # fmt: skip
        rec["errors"]["estimate_rendered"] = _errors(est_world, truth[frames])
        rec["errors"]["fill"] = _errors(joints, truth)
        if temporal is not None:
            from dualhuman_builder.models.temporal import refine_motion

            joints = np.stack([refine_motion(temporal, joints[:, p], fps, dev) for p in range(2)], axis=1)
            rec["errors"]["temporal"] = _errors(joints, truth)
        if prior is not None:
            from dualhuman_builder.models.reaction_prior.refine import refine_sequence

            r = 0 if actor_is_b(text) else 1
            refined, nw = refine_sequence(prior, joints[:, 1 - r], joints[:, r], int(prior_window), p_lambda,
                                          p_iters, float(prior.config["refine_lr"]), dev)  # fmt: skip
            joints = joints.copy()
            joints[:, r] = refined
            rec["prior_windows"], rec["reactor"] = int(nw), "ab"[r]
            rec["errors"]["prior"] = _errors(joints, truth)
        rec["errors"]["final"] = _errors(joints, truth)
        rec["errors"]["final_rendered"] = _errors(joints[frames], truth[frames])
        for key, e in rec["errors"].items():
            totals.setdefault(key, []).append((len(frames) if key.endswith("rendered") else T, e))
        tracks = {}
        for p, name in enumerate("ab"):
            est = np.ascontiguousarray(joints[:, p], dtype=np.float32)
            transl = m[f"{name}.transl"] + (est[:, 0] - m[f"{name}.joints"][:, 0])
            tr = BodyTrack(pose=m[f"{name}.pose"], transl=transl, shape=m[f"{name}.shape"], fps=fps,
                           bone_names=tuple(body.get("bone_names", ())), shape_names=tuple(body.get("shape_names", ())),
                           model=body.get("name", ""), model_version=body.get("version", ""))  # fmt: skip
            tr._store({"joints": est})
            tracks[name] = tr
            rec[f"{name}_joints_sha256"] = hashlib.sha256(est.tobytes()).hexdigest()
        seq = InteractionSequence((tracks["a"], tracks["b"]), take=seq_doc.get("take", ""),
                                  frame_range=tuple(seq_doc.get("frame_range") or (0, T)),
                                  labels=tuple(text.get("labels", [])), text=tuple(text.get("texts", [])))  # fmt: skip
        per_seq[sid] = rec
        meta = dict(seq_doc.get("meta") or {})
        meta["estimation"] = {**rec, **{k: how[k] for k in SEQUENCE_NOTES}}
        items.append(derived_item(sid, seq, seq_doc, text, meta))
        splits[sid] = manifest["sequences"][sid].get("split", "train")
        if progress:
            fe = rec["errors"]["final"]
            say(f"[{n}/{len(sids)}] {sid}: {len(frames)} rendered frames of {T} ({cam_name}); MPJPE {fe['mpjpe_mm']:.1f} mm, "
                f"PA-MPJPE {fe['pa_mpjpe_mm']:.1f} mm, translation {fe['translation_mm']:.1f} mm")  # fmt: skip

    def mean(key: str) -> dict[str, float]:
        w = sum(c for c, _ in totals[key])
        return {name: sum(c * e[name] for c, e in totals[key]) / w for name in totals[key][0][1]}

    figures = {key: mean(key) for key in totals}
    summary = {**how, "sequences": len(items), "frames": int(sum(c for c, _ in totals["fill"])),
               "rendered_frames": int(sum(c for c, _ in totals["estimate_rendered"])), "errors": figures,
               "per_sequence": per_seq}  # fmt: skip
    write_derived_export(items, dst, manifest, vocabulary, splits,
                         {"estimation": {k: v for k, v in summary.items() if k != "per_sequence"}})
    summary["out"], summary["up_to_date"] = str(dst), False
    if progress:
        f = figures["final"]
        say(f"estimated {len(items)} sequences ({summary['rendered_frames']} rendered frames, {summary['frames']} in all; "
            f"stages {' -> '.join(stages)}): MPJPE {f['mpjpe_mm']:.1f} mm, PA-MPJPE {f['pa_mpjpe_mm']:.1f} mm, "
            f"translation {f['translation_mm']:.1f} mm; {dst}")  # fmt: skip
    return summary


def _inputs_key(src: Path, dev: torch.device, run_dirs: dict[str, Any], settings: dict[str, Any]) -> str | None:
    """SHA-256 of what an estimate depends on: the toolkit's version, the device type, the input export's
    manifest (which records every file's SHA-256), each run's config and last weights' SHA-256, and
    ``settings``; None when the input has no manifest (the estimate then says what is wrong)."""
    from dualhuman_builder import __version__
    from dualhuman_builder.models import runs

    def run_digest(run: Any) -> Any:
        if run is None:
            return None
        last = runs.read_json(Path(run) / runs.CHECKPOINTS / runs.LAST, "the checkpoint record")
        return [hashlib.sha256((Path(run) / runs.CONFIG).read_bytes()).hexdigest(), last.get("weights_sha256")]

    try:
        manifest = (src / "manifest.json").read_bytes()
    except OSError:
        return None
    doc = {"version": __version__, "device": dev.type, "settings": settings, "input": hashlib.sha256(manifest).hexdigest(),
           "runs": {k: run_digest(r) for k, r in run_dirs.items()}}  # fmt: skip
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def _kept(dst: Path, key: str) -> dict[str, Any] | None:
    """The summary of the estimate in ``dst`` when its manifest records inputs ``key`` and every estimated
    sequence's ``sequence.json`` is there; else None (estimate again)."""
    try:
        doc = json.loads((dst / "manifest.json").read_text())
        est = doc.get("estimation") or {}
        if est.get("inputs_sha256") != key:
            return None
        per_seq = {}
        for sid in doc.get("sequences", {}):
            meta = json.loads((dst / "sequences" / sid / "sequence.json").read_text()).get("meta", {}).get("estimation")
            per_seq[sid] = {k: v for k, v in meta.items() if k not in SEQUENCE_NOTES}
    except (OSError, ValueError, AttributeError, TypeError):
        return None
    return {**est, "per_sequence": per_seq, "out": str(dst), "up_to_date": True}


__all__ = ["ESTIMATORS", "estimate_export", "fill_frames"]
