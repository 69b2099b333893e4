"""The training loop every bundled model shares: :func:`train`, :func:`load_run`, :func:`evaluate`.

A model is a :class:`~dualhuman_builder.models.base.ModelSpec`; the loop owns the rest. It reads the
export's train split as :class:`~dualhuman_builder.models.data.InteractionWindows` (the config's
``window``, ``stride``, ``cameras`` and ``visibility`` when the model has them; 64 frames, half-window
stride, 8 cameras and visibility otherwise), runs every phase of the spec in order with one AdamW per
phase (the phase's ``lr`` and ``weight_decay``; the other parameters frozen), and writes the run folder
of :mod:`~dualhuman_builder.models.runs`.

**Reproducible and resumable.** The weights are drawn after seeding torch, numpy and Python's random
with ``seed``; before every step the three are seeded again from ``(seed, step)`` and the step's batch
is drawn from a permutation of the windows seeded by ``(seed, phase, epoch)``. So a run stopped and
resumed from its last checkpoint continues with the very batches and random draws the uninterrupted
run would have used and ends with the same weights (on the CPU; GPU kernels may differ in the last bits).
A run folder that exists is resumed when its ``config.json`` matches (model, config, batch size,
seed, steps scale, the export's manifest digest) and refused, naming what differs, otherwise.

**Devices.** ``device="cpu"`` or ``"cuda"`` (``"cuda:N"``); mixed precision (``amp``, bf16 autocast
of the forward pass and losses, no loss scaling needed) is on by default on a GPU and off on the CPU.

**Speed figures.** Every step logs windows/s and the loader's share of the step: the time spent
getting the batch (indexing, collating, moving it to the device) over the whole step's time (with
the GPU synchronised at the step's end, so the share is not hidden in asynchronous kernels).
"""

from __future__ import annotations

import json
import math
import random
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.models import runs
from dualhuman_builder.models.base import INIT_KEYS, ModelSpec, Phase, get_model
from dualhuman_builder.models.data import InteractionWindows

#: Defaults of the data options a model's config may set.
DATA_DEFAULTS = {"window": 64, "stride": None, "cameras": 8, "visibility": True}
#: Seconds between checkpoints within a phase (one is also written at every phase's end and on Ctrl-C).
CHECKPOINT_SECONDS = 600.0


# ------------------------------------------------------------------ options
def resolve_device(device: str | torch.device) -> torch.device:
    """``cpu``, ``cuda`` or ``cuda:N`` as a torch device; DualhumanError when CUDA is asked for and absent."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise DualhumanError(f"unknown device {device!r} ({e})", fix="use --device cpu or --device cuda") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise DualhumanError("--device cuda was asked for, but torch sees no CUDA GPU on this machine",
                                 fix="use --device cpu, or install a CUDA build of torch on a machine with an NVIDIA GPU")  # fmt: skip
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise DualhumanError(f"{dev} does not exist: {torch.cuda.device_count()} GPU(s)", fix="use --device cuda")
    elif dev.type != "cpu":
        raise DualhumanError(f"device {device!r} is not supported", fix="use --device cpu or --device cuda")
    return dev


def parse_set(values: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """``key=value`` strings (the CLI's ``--set``) as overrides; the value is JSON when it parses
    (``3``, ``1e-4``, ``true``, ``[2, 3]``), else the string itself."""
    out: dict[str, Any] = {}
    for item in values:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise DualhumanError(f"--set {item!r} is not key=value", fix="write e.g. --set latent_dim=32")
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out


def merge_config(defaults: dict[str, Any], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """``defaults`` with ``overrides`` applied (a dotted key, ``noise.occluded_m``, reaches into a nested
    setting); a key the model does not have, or a value of the wrong kind (text for a number, a number
    for a flag), is a DualhumanError naming the known keys."""
    config = json.loads(json.dumps(defaults))
    for key, value in (overrides or {}).items():
        parts = str(key).split(".")
        where = config
        for part in parts[:-1]:
            if not isinstance(where.get(part), dict):
                raise DualhumanError(f"the model has no setting {key!r}", fix=f"choose from: {', '.join(sorted(where))}")
            where = where[part]
        leaf = parts[-1]
        if leaf not in where:
            raise DualhumanError(f"the model has no setting {key!r}", fix=f"choose from: {', '.join(sorted(where))}")
        old = where[leaf]
        number = (int, float)
        ok = (old is None or value is None or type(old) is type(value)
              or (isinstance(old, number) and not isinstance(old, bool) and isinstance(value, number) and not isinstance(value, bool))
              or (isinstance(old, list) and isinstance(value, list)))  # fmt: skip
        if not ok:
            raise DualhumanError(f"setting {key!r} is {type(old).__name__} ({old!r}), got {type(value).__name__} {value!r}",
                                 fix=f"give {key} a value like {json.dumps(old)}")  # fmt: skip
        if isinstance(old, int) and not isinstance(old, bool) and isinstance(value, float) and value.is_integer():
            value = int(value)
        where[leaf] = value
    return config


def scaled_phases(spec: ModelSpec, config: dict[str, Any], steps_scale: float) -> list[Phase]:
    """The spec's phases with ``steps`` multiplied by ``steps_scale`` (at least one step each)."""
    out = []
    for p in spec.phases(config):
        out.append(Phase(p.name, max(1, round(p.steps * steps_scale)), p.lr, p.weight_decay))
    names = [p.name for p in out]
    if len(set(names)) != len(names) or not out:
        raise DualhumanError(f"model {spec.name!r} names phases {names}", fix="a model needs distinct phase names")
    return out


def _seed_all(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _step_seed(seed: int, step: int) -> int:
    return int(np.random.SeedSequence([seed, step]).generate_state(1, dtype=np.uint64)[0] % 2**63)


def to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    """``batch`` with every tensor on ``device`` (pinned and non-blocking to a GPU)."""
    cuda = device.type == "cuda"
    return {k: (v.pin_memory().to(device, non_blocking=True) if cuda else v.to(device)) if isinstance(v, torch.Tensor) else v
            for k, v in batch.items()}  # fmt: skip


class BatchStream:
    """The batches of one phase: step ``k`` takes items ``k*B .. (k+1)*B-1`` of an endless stream of
    permutations of the windows, each seeded by ``(seed, phase index, epoch)``: any step's batch is
    known without replaying the ones before it, so a resumed run draws what the whole run would."""

    def __init__(self, dataset: InteractionWindows, batch_size: int, seed: int, phase_index: int):
        self.ds, self.n, self.bs = dataset, len(dataset), int(batch_size)
        self.seed, self.phase_index = int(seed), int(phase_index)
        self._perm: tuple[int, np.ndarray] | None = None

    def _order(self, epoch: int) -> np.ndarray:
        if self._perm is None or self._perm[0] != epoch:
            self._perm = (epoch, np.random.default_rng([self.seed, self.phase_index, epoch]).permutation(self.n))
        return self._perm[1]

    def batch(self, step: int) -> dict[str, Any]:
        js = np.arange(step * self.bs, (step + 1) * self.bs, dtype=np.int64)
        epochs = js // self.n
        idx = np.empty(len(js), dtype=np.int64)
        for epoch in np.unique(epochs):
            sel = epochs == epoch
            idx[sel] = self._order(int(epoch))[js[sel] % self.n]
        self.ds.set_epoch(int(epochs[0]))  # the texts drawn for the batch
        return self.ds.batch(idx)


class _Display:
    """A rich progress bar on stderr (phase, steps, loss, windows/s, time left) on a terminal; one
    line per phase and every tenth of it otherwise. ``progress`` may also be a callable, which gets
    each step's record instead."""

    def __init__(self, progress: bool | Callable[[dict[str, Any]], None]):
        self.callback = progress if callable(progress) else None
        self.on = bool(progress) and self.callback is None
        self.bar = None
        self.task = None
        self.total = 0

    def __enter__(self):
        if self.on:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.console = Console(stderr=True)
            if self.console.is_terminal:
                self.bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                    TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn(),
                                    console=self.console, transient=False)  # fmt: skip
                self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)

    def say(self, text: str) -> None:
        if self.on:
            from rich.markup import escape

            (self.bar.console if self.bar is not None else self.console).print(escape(text), highlight=False, soft_wrap=True)

    def phase(self, phase: Phase, done: int) -> None:
        self.total = phase.steps
        if self.bar is not None:
            if self.task is not None:
                self.bar.update(self.task, visible=True)
            self.task = self.bar.add_task(f"phase {phase.name}", total=phase.steps, completed=done, info="")
        else:
            self.say(f"phase {phase.name}: {phase.steps} steps" + (f" (resuming at {done})" if done else ""))

    def step(self, rec: dict[str, Any]) -> None:
        if self.callback is not None:
            self.callback(rec)
            return
        info = f"loss {rec['loss']:.4g}  {rec['windows_per_s']:.0f} win/s  loader {100 * rec['loader_share']:.0f} %"
        if self.bar is not None:
            self.bar.update(self.task, completed=rec["phase_step"], info=info)
        elif self.on and (rec["phase_step"] == self.total or rec["phase_step"] % max(1, self.total // 10) == 0):
            self.say(f"  {rec['phase']} {rec['phase_step']}/{self.total}: {info}")


class _Interrupt:
    """Ctrl-C (SIGINT) during training asks the loop to stop after the current step, write a checkpoint
    and raise KeyboardInterrupt; a second Ctrl-C stops at once. Only in the main thread."""

    def __init__(self):
        self.asked = False
        self._old = None

    def _handler(self, signum, frame):
        if self.asked:
            raise KeyboardInterrupt
        self.asked = True

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        import signal

        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)


def _tensorboard(run_dir: Path, enabled: bool | None):
    if enabled is False:
        return None
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        if enabled:
            raise DualhumanError("TensorBoard logging was asked for, but tensorboard is not installed",
                                 fix="pip install tensorboard, or leave --tensorboard out") from None  # fmt: skip
        return None
    return SummaryWriter(str(run_dir / "tensorboard"))


def _manifest_digest(export_dir: Path) -> str:
    from dualhuman_builder.fileio import sha256_file

    path = export_dir / "manifest.json"
    if not path.is_file():
        raise DualhumanError(f"{path} does not exist: {export_dir} is not a dataset export",
                             fix="pass the folder `dualhuman export` wrote")  # fmt: skip
    return sha256_file(path)


def _data_options(config: dict[str, Any]) -> dict[str, Any]:
    return {k: config.get(k, v) for k, v in DATA_DEFAULTS.items()}


def _dataset(export_dir: Path, split: str, config: dict[str, Any], seed: int, spec: ModelSpec | None = None):
    """The spec's own dataset (:meth:`~dualhuman_builder.models.base.ModelSpec.make_dataset`, e.g. images),
    else windows of motion (:class:`InteractionWindows`)."""
    make = getattr(spec, "make_dataset", None)
    if make is not None:
        return make(export_dir, split, config, seed)
    return motion_windows(export_dir, split, config, seed)


def motion_windows(export_dir: str | Path, split: str, config: dict[str, Any], seed: int) -> InteractionWindows:
    """The loop's default dataset: windows of motion shaped by the config's data options
    (:data:`DATA_DEFAULTS`), for a spec's ``make_dataset`` that checks or wraps them."""
    o = _data_options(config)
    return InteractionWindows(export_dir, split, window=int(o["window"]), stride=o["stride"], visibility=bool(o["visibility"]),
                              seed=seed, cameras=int(o["cameras"]))  # fmt: skip


def _data_facts(data) -> dict[str, Any]:
    """What a run trained on, for its config and README: sequences, items (windows or images), frames,
    and the windows dataset's role swaps and too-short sequences (None for a dataset without them)."""
    return {"sequences": getattr(data, "num_sequences", None), "windows": len(data),
            "frames": getattr(data, "frames", None), "swapped": getattr(data, "swapped", None),
            "too_short": getattr(data, "too_short", None)}  # fmt: skip


def _spec(spec_name_or_spec: str | ModelSpec) -> ModelSpec:
    if isinstance(spec_name_or_spec, str):
        return get_model(spec_name_or_spec)
    if not isinstance(spec_name_or_spec, ModelSpec):
        raise DualhumanError(f"{spec_name_or_spec!r} is not a model", fix="pass a registered model name or a ModelSpec")
    return spec_name_or_spec


# ------------------------------------------------------------------ train
def train(spec_name_or_spec: str | ModelSpec, export_dir: str | Path, out_dir: str | Path, *,
          config_overrides: dict[str, Any] | None = None, steps_scale: float = 1.0, batch_size: int = 32, seed: int = 0,
          device: str = "cpu", amp: bool | None = None, resume: bool = True,
          progress: bool | Callable[[dict[str, Any]], None] = True, max_steps: int | None = None,
          tensorboard: bool | None = None, checkpoint_every: int | None = None, split: str = "train") -> Path:  # fmt: skip
    """Train a model on a split of an export (``train``; ``fit`` to keep ``validation`` unseen, see
    :func:`~dualhuman_builder.models.data.validation_subjects`); returns the run folder ``out_dir``.

    ``spec_name_or_spec``: a registered name (``reaction-prior``) or a spec. ``config_overrides``:
    settings over the spec's defaults (:func:`merge_config`). ``steps_scale``: multiplies every phase's
    steps. ``batch_size``: windows per step (at most the split's windows). ``seed``: weights, batches
    and every random draw. ``device``: ``cpu`` / ``cuda``. ``amp``: bf16 autocast (default: on a GPU
    only). ``resume``: continue the run in ``out_dir`` (False: refuse an existing run). ``progress``:
    a progress display on stderr, False for none, or a callable that gets every step's record.
    ``max_steps``: stop (with a checkpoint) after this many steps of the whole run, to be resumed
    later. ``tensorboard``: None: log there too when TensorBoard is installed. ``checkpoint_every``:
    steps between checkpoints (default: every 10 minutes; always at each phase's end, and on
    Ctrl-C, which stops after the current step and then raises KeyboardInterrupt).
    """
    spec = _spec(spec_name_or_spec)
    export_dir, run_dir = Path(export_dir), Path(out_dir)
    dev = resolve_device(device)
    amp = (dev.type == "cuda") if amp is None else bool(amp)
    if not (isinstance(batch_size, int) and batch_size >= 1):
        raise DualhumanError(f"batch size must be a positive integer, got {batch_size!r}", fix="use e.g. --batch-size 32")
    if not (isinstance(steps_scale, (int, float)) and math.isfinite(steps_scale) and steps_scale > 0):
        raise DualhumanError(f"steps scale must be a positive number, got {steps_scale!r}", fix="use e.g. --steps-scale 0.1")
    config = merge_config(spec.default_config(), config_overrides)
    phases = scaled_phases(spec, config, float(steps_scale))
    digest = _manifest_digest(export_dir)
    doc = {
        "model": spec.name,
        "config": config,
        "train": {"batch_size": batch_size, "seed": int(seed), "steps_scale": float(steps_scale)},
        "phases": [{"name": p.name, "steps": p.steps, "lr": p.lr, "weight_decay": p.weight_decay} for p in phases],
        "export": {"path": str(export_dir.resolve()), "manifest_sha256": digest, "split": split},
    }
    start = _open_run(run_dir, doc, resume, spec.default_config())
    if start is not None and start >= sum(p.steps for p in phases) and (run_dir / runs.SUMMARY).is_file():
        with _Display(progress) as show:
            show.say(f"{run_dir} is complete already ({start} steps)")
        return run_dir  # nothing to do: the run folder stays as it is, byte for byte
    data = _dataset(export_dir, split, config, seed, spec)
    from dualhuman_builder import __version__

    doc.update(toolkit_version=__version__, torch_version=torch.__version__, device=str(dev), amp=amp,
               data={"split": split, **_data_options(config), **_data_facts(data)})
    if start is None:
        runs.write_json(run_dir / runs.CONFIG, doc)

    _seed_all(int(seed))
    module = spec.build(config if start is None else _checkpoint_config(spec, config)).to(dev)
    ckpt = None
    if start is not None:
        ckpt, weights, opt_tensors = runs.load_checkpoint(run_dir, dev)
        module.load_state_dict(weights)
        runs.keep_metrics_until(run_dir, int(ckpt["global_step"]))
    total = sum(p.steps for p in phases)
    global_step = int(ckpt["global_step"]) if ckpt else 0
    bs = min(batch_size, len(data))
    writer = _tensorboard(run_dir, tensorboard)
    t_run = float(ckpt.get("time_s", 0.0)) if ckpt else 0.0
    last_ckpt_time = time.perf_counter()
    status = "complete"
    with _Display(progress) as show, open(run_dir / runs.METRICS, "a" if start else "w", encoding="utf-8") as metrics, _Interrupt() as interrupt:
        show.say(f"training {spec.name} on {getattr(data, 'num_sequences', '?')} sequences ({len(data)} items), "
                 f"{total} steps on {dev}{' (bf16)' if amp else ''} -> {run_dir}")  # fmt: skip
        offset = 0
        try:
            for pi, phase in enumerate(phases):
                first, offset = offset, offset + phase.steps
                if global_step >= offset:
                    continue
                done = global_step - first
                params = list(spec.parameters(module, phase.name))
                ids = {id(p) for p in params}
                for p in module.parameters():
                    p.requires_grad_(id(p) in ids)
                opt = torch.optim.AdamW(params, lr=phase.lr, weight_decay=phase.weight_decay)
                if ckpt is not None and done > 0 and ckpt.get("phase") == phase.name and ckpt.get("optimizer"):
                    runs.restore_optimizer(opt, opt_tensors, ckpt["optimizer_state"])
                stream = BatchStream(data, bs, int(seed), pi)
                show.phase(phase, done)
                module.train()
                for k in range(done, phase.steps):
                    if max_steps is not None and global_step >= max_steps:
                        status = "stopped"
                        break
                    if interrupt.asked:
                        status = "interrupted"
                        break
                    t0 = time.perf_counter()
                    step_seed = _step_seed(int(seed), global_step)
                    _seed_all(step_seed)
                    batch = to_device(stream.batch(k), dev)
                    t1 = time.perf_counter()
                    with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp):
                        losses = spec.losses(module, batch, phase.name)
                    loss = losses["loss"]
                    opt.zero_grad(set_to_none=True)
                    loss.float().backward()
                    opt.step()
                    values = {n: float(v.detach().float()) for n, v in losses.items()}
                    if dev.type == "cuda":
                        torch.cuda.synchronize(dev)
                    t2 = time.perf_counter()
                    if not math.isfinite(values["loss"]):
                        raise DualhumanError(f"the loss of phase {phase.name!r} is {values['loss']} at step {k}",
                                             fix="lower the learning rate or check the data (`dualhuman export verify`); "
                                                 "the last checkpoint holds the weights before it")  # fmt: skip
                    global_step += 1
                    t_run += t2 - t0
                    rec = {"phase": phase.name, "step": global_step, "phase_step": k + 1, "lr": phase.lr, **values,
                           "windows_per_s": bs / max(t2 - t0, 1e-9), "loader_share": (t1 - t0) / max(t2 - t0, 1e-9),
                           "step_s": t2 - t0, "time_s": t_run}  # fmt: skip
                    metrics.write(json.dumps(rec) + "\n")
                    metrics.flush()
                    if writer is not None:
                        for n, v in values.items():
                            writer.add_scalar(f"{phase.name}/{n}", v, global_step)
                        writer.add_scalar("speed/windows_per_s", rec["windows_per_s"], global_step)
                        writer.add_scalar("speed/loader_share", rec["loader_share"], global_step)
                    show.step(rec)
                    due = (checkpoint_every is not None and global_step % checkpoint_every == 0) or (
                        checkpoint_every is None and time.perf_counter() - last_ckpt_time > CHECKPOINT_SECONDS)
                    if due and k + 1 < phase.steps:
                        runs.save_checkpoint(run_dir, module, opt, _info(phase, k + 1, global_step, t_run))
                        last_ckpt_time = time.perf_counter()
                if status != "complete":
                    runs.save_checkpoint(run_dir, module, opt, _info(phase, global_step - first, global_step, t_run))
                    show.say(f"{status} after step {global_step} of {total}; the same command continues the run")
                    break
                runs.save_checkpoint(run_dir, module, opt, _info(phase, phase.steps, global_step, t_run))
                last_ckpt_time = time.perf_counter()
        finally:
            if writer is not None:
                writer.close()
    _finish(run_dir, doc, total, global_step, t_run, status, phases)
    if status == "interrupted":
        raise KeyboardInterrupt(f"training interrupted at step {global_step}; checkpoint written to {run_dir}")
    return run_dir


def _info(phase: Phase, phase_step: int, global_step: int, t_run: float) -> dict[str, Any]:
    return {"phase": phase.name, "phase_step": int(phase_step), "global_step": int(global_step), "time_s": t_run}


def _open_run(run_dir: Path, doc: dict[str, Any], resume: bool, defaults: dict[str, Any]) -> int | None:
    """None for a fresh run folder; the checkpoint's global step when an existing run resumes.

    A setting the run's config lacks counts as the model's default (``defaults``), as loading the run
    takes it: a setting added to a model since the run was made does not stop the run from resuming
    unless it is now set to another value."""
    cfg_path = run_dir / runs.CONFIG
    if run_dir.exists() and not run_dir.is_dir():
        raise DualhumanError(f"{run_dir} is a file", fix="choose another --out")
    if cfg_path.is_file():
        old = runs.read_json(cfg_path, "the run's config")
        if not resume:
            raise DualhumanError(f"{run_dir} holds a run already", fix="choose another --out, or remove the folder to start over")
        keys = ("model", "config", "train", "phases")
        before = {k: old.get(k) for k in keys}
        if isinstance(before["config"], dict):
            before["config"] = {**defaults, **before["config"]}
        diff = runs.differences(before, {k: doc[k] for k in keys})
        if old.get("export", {}).get("manifest_sha256") != doc["export"]["manifest_sha256"]:
            diff.append(f"export: manifest {str(old.get('export', {}).get('manifest_sha256'))[:12]} -> "
                        f"{doc['export']['manifest_sha256'][:12]} (another or a changed dataset)")  # fmt: skip
        if old.get("export", {}).get("split", "train") != doc["export"]["split"]:
            diff.append(f"split: {old.get('export', {}).get('split', 'train')} -> {doc['export']['split']}")
        if diff:
            raise DualhumanError(f"{run_dir} holds a run with other settings, so it cannot be continued: " + "; ".join(diff[:8]),
                                 fix="repeat the run's own settings to continue it, or choose another --out")  # fmt: skip
        if not (run_dir / runs.CHECKPOINTS / runs.LAST).is_file():
            return None  # stopped before its first checkpoint: start again
        return int(runs.read_json(run_dir / runs.CHECKPOINTS / runs.LAST, "the checkpoint record")["global_step"])
    if run_dir.is_dir() and any(run_dir.iterdir()):
        raise DualhumanError(f"{run_dir} is a folder with other files, not a run folder", fix="choose a new or empty --out")
    run_dir.mkdir(parents=True, exist_ok=True)
    return None


def _finish(run_dir: Path, doc: dict[str, Any], total: int, global_step: int, t_run: float, status: str,
            phases: list[Phase]) -> None:  # fmt: skip
    records = runs.read_metrics(run_dir)
    runs.plot_curves(run_dir, records)
    per_phase = runs.summarise(records)
    summary = {
        "model": doc["model"], "status": status, "global_step": global_step, "total_steps": total, "time_s": t_run,
        "device": doc["device"], "amp": doc["amp"], "seed": doc["train"]["seed"], "batch_size": doc["train"]["batch_size"],
        "window": doc["data"]["window"], "export": doc["export"], "data": doc["data"],
        "phases": {p.name: per_phase.get(p.name, {"steps": 0}) for p in phases},
        "windows_per_s": (sum(r.get("windows_per_s", 0.0) for r in records[2:]) / max(1, len(records[2:]))) if records else None,
        "loader_share": (sum(r.get("loader_share", 0.0) for r in records[2:]) / max(1, len(records[2:]))) if records else None,
        "toolkit_version": doc["toolkit_version"], "torch_version": doc["torch_version"],
    }  # fmt: skip
    runs.write_json(run_dir / runs.SUMMARY, summary)
    runs.write_readme(run_dir, summary)


# ------------------------------------------------------------------ load and evaluate
def _checkpoint_config(spec: ModelSpec, config: dict[str, Any]) -> dict[str, Any]:
    """``config`` for a module that takes a checkpoint's weights: the spec's ``init_keys``
    (:data:`~dualhuman_builder.models.base.INIT_KEYS`) set to None, as the checkpoint holds those weights."""
    return {**config, **{k: None for k in getattr(spec, INIT_KEYS, ())}}


def load_run(run_dir: str | Path, device: str = "cpu") -> tuple[ModelSpec, dict[str, Any], torch.nn.Module]:
    """``(spec, config, module)`` of a run folder: the module with its last checkpoint's weights, in
    eval mode on ``device``."""
    run_dir = Path(run_dir)
    doc = runs.read_json(run_dir / runs.CONFIG, "the run's config")
    spec = get_model(str(doc.get("model")))
    config = doc.get("config")
    if not isinstance(config, dict):
        raise DualhumanError(f"{run_dir}/config.json has no model config", fix="pass a run folder `dualhuman train` wrote")
    dev = resolve_device(device)
    _seed_all(int(doc.get("train", {}).get("seed", 0)))
    module = spec.build(_checkpoint_config(spec, config)).to(dev)
    _, weights, _ = runs.load_checkpoint(run_dir, dev, optimizer=False)
    module.load_state_dict(weights)
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    return spec, config, module


def iter_batches(dataset: InteractionWindows, batch_size: int, device: torch.device) -> Iterator[dict[str, Any]]:
    """The windows of ``dataset`` in order, ``batch_size`` at a time, on ``device``."""
    for lo in range(0, len(dataset), batch_size):
        yield to_device(dataset.batch(np.arange(lo, min(len(dataset), lo + batch_size))), device)


def evaluate(run_dir: str | Path, export_dir: str | Path, split: str = "test", *, batch_size: int = 64,
             device: str = "cpu", seed: int = 0) -> dict[str, Any]:  # fmt: skip
    """The model's figures (its spec's ``evaluate``) on ``split`` of an export, written to
    ``RUN/eval-<split>.json`` with what they were measured on; returns the same dict."""
    run_dir, export_dir = Path(run_dir), Path(export_dir)
    spec, config, module = load_run(run_dir, device)
    dev = resolve_device(device)
    data = _dataset(export_dir, split, config, seed, spec)
    _seed_all(int(seed))
    t0 = time.perf_counter()
    with torch.no_grad():
        figures = spec.evaluate(module, iter_batches(data, int(batch_size), dev), dev)
    result = {
        "model": spec.name,
        "split": split,
        "export": {"path": str(export_dir.resolve()), "manifest_sha256": _manifest_digest(export_dir)},
        "sequences": getattr(data, "num_sequences", None),
        "windows": len(data),
        "seed": int(seed),
        "time_s": time.perf_counter() - t0,
        "figures": {k: float(v) for k, v in figures.items()},
    }
    if not all(math.isfinite(v) for v in result["figures"].values()):
        result["figures"] = {k: (v if math.isfinite(v) else None) for k, v in result["figures"].items()}
    runs.write_json(run_dir / f"eval-{split}.json", result)
    return result
