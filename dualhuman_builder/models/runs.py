"""The run folder of a training run: what :func:`~dualhuman_builder.models.training.train` writes and
:func:`~dualhuman_builder.models.training.load_run` reads.

```
RUN/ config.json        model name, merged model config, training options, the export's manifest digest,
                        toolkit and torch versions (a resume must match it)
     metrics.jsonl      one JSON object per optimiser step: phase, step, losses, lr, windows/s, loader share
     checkpoints/       last.json (phase, step, files, their SHA-256, the optimiser's scalar state),
                        model-<step>.safetensors, optimizer-<step>.safetensors; last.safetensors: the
                        latest weights under a fixed name (a hard link or copy of model-<step>)
     summary.json       what was trained on, steps, final losses, time, windows/s, loader share
     README.md          the same for a person
     curves.png         the losses of every phase against the step
     eval-<split>.json  figures of `dualhuman evaluate`
     tensorboard/       event files, when TensorBoard is installed (optional)
```

Checkpoints are crash-safe: the step's weights and optimiser files are written first (each
atomically, under names carrying the step), then ``last.json`` is replaced atomically to point at
them, and only then are older step files removed; a crash at any moment leaves ``last.json``
naming a complete, checksummed pair. Nothing is pickled: tensors go to ``safetensors``, the rest to JSON.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import torch

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.fileio import atomic_open, atomic_path, sha256_file

CONFIG = "config.json"
METRICS = "metrics.jsonl"
CHECKPOINTS = "checkpoints"
LAST = "last.json"
LAST_WEIGHTS = "last.safetensors"
SUMMARY = "summary.json"
README = "README.md"
CURVES = "curves.png"


def write_json(path: Path, obj: Any) -> None:
    """``obj`` as indented JSON at ``path``, atomically."""
    with atomic_open(path, "w", encoding="utf-8") as f:
        f.write(json.dumps(obj, indent=1, sort_keys=False, allow_nan=False) + "\n")


def read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DualhumanError(f"{path} does not exist: {what} missing", fix="pass a run folder `dualhuman train` wrote") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DualhumanError(f"{path} is not valid JSON ({e})", fix="pass a run folder `dualhuman train` wrote") from None
    if not isinstance(doc, dict):
        raise DualhumanError(f"{path} is not a JSON object", fix="pass a run folder `dualhuman train` wrote")
    return doc


def differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    """Dotted key paths where two JSON values differ (``config.window: 64 -> 32``)."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: list[str] = []
        for k in sorted(set(old) | set(new), key=str):
            where = f"{prefix}.{k}" if prefix else str(k)
            if k not in old:
                out.append(f"{where}: (absent) -> {json.dumps(new[k])[:60]}")
            elif k not in new:
                out.append(f"{where}: {json.dumps(old[k])[:60]} -> (absent)")
            else:
                out.extend(differences(old[k], new[k], where))
        return out
    if old != new:
        return [f"{prefix}: {json.dumps(old)[:60]} -> {json.dumps(new)[:60]}"]
    return []


# ------------------------------------------------------------------ checkpoints
def _tensors(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """CPU, contiguous, unshared copies (safetensors refuses tensors that share memory)."""
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in state.items()}


def _save_tensors(path: Path, tensors: dict[str, torch.Tensor], meta: dict[str, str]) -> None:
    from safetensors.torch import save_file

    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def optimizer_state(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """An optimiser's state as ``(tensors, json)``: every tensor of its per-parameter state under
    ``state.<index>.<name>``, and the scalars and ``param_groups`` as JSON."""
    sd = opt.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for idx, st in sd["state"].items():
        for name, value in st.items():
            if isinstance(value, torch.Tensor):
                tensors[f"state.{idx}.{name}"] = value
            else:
                scalars.setdefault(str(idx), {})[name] = value
    groups = [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in sd["param_groups"]]
    return _tensors(tensors), {"param_groups": groups, "scalars": scalars}


def restore_optimizer(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], doc: dict[str, Any]) -> None:
    """Load what :func:`optimizer_state` saved into ``opt`` (built over the same parameters)."""
    state: dict[int, dict[str, Any]] = {}
    for key, value in tensors.items():
        _, idx, name = key.split(".", 2)
        state.setdefault(int(idx), {})[name] = value
    for idx, scalars in doc.get("scalars", {}).items():
        state.setdefault(int(idx), {}).update(scalars)
    groups = [{k: (tuple(v) if k == "betas" else v) for k, v in g.items()} for g in doc["param_groups"]]
    opt.load_state_dict({"state": state, "param_groups": groups})


def save_checkpoint(run_dir: Path, module: torch.nn.Module, opt: torch.optim.Optimizer | None, info: dict[str, Any]) -> None:
    """Write the step's weights and optimiser state, then ``last.json`` (``info`` plus the file names
    and their SHA-256), then ``last.safetensors``; then remove older step files."""
    folder = Path(run_dir) / CHECKPOINTS
    folder.mkdir(parents=True, exist_ok=True)
    step = int(info["global_step"])
    meta = {"phase": str(info["phase"]), "global_step": str(step)}
    weights, optim = f"model-{step:09d}.safetensors", f"optimizer-{step:09d}.safetensors"
    _save_tensors(folder / weights, _tensors(module.state_dict()), meta)
    doc = dict(info, weights=weights, weights_sha256=sha256_file(folder / weights))
    if opt is not None:
        tensors, opt_doc = optimizer_state(opt)
        _save_tensors(folder / optim, tensors, meta)
        doc.update(optimizer=optim, optimizer_sha256=sha256_file(folder / optim), optimizer_state=opt_doc)
    else:
        doc.update(optimizer=None)
    write_json(folder / LAST, doc)
    tmp = folder / f".{LAST_WEIGHTS}.{os.getpid()}.link"
    tmp.unlink(missing_ok=True)
    try:
        os.link(folder / weights, tmp)
        os.replace(tmp, folder / LAST_WEIGHTS)
    except OSError:
        tmp.unlink(missing_ok=True)
        with atomic_path(folder / LAST_WEIGHTS) as t:
            t.write_bytes((folder / weights).read_bytes())
    keep = {weights, optim, LAST, LAST_WEIGHTS}
    for p in folder.iterdir():
        if p.name not in keep and p.suffix == ".safetensors" and p.name.startswith(("model-", "optimizer-")):
            p.unlink(missing_ok=True)


def load_checkpoint(run_dir: Path, device: str | torch.device = "cpu", optimizer: bool = True) -> tuple[dict, dict, dict | None]:
    """``(last.json, model tensors, optimizer tensors or None)`` of the run's latest checkpoint, each
    file checked against the SHA-256 ``last.json`` records."""
    from safetensors.torch import load_file

    folder = Path(run_dir) / CHECKPOINTS
    doc = read_json(folder / LAST, "the checkpoint record")
    out = []
    for key in ("weights", "optimizer") if optimizer else ("weights",):
        name = doc.get(key)
        if name is None:
            out.append(None)
            continue
        path = folder / str(name)
        if not isinstance(name, str) or "/" in name or not path.is_file() or sha256_file(path) != doc.get(f"{key}_sha256"):
            raise DualhumanError(f"{path}: missing or not the file {LAST} records",
                                 fix=f"restore the run folder, or remove {folder} to train from the start")  # fmt: skip
        out.append(load_file(str(path), device=str(device)))
    return doc, out[0], out[1] if optimizer else None


# ------------------------------------------------------------------ metrics, curves, summary
def read_metrics(run_dir: Path) -> list[dict[str, Any]]:
    """The step records of ``metrics.jsonl`` (a torn last line, from a crash, is left out)."""
    path = Path(run_dir) / METRICS
    if not path.is_file():
        return []
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict):
            out.append(rec)
    return out


def keep_metrics_until(run_dir: Path, step: int) -> None:
    """Drop the records after global step ``step`` (steps a resume will train again)."""
    path = Path(run_dir) / METRICS
    if not path.is_file():
        return
    keep = [json.dumps(r) for r in read_metrics(run_dir) if int(r.get("step", 0)) <= step]
    with atomic_open(path, "w", encoding="utf-8") as f:
        f.write("".join(line + "\n" for line in keep))


#: Keys of a step record that are not losses.
RECORD_KEYS = ("phase", "step", "phase_step", "lr", "windows_per_s", "loader_share", "step_s", "time_s")


def loss_names(records: list[dict[str, Any]]) -> list[str]:
    """The losses logged in ``records``, ``loss`` first."""
    names = dict.fromkeys(n for r in records[:5] for n in r if n not in RECORD_KEYS)
    return sorted(names, key=lambda n: (n != "loss", n))


def plot_curves(run_dir: Path, records: list[dict[str, Any]]) -> Path | None:
    """``curves.png``: one panel per phase, every logged loss against the global step (log scale when
    all positive), smoothed over 1 % of the steps with the raw values faint behind. None without records."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    phases: dict[str, list[dict]] = {}
    for r in records:
        phases.setdefault(str(r.get("phase")), []).append(r)
    if not phases:
        return None
    fig = Figure(figsize=(5.0 * len(phases), 3.6), dpi=110)
    FigureCanvasAgg(fig)
    for k, (phase, recs) in enumerate(phases.items()):
        ax = fig.add_subplot(1, len(phases), k + 1)
        steps = [int(r["step"]) for r in recs]
        names = loss_names(recs)
        positive = True
        for name in names:
            ys = [float(r.get(name, math.nan)) for r in recs]
            positive &= all(y > 0 for y in ys if math.isfinite(y))
            w = max(1, len(ys) // 100)
            smooth = [sum(ys[max(0, i - w + 1): i + 1]) / len(ys[max(0, i - w + 1): i + 1]) for i in range(len(ys))]
            line = ax.plot(steps, smooth, label=name, lw=1.4)[0]
            if w > 1:
                ax.plot(steps, ys, color=line.get_color(), alpha=0.2, lw=0.6)
        if positive:
            ax.set_yscale("log")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(f"phase {phase}")
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = Path(run_dir) / CURVES
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def summarise(records: list[dict[str, Any]], tail: int = 20) -> dict[str, Any]:
    """Per phase: steps, the mean of each loss over the last ``tail`` steps, median windows/s and mean
    loader share (both without the first two steps of the phase, which warm caches up)."""
    out: dict[str, Any] = {}
    phases: dict[str, list[dict]] = {}
    for r in records:
        phases.setdefault(str(r.get("phase")), []).append(r)
    for phase, recs in phases.items():
        last = recs[-tail:]
        names = loss_names(recs)
        timed = recs[2:] or recs
        wps = sorted(float(r.get("windows_per_s", 0.0)) for r in timed)
        out[phase] = {
            "steps": len(recs),
            "final": {n: sum(float(r[n]) for r in last if n in r) / max(1, sum(n in r for r in last)) for n in names},
            "windows_per_s": wps[len(wps) // 2] if wps else None,
            "loader_share": sum(float(r.get("loader_share", 0.0)) for r in timed) / max(1, len(timed)),
        }
    return out


def write_readme(run_dir: Path, summary: dict[str, Any]) -> None:
    """``README.md``: the run in words, from ``summary``."""
    s = summary
    lines = [
        f"# Training run: {s['model']}",
        "",
        (f"Trained with dualhuman_builder {s['toolkit_version']} (torch {s['torch_version']}) on {s['device']}"
         f"{' with bf16 mixed precision' if s['amp'] else ''}, seed {s['seed']}, batch {s['batch_size']} windows "
         f"of {s['window']} frames."),
        "",
        (f"Data: `{s['export']['path']}` (manifest SHA-256 `{s['export']['manifest_sha256'][:16]}...`), split "
         f"`train`: {s['data']['sequences']} sequences, {s['data']['windows']} items"
         + (f", {s['data']['frames']} frames" if s['data'].get('frames') is not None else "")
         + (f"; {len(s['data']['swapped'])} with person b as the actor" if s['data'].get('swapped') is not None else "")
         + (f", {len(s['data']['too_short'])} shorter than a window (left out)" if s['data'].get('too_short') is not None
            else "") + "."),
        "",
        f"Status: {s['status']}, {s['global_step']} of {s['total_steps']} steps, {s['time_s']:.1f} s of training.",
        "",
        "| phase | steps | final loss | windows/s | loader share |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, p in s["phases"].items():
        wps = f"{p['windows_per_s']:.1f}" if p.get("windows_per_s") else "-"
        loss = p.get("final", {}).get("loss")
        lines.append(f"| {name} | {p['steps']} | {'-' if loss is None else f'{loss:.4g}'} | {wps} | "
                     f"{100 * p.get('loader_share', 0.0):.1f} % |")  # fmt: skip
    lines += [
        "",
        ("Final losses: the mean over the phase's last 20 steps. Windows/s: the median over the phase's steps; loader "
         "share: the part of a step spent waiting for its batch (reading, collating, moving to the device)."),
        "",
        ("Files: `config.json` (what a resume must match), `metrics.jsonl` (every step), `curves.png`, "
         "`checkpoints/last.safetensors` (the weights), `checkpoints/last.json`, `summary.json`."),
        "",
        "Continue an interrupted run with the same command; evaluate with `dualhuman evaluate RUN DATASET`.",
        "",
    ]
    with atomic_open(Path(run_dir) / README, "w", encoding="utf-8") as f:
        f.write("\n".join(lines))
