"""Test-time optimisation with the reaction prior (paper §3.1 Eq. 5, §3.2): refine a noisy reactor.

Per window of ``L`` frames (the paper's L = 64), in the actor's window frame (:mod:`.representation`),
the reactor's code ``(mu_r, sigma_r)`` starts at the encoding of the noisy reactor ``x^_r`` and is
optimised (Adam, ``iterations`` steps, the step size cosine-annealed from ``lr`` to ``lr / 100``: Adam's
steps are about ``lr`` whatever the gradient, so a constant one keeps circling the optimum) to minimise

    || D(mu_r) - x^_r ||^2  +  lambda_prior * KL[ N(mu_r, sigma_r) || G(E(x^_a)) ]

where the data term is the sum of squared differences over the window in the model's normalised
units (each number of its representation, joint coordinates or the paper's features, scaled by its
training deviation), ``D``
decodes the mean (a deterministic decode; sigma enters through the KL), ``G(E(x^_a))`` is the prior the
generator gives from the actor's encoding, and the KL is summed over the code's dimensions (nats);
``lambda_prior = 0.01`` as in the paper. The result is ``D(mu_r)`` back in the world frame.

Windows start every ``L/2`` frames, and a last one ends on the sequence's last frame; a sequence
shorter than ``L`` is padded by repeating its last frame and cropped after. **Blend**: each frame's
result is the weighted mean of the windows that cover it, with triangular weights ``min(t + 1, L - t)``
(t the frame's index in its window), so a window's edges, where it knows least of the motion around
them, count least, and consecutive windows cross-fade without a seam.

:func:`refine_export` applies this to every sequence of an export and writes the refined export.
"""

from __future__ import annotations

import hashlib
import json
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.models.reaction_prior.noise import corrupt
from dualhuman_builder.models.reaction_prior.representation import canonical_pair, check_fps, to_world
from dualhuman_builder.models.reaction_prior.noise import noise_model
from dualhuman_builder.models.reaction_prior.vae import kl_gauss

#: Windows optimised together (memory: a few MB per window with the CPU-sized VAE).
CHUNK_WINDOWS = 64


def window_starts(T: int, L: int) -> list[int]:
    """Window starts over ``T`` frames: every ``L // 2``, plus one ending on the last frame."""
    if T <= L:
        return [0]
    step = max(1, L // 2)
    starts = list(range(0, T - L + 1, step))
    if starts[-1] + L < T:
        starts.append(T - L)
    return starts


def blend_weights(L: int) -> np.ndarray:
    """``(L,)`` triangular weights ``min(t + 1, L - t)`` of a window's frames (module docstring)."""
    t = np.arange(L)
    return np.minimum(t + 1, L - t).astype(np.float64)


def refine_windows(module, actor: torch.Tensor, noisy: torch.Tensor, lambda_prior: float = 0.01,
                   iterations: int = 100, lr: float = 0.05, terms: dict[str, float] | None = None) -> torch.Tensor:  # fmt: skip
    """Refined reactor windows ``(N, L, 22, 3)`` world metres from the actor's ``actor (N, L, 22, 3)``
    and the noisy reactor's ``noisy`` (same shape), by Eq. 5 (module docstring). The module's weights
    are not changed (gradients are taken with respect to the code only). ``terms``: if given, the
    last step's data term and weighted prior term (``lambda_prior * KL``), summed over the windows,
    are added to its ``"data"`` and ``"prior"`` (how much the prior weighs in the objective)."""
    was = module.training
    module.eval()
    try:
        with torch.no_grad():
            ca, cr, origin, yaw = canonical_pair(actor.float(), noisy.float())
            mu0, ls0 = module.encode(cr)
            pm, pl = module.react(*module.encode(ca))
        mu, ls = mu0.clone().requires_grad_(True), ls0.clone().requires_grad_(True)
        if iterations > 0:
            opt = torch.optim.Adam([mu, ls], lr=lr)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, int(iterations), eta_min=lr * 0.01)
            with torch.enable_grad():
                target = module.norm(module.rows(cr))
                for _ in range(int(iterations)):
                    data = (module.decode_rows(mu, cr.shape[1]) - target).square().sum(dim=(1, 2))
                    prior = kl_gauss(mu, ls, pm, pl).sum(-1)
                    loss = (data + lambda_prior * prior).sum()
                    opt.zero_grad(set_to_none=True)
                    mu.grad, ls.grad = torch.autograd.grad(loss, [mu, ls])
                    opt.step()
                    sched.step()
                if terms is not None:
                    terms["data"] = terms.get("data", 0.0) + float(data.detach().sum())
                    terms["prior"] = terms.get("prior", 0.0) + float(lambda_prior * prior.detach().sum())
        with torch.no_grad():
            return to_world(module.decode(mu.detach(), cr.shape[1]), origin, yaw)
    finally:
        module.train(was)


def refine_sequence(module, actor: np.ndarray, noisy: np.ndarray, window: int = 64, lambda_prior: float = 0.01,
                    iterations: int = 100, lr: float = 0.05,
                    device: str | torch.device = "cpu") -> tuple[np.ndarray, int]:  # fmt: skip
    """Refined reactor ``(T, 22, 3)`` float32 world metres of one sequence, and the number of windows,
    from the actor's joints and the noisy reactor's (both ``(T, 22, 3)``), windowed and blended as
    the module docstring says."""
    return refine_sequences(module, [(actor, noisy)], window, lambda_prior, iterations, lr, device)[0]


def refine_sequences(module, pairs: list[tuple[np.ndarray, np.ndarray]], window: int = 64,
                     lambda_prior: float = 0.01, iterations: int = 100, lr: float = 0.05,
                     device: str | torch.device = "cpu",
                     terms: dict[str, float] | None = None) -> list[tuple[np.ndarray, int]]:  # fmt: skip
    """:func:`refine_sequence` of each ``(actor, noisy)`` pair, the windows of every sequence optimised
    together in chunks of :data:`CHUNK_WINDOWS`: each window's code has its own loss term and Adam
    moments, so a window's result does not depend on its chunk, and pooling short sequences saves
    the per-step overhead of many small batches. ``terms``: as :func:`refine_windows` takes it."""
    L = int(window)
    padded, todo = [], []  # todo: (sequence index, window start)
    for i, (actor, noisy) in enumerate(pairs):
        a, r = np.asarray(actor, np.float32), np.asarray(noisy, np.float32)
        if a.shape != r.shape or a.ndim != 3:
            raise ValueError(f"sequence {i}: actor {a.shape} and noisy reactor {r.shape} must both be (T, 22, 3)")
        if len(a) < L:  # pad with the last frame, crop after
            a = np.concatenate([a, np.repeat(a[-1:], L - len(a), axis=0)])
            r = np.concatenate([r, np.repeat(r[-1:], L - len(r), axis=0)])
        padded.append((a, r))
        todo += [(i, s) for s in window_starts(len(a), L)]
    acc = [np.zeros(a.shape, np.float64) for a, _ in padded]
    wsum = [np.zeros(len(a), np.float64) for a, _ in padded]
    w = blend_weights(L)
    for c0 in range(0, len(todo), CHUNK_WINDOWS):
        chunk = todo[c0 : c0 + CHUNK_WINDOWS]
        wa = torch.from_numpy(np.stack([padded[i][0][s : s + L] for i, s in chunk])).to(device)
        wr = torch.from_numpy(np.stack([padded[i][1][s : s + L] for i, s in chunk])).to(device)
        out = refine_windows(module, wa, wr, lambda_prior, iterations, lr, terms).cpu().numpy().astype(np.float64)
        for (i, s), o in zip(chunk, out):
            acc[i][s : s + L] += w[:, None, None] * o
            wsum[i][s : s + L] += w
    counts = [0] * len(pairs)
    for i, _ in todo:
        counts[i] += 1
    return [((acc[i] / wsum[i][:, None, None])[: len(pairs[i][0])].astype(np.float32), counts[i])
            for i in range(len(pairs))]  # fmt: skip


def _seq_seed(seed: int, sid: str) -> int:
    return (int(seed) * 1_000_003 + zlib.crc32(sid.encode())) % (2**63)


def corrupt_sequence(joints: np.ndarray, visibility: np.ndarray, config: dict[str, Any], seed: int,
                     sid: str) -> np.ndarray:  # fmt: skip
    """``joints (T, 22, 3)`` corrupted by the config's visibility-driven noise (:mod:`.noise`), drawn
    from a generator seeded by ``seed`` and the sequence id (the same call gives the same noise)."""
    g = torch.Generator().manual_seed(_seq_seed(seed, sid))
    j = torch.from_numpy(np.asarray(joints, np.float32))[None]
    v = torch.from_numpy(np.asarray(visibility, np.float32))[None]
    return corrupt(j, v, noise_model(config), generator=g)[0].numpy()


def _errors(pred: np.ndarray, true: np.ndarray) -> dict[str, float]:
    """Joint error (absolute, mm), root-relative MPJPE (mm) and root error (mm) of ``(T, 22, 3)`` arrays."""
    d = pred - true
    rel = (pred - pred[:, :1]) - (true - true[:, :1])
    return {"joint_error_mm": float(np.linalg.norm(d, axis=-1).mean() * 1000),
            "mpjpe_mm": float(np.linalg.norm(rel, axis=-1).mean() * 1000),
            "root_error_mm": float(np.linalg.norm(d[:, 0], axis=-1).mean() * 1000)}  # fmt: skip


def _read_json(folder: Path, rel: str) -> Any:
    from dualhuman_builder.fileio import read_confined

    return json.loads(read_confined(folder, rel, 64 * 2**20, f"{rel} of {folder}").decode("utf-8"))


def _motion(folder: Path, sid: str) -> dict[str, np.ndarray]:
    from dualhuman_builder.export.files import load_motion
    from dualhuman_builder.fileio import open_confined

    rel = f"sequences/{sid}/motion.npz"
    with open_confined(folder, rel, f"{rel} of {folder}") as f:
        return load_motion(f)


def refine_export(run_dir: str | Path, export_dir: str | Path, out_dir: str | Path, *, window: int = 64,
                  lambda_prior: float = 0.01, iterations: int | None = None, device: str = "cpu", progress: bool = True,
                  noisy_from: str | Path | None = None, seed: int = 0, lr: float | None = None,
                  say: Callable[[str], None] | None = None) -> dict[str, Any]:  # fmt: skip
    """Refine the reactor of every sequence of the export ``export_dir`` with the reaction prior of the
    training run ``run_dir``, and write the result as an export under ``out_dir``; returns a summary.

    The noisy reactor is the reactor of ``noisy_from`` (another export of the same sequences, e.g. an
    estimator's output) when given; otherwise the export's reactor corrupted by the visibility-driven
    noise of the run's config (:mod:`.noise`), seeded by ``seed`` and the sequence id. The actor is
    the export's. ``window``, ``lambda_prior``, ``iterations``, ``lr``: the optimisation (module
    docstring; ``iterations`` and ``lr`` default to the run's ``refine_iterations`` and ``refine_lr``).
    ``progress``: one line per sequence (to ``say``, default print).

    The written export (`dualhuman export verify` accepts it) has the input's sequences, splits,
    labels, texts and roles. Person by person, ``motion.npz``: the actor's arrays are the input's; the
    reactor's ``joints`` are the refined joints, its ``features`` are computed from them, its ``transl``
    is the input's moved by the refined pelvis's displacement from the input's pelvis, and its
    ``pose`` and ``shape`` are the input's, carried over unchanged (they are not refined and do not
    reproduce the refined joints). Contacts and renders describe the input bodies and are not carried
    over. Each ``sequence.json`` ``meta.refinement`` and the manifest's ``refinement`` say all this,
    with the noise source and the figures before and after (against the input export's reactor).
    """
    from dualhuman_builder.export.files import read_manifest
    from dualhuman_builder.models.derived import derived_item, write_derived_export
    from dualhuman_builder.labels import Vocabulary
    from dualhuman_builder.models.data import actor_is_b
    from dualhuman_builder.models.training import load_run
    from dualhuman_builder.models.visibility import joint_visibility
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    say = say or print
    src, dst = Path(export_dir), Path(out_dir)
    if src.resolve() == dst.resolve():
        raise DualhumanError(f"refusing to refine {src} into itself", fix="give another --out folder")
    spec, _, module = load_run(run_dir, device=device)
    if getattr(spec, "name", None) != "reaction-prior":
        raise DualhumanError(f"{run_dir} is a run of {getattr(spec, 'name', '?')!r}, not of the reaction prior",
                             fix="pass a run of `dualhuman train reaction-prior`")  # fmt: skip
    cfg = module.config
    iterations = int(cfg["refine_iterations"] if iterations is None else iterations)
    lr = float(cfg["refine_lr"] if lr is None else lr)
    if not cfg["use_vae"] and int(window) != int(cfg["window"]):
        raise DualhumanError(f"this run (without the motion VAE) codes windows of {cfg['window']} frames, not {window}",
                             fix=f"use --window {cfg['window']}")  # fmt: skip
    manifest = read_manifest(src)
    check_fps(cfg, float(manifest["fps"]), str(src))
    noisy_dir = Path(noisy_from) if noisy_from is not None else None
    noisy_manifest = read_manifest(noisy_dir) if noisy_dir is not None else None
    body = manifest.get("body_model", {})
    vocabulary = Vocabulary.from_dict(_read_json(src, manifest.get("vocabulary", {}).get("file", "labels.json")))
    fps = float(manifest["fps"])
    how = {
        "run": str(Path(run_dir)), "input": str(src), "window": int(window), "overlap": int(window) // 2,
        "blend": "triangular weights min(t + 1, L - t)", "lambda_prior": float(lambda_prior),
        "iterations": int(iterations), "lr": float(lr),
        "noisy_reactor": (f"the reactor of {noisy_dir}" if noisy_dir is not None else
                          f"the input's reactor corrupted by visibility-driven noise, seed {int(seed)}"),
        "noise": None if noisy_dir is not None else noise_model(cfg).as_dict(),
        "refined": ["reactor joints", "reactor features (from the refined joints)",
                    "reactor transl (moved by the refined pelvis displacement)"],
        "carried_over": ["actor: every array of the input", "reactor pose and shape of the input (not refined)",
                         "labels, texts, roles, subjects, splits"],
        "not_carried": ["contacts", "renders", "cameras"],
    }  # fmt: skip
    items, splits, per_seq = [], {}, {}
    totals = {"before": [], "after": []}
    n_windows = 0
    for k, (sid, info) in enumerate(sorted(manifest["sequences"].items()), 1):
        m = _motion(src, sid)
        text = _read_json(src, f"sequences/{sid}/text.json")
        seq_doc = _read_json(src, f"sequences/{sid}/sequence.json")
        r = "a" if actor_is_b(text) else "b"
        a = "b" if r == "a" else "a"
        truth = m[f"{r}.joints"].astype(np.float32)
        if noisy_dir is not None:
            if sid not in noisy_manifest.get("sequences", {}):
                raise DualhumanError(f"{noisy_dir} has no sequence {sid!r}", fix="pass an export of the same sequences")
            noisy = _motion(noisy_dir, sid)[f"{r}.joints"].astype(np.float32)
            if noisy.shape != truth.shape:
                raise DualhumanError(f"{noisy_dir}: sequence {sid!r} has {len(noisy)} frames, {src} {len(truth)}",
                                     fix="pass an export of the same sequences and frames")  # fmt: skip
        else:
            vis = joint_visibility(m["a.joints"], m["b.joints"])
            noisy = corrupt_sequence(truth, vis[0] if r == "a" else vis[1], cfg, seed, sid)
        refined, nw = refine_sequence(module, m[f"{a}.joints"], noisy, window, lambda_prior, iterations, lr, device)
        n_windows += nw
        before, after = _errors(noisy, truth), _errors(refined, truth)
        totals["before"].append((len(truth), before))
        totals["after"].append((len(truth), after))
        transl = m[f"{r}.transl"] + (refined[:, 0] - truth[:, 0])
        tracks = {}
        for p in ("a", "b"):
            t = BodyTrack(pose=m[f"{p}.pose"], transl=transl if p == r else m[f"{p}.transl"], shape=m[f"{p}.shape"],
                          fps=fps, bone_names=tuple(body.get("bone_names", ())),
                          shape_names=tuple(body.get("shape_names", ())), model=body.get("name", ""),
                          model_version=body.get("version", ""))  # fmt: skip
            t._store({"joints": np.ascontiguousarray(refined if p == r else m[f"{p}.joints"], dtype=np.float32)})
            tracks[p] = t
        seq = InteractionSequence((tracks["a"], tracks["b"]), take=seq_doc.get("take", ""),
                                  frame_range=tuple(seq_doc.get("frame_range") or (0, len(truth))),
                                  labels=tuple(text.get("labels", [])), text=tuple(text.get("texts", [])))  # fmt: skip
        rec = {"reactor": r, "windows": nw, "before": before, "after": after,
               "joints_sha256": hashlib.sha256(refined.tobytes()).hexdigest()}  # fmt: skip
        per_seq[sid] = rec
        meta = dict(seq_doc.get("meta") or {})
        meta["refinement"] = {**rec, "refined": how["refined"], "carried_over": how["carried_over"]}
        items.append(derived_item(sid, seq, seq_doc, text, meta))
        splits[sid] = info.get("split", "train")
        if progress:
            say(f"[{k}/{len(manifest['sequences'])}] {sid}: {nw} windows, joint error "
                f"{before['joint_error_mm']:.1f} -> {after['joint_error_mm']:.1f} mm")  # fmt: skip

    def mean(which: str) -> dict[str, float]:
        n = sum(t for t, _ in totals[which])
        return {key: sum(t * e[key] for t, e in totals[which]) / n for key in totals[which][0][1]}

    summary = {**how, "sequences": len(items), "windows": n_windows, "frames": int(sum(t for t, _ in totals["before"])),
               "before": mean("before"), "after": mean("after"), "per_sequence": per_seq}  # fmt: skip
    write_derived_export(items, dst, manifest, vocabulary, splits,
                         {"refinement": {k: v for k, v in summary.items() if k != "per_sequence"}})
    summary["out"] = str(dst)
    if progress:
        b, f = summary["before"], summary["after"]
        say(f"refined {len(items)} sequences ({n_windows} windows): joint error {b['joint_error_mm']:.1f} -> "
            f"{f['joint_error_mm']:.1f} mm, MPJPE {b['mpjpe_mm']:.1f} -> {f['mpjpe_mm']:.1f} mm, root "
            f"{b['root_error_mm']:.1f} -> {f['root_error_mm']:.1f} mm; {dst}")  # fmt: skip
    return summary
