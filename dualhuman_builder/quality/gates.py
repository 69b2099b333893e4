"""Quality gates: checks of a take's stage results against thresholds, whose failures are flags.

Each gate reads one stage's artifacts and report (:data:`GATES`: gate -> stage) and is evaluated
only when that stage's run is done; otherwise it is skipped, not failed. The thresholds are in one
config, the bundled ``gates.toml`` (:data:`DEFAULT_CONFIG`, documented value by value), which a
user's file overrides key by key (:func:`load_config`). :func:`check_take` evaluates every gate of a
take and stores its flags in the catalog (:func:`~dualhuman_builder.workspace.catalog.replace_flags`),
replacing the take's previous ones; ``dualhuman status`` shows them, ``dualhuman export`` leaves
flagged takes out unless ``--include-flagged``, and the review page (:mod:`.review`) lists them.

A gate that cannot read its input (a damaged or malformed artifact) is a flag itself, with no value:
such a take is not fit to export until it is looked at.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from dualhuman_builder.errors import DualhumanError, FormatError, WorkspaceError

#: The bundled thresholds (package data).
DEFAULT_CONFIG = "gates.toml"
#: The largest config file read (bytes): a config is a few dozen lines.
MAX_CONFIG_BYTES = 1 << 20


@dataclass(frozen=True)
class Flag:
    """One failed gate of a take: ``gate`` (a name of :data:`GATES`), the ``stage`` it read, the
    measured ``value`` and the ``threshold`` it crossed (in the units of the config key the message
    names; None where the gate has no number, e.g. a sync warning), a ``message`` for people, and
    the ``subject`` it concerns (a tracker serial, an actor; "" for the whole take)."""

    gate: str
    stage: str
    value: float | None
    threshold: float | None
    message: str
    subject: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _finite(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


# ------------------------------------------------------------------------------ config
def _read_toml(text: str, where: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise FormatError(f"quality gate config {where} is not valid TOML: {e}",
                          fix="check the file against the bundled dualhuman_builder/quality/gates.toml") from None  # fmt: skip


def default_config() -> dict[str, dict[str, Any]]:
    """The bundled thresholds, ``{gate: {key: value}}``."""
    text = resources.files("dualhuman_builder.quality").joinpath(DEFAULT_CONFIG).read_text(encoding="utf-8")
    return _read_toml(text, DEFAULT_CONFIG)


def load_config(config: str | Path | Mapping | None = None) -> dict[str, dict[str, Any]]:
    """The gates' thresholds: the bundled ones, with those of ``config`` (a TOML file's path or a
    mapping ``{gate: {key: value}}``) in their place. An unknown gate or key, or a value of another
    type than the bundled one, is a :class:`FormatError` naming it."""
    base = default_config()
    if config is None:
        return base
    where = "(given)"
    if not isinstance(config, Mapping):
        path = Path(config)
        where = str(path)
        try:
            size = path.stat().st_size
            if size > MAX_CONFIG_BYTES:
                raise FormatError(f"quality gate config {path} is {size:,} bytes; a config is a few KiB", path=path)
            text = path.read_bytes().decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError(f"quality gate config {path} is not UTF-8 text", path=path) from None
        except OSError as e:
            raise FormatError(f"cannot read the quality gate config: {e.strerror or e}", path=path,
                              fix="give the path of a TOML file like dualhuman_builder/quality/gates.toml") from None  # fmt: skip
        config = _read_toml(text, where)
    fix = f"the gates and keys are those of the bundled gates.toml: {', '.join(base)}"
    for gate, keys in config.items():
        if gate not in base:
            raise FormatError(f"quality gate config {where}: no gate named {gate!r}", fix=fix)
        if not isinstance(keys, Mapping):
            raise FormatError(f"quality gate config {where}: [{gate}] must be a table of keys", fix=fix)
        for key, value in keys.items():
            if key not in base[gate]:
                raise FormatError(f"quality gate config {where}: gate {gate!r} has no key {key!r} "
                                  f"(it has {', '.join(base[gate])})", fix=fix)  # fmt: skip
            ref = base[gate][key]
            ok = (isinstance(value, bool) if isinstance(ref, bool) else
                  isinstance(value, list) and all(isinstance(v, str) for v in value) if isinstance(ref, list) else
                  isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0)  # fmt: skip
            if not ok:
                want = "true or false" if isinstance(ref, bool) else "a list of strings" if isinstance(ref, list) else \
                    "a finite number >= 0"  # fmt: skip
                raise FormatError(f"quality gate config {where}: {gate}.{key} = {value!r} must be {want}", fix=fix)
            base[gate][key] = value
    return base


# ------------------------------------------------------------------------------ the gates
def _tracker_loss(ws, take, cfg, arts, rec) -> list[Flag]:
    stats = json.loads(arts["fuse.json"].read_text(encoding="utf-8"))
    out = []
    for actor, info in stats.items():
        if not info.get("fused_with_trackers", True):
            out.append(Flag("tracker_loss", "fuse", 1.0, cfg["max_share"],
                            f"{actor}: fused without trackers (the suit's position drift remains)", actor))  # fmt: skip
            continue
        for serial, s in (info.get("trackers") or {}).items():
            valid, bridged = int(s["valid_frames"]), int(s["bridged_frames"])
            share = bridged / (valid + bridged) if valid + bridged else 1.0
            if share > cfg["max_share"]:
                out.append(Flag("tracker_loss", "fuse", round(share, 4), cfg["max_share"],
                                f"{actor}: tracker {serial} lost or rejected in {100 * share:.1f} % of the frames "
                                f"({bridged} bridged, {s.get('rejected_jumps', 0)} jumps rejected; "
                                f"tracker_loss.max_share {100 * cfg['max_share']:g} %)", serial))  # fmt: skip
    return out


def _sync_warnings(ws, take, cfg, arts, rec) -> list[Flag]:
    report = json.loads(arts["sync.json"].read_text(encoding="utf-8"))
    return [Flag("sync_warnings", "sync", None, None, str(w))
            for w in report.get("warnings") or () if not any(s in str(w) for s in cfg["ignore"])]  # fmt: skip


def _root_drift(ws, take, cfg, arts, rec) -> list[Flag]:
    from dualhuman_builder.sync.stage import load_sync

    sync = load_sync(ws, take)
    t = np.asarray(sync.times_s, np.float64)
    duration = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    out = []
    for a in sync.actors:
        if a.mounts is None:
            continue  # no trackers: the tracker_loss gate says so
        d = np.asarray(a.mounts.drift, np.float64)[:, [0, 2]]
        ok = np.isfinite(d).all(axis=1)
        if ok.sum() < 2:
            continue
        d, tt = d[ok], t[ok]
        excursion = float(np.linalg.norm(d - d[0], axis=1).max())
        if excursion > cfg["max_excursion_m"]:
            out.append(Flag("root_drift", "sync", round(excursion, 4), cfg["max_excursion_m"],
                            f"{a.actor}: the suit's root drifted {100 * excursion:.1f} cm from the trackers over the take "
                            f"(root_drift.max_excursion_m {cfg['max_excursion_m']:g} m)", a.actor))  # fmt: skip
        if duration >= cfg["min_rate_s"]:
            slope = np.linalg.lstsq(np.stack([tt - tt[0], np.ones_like(tt)], 1), d, rcond=None)[0][0]  # m/s per axis
            rate = float(np.linalg.norm(slope) * 60.0)
            if rate > cfg["max_m_per_min"]:
                out.append(Flag("root_drift", "sync", round(rate, 4), cfg["max_m_per_min"],
                                f"{a.actor}: the suit's root drifts {rate:.2f} m/min from the trackers "
                                f"(root_drift.max_m_per_min {cfg['max_m_per_min']:g})", a.actor))  # fmt: skip
    return out


def _fit_frames(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k.replace("|", "/"): np.asarray(z[k]) for k in z.files}


def _fit_residuals(ws, take, cfg, arts, rec) -> list[Flag]:
    frames = _fit_frames(arts["frames.npz"])
    out = []
    valid = frames.get("valid")
    if valid is not None and valid.size:
        share = float(np.mean(valid.astype(bool)))
        if share < cfg["min_valid_share"]:
            out.append(Flag("fit_residuals", "fit", round(share, 4), cfg["min_valid_share"],
                            f"only {100 * share:.1f} % of the frames have valid fit input "
                            f"(fit_residuals.min_valid_share {100 * cfg['min_valid_share']:g} %)"))  # fmt: skip
    for key, v in frames.items():
        if not key.startswith("tracker residual (mm)/"):
            continue
        actor = key.split("/", 1)[1]
        v = np.asarray(v, np.float64)
        v = v[np.isfinite(v)]
        if not v.size:
            continue
        p95 = float(np.percentile(v, 95))
        if p95 > cfg["max_p95_mm"]:
            out.append(Flag("fit_residuals", "fit", round(p95, 2), cfg["max_p95_mm"],
                            f"{actor}: the fitted body misses its trackers by {p95:.1f} mm (95th percentile over the "
                            f"frames; fit_residuals.max_p95_mm {cfg['max_p95_mm']:g})", actor))  # fmt: skip
    return out


def _penetration(ws, take, cfg, arts, rec) -> list[Flag]:
    out = []
    summary = rec["summary"]
    mm, share = summary.get("max_penetration_after_mm"), summary.get("penetrating_share_after")
    if mm is not None and _finite(mm) is not None and float(mm) > cfg["max_mm"]:
        out.append(Flag("penetration", "fit", round(float(mm), 3), cfg["max_mm"],
                        f"the bodies overlap by up to {float(mm):.1f} mm after the collision passes "
                        f"(penetration.max_mm {cfg['max_mm']:g})"))  # fmt: skip
    if share is not None and _finite(share) is not None and float(share) > cfg["max_share"]:
        out.append(Flag("penetration", "fit", round(float(share), 6), cfg["max_share"],
                        f"{100 * float(share):.2f} % of the vertex-frames lie inside the other body "
                        f"(penetration.max_share {100 * cfg['max_share']:g} %)"))  # fmt: skip
    return out


#: HumanML3D joint indices of the feet (the ball of each foot; :data:`~dualhuman_builder.body.joints.JOINT22_NAMES`).
FEET = {"left": 10, "right": 11}


def foot_slide_mm_s(joints: np.ndarray, fps: float, stance_speed_m_s: float, stance_height_m: float) -> float | None:
    """Mean horizontal speed (mm/s) of the feet over the frame pairs where a foot is in stance at
    both ends: slower than ``stance_speed_m_s`` and within ``stance_height_m`` of its lowest height
    in the take. ``joints (T, 22, 3)`` m, Y up. None when no foot is ever in stance."""
    steps = []
    for j in FEET.values():
        p = np.asarray(joints[:, j], np.float64)
        if len(p) < 2 or not np.isfinite(p).all():
            continue
        speed = np.linalg.norm(np.diff(p, axis=0), axis=1) * fps
        low = p[:, 1] - p[:, 1].min() < stance_height_m
        stance = np.zeros(len(p), bool)
        stance[1:] = speed < stance_speed_m_s
        stance[0] = stance[1]
        stance &= low
        both = stance[1:] & stance[:-1]
        steps.append(np.linalg.norm(np.diff(p[:, [0, 2]], axis=0), axis=1)[both] * fps)
    steps = np.concatenate(steps) if steps else np.zeros(0)
    return float(steps.mean() * 1000) if steps.size else None


def _foot_slide(ws, take, cfg, arts, rec) -> list[Flag]:
    from dualhuman_builder.fit.fitter import FitConfig
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    fc = FitConfig()
    if "bodies.npz" in arts:
        tracks = list(InteractionSequence.load(arts["bodies.npz"]).actors)
    else:
        tracks = [BodyTrack.load(p) for name, p in sorted(arts.items()) if name.endswith(".body.npz")]
    out = []
    for k, tr in enumerate(tracks):
        v = foot_slide_mm_s(tr.joints(), float(tr.fps), fc.stance_speed_m_s, fc.stance_height_m)
        if v is not None and v > cfg["max_mm_s"]:
            actor = tr.actor or f"actor {k}"
            out.append(Flag("foot_slide", "fit", round(v, 2), cfg["max_mm_s"],
                            f"{actor}: feet in stance slide at {v:.0f} mm/s on average (foot_slide.max_mm_s "
                            f"{cfg['max_mm_s']:g})", actor))  # fmt: skip
    return out


def flickers(on: np.ndarray, min_run: int) -> int:
    """Runs of ``on`` (per-frame bool), and gaps between them, shorter than ``min_run`` frames; a
    gap at the start or end of the take does not count (it may be cut)."""
    on = np.asarray(on, bool)
    if on.size == 0:
        return 0
    edges = np.flatnonzero(np.diff(on.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [on.size]])
    n = 0
    for k in range(len(bounds) - 1):
        length = bounds[k + 1] - bounds[k]
        interior = 0 < k < len(bounds) - 2
        if length < min_run and (on[bounds[k]] or interior):
            n += 1
    return n


def _contact_flicker(ws, take, cfg, arts, rec) -> list[Flag]:
    report = json.loads(arts["contacts.json"].read_text(encoding="utf-8"))
    counts = [np.asarray(v, np.float64) for v in (report.get("contact_vertices") or {}).values()]
    if not counts:
        return []
    T = max(len(c) for c in counts)
    on = np.zeros(T, bool)
    for c in counts:
        on[: len(c)] |= c > 0
    n = flickers(on, int(cfg["min_run_frames"]))
    if n > cfg["max_flickers"]:
        return [Flag("contact_flicker", "contacts", float(n), float(cfg["max_flickers"]),
                     f"the contact label toggles {n} times within {int(cfg['min_run_frames'])} frames "
                     f"(contact_flicker.max_flickers {cfg['max_flickers']:g})")]  # fmt: skip
    return []


#: The image kinds of a rendered view and frame, with their file extension.
RENDER_IMAGES = (("rgb", "png"), ("depth", "exr"), ("mask", "png"))


def _render_completeness(ws, take, cfg, arts, rec) -> list[Flag]:
    info = json.loads(arts["render.json"].read_text(encoding="utf-8"))
    frames, views = [int(f) for f in info.get("frames") or ()], [str(v) for v in info.get("views") or ()]
    expected = [f"views/{v}/{kind}/{f:05d}.{ext}" for v in views for f in frames for kind, ext in RENDER_IMAGES]
    if not expected:
        return [Flag("render_completeness", "render", 1.0, cfg["max_missing_share"], "render.json lists no frames or views")]
    missing = [e for e in expected if e not in arts or not arts[e].is_file()]
    share = len(missing) / len(expected)
    if share > cfg["max_missing_share"]:
        return [Flag("render_completeness", "render", round(share, 4), cfg["max_missing_share"],
                     f"{len(missing)} of {len(expected)} images missing (first: {missing[0]}; "
                     f"render_completeness.max_missing_share {cfg['max_missing_share']:g})")]  # fmt: skip
    return []


@dataclass(frozen=True)
class Gate:
    """A gate: its ``name`` (a table of the config), the ``stage`` whose done run it reads, and its
    check ``(ws, take, config, artifacts, record) -> [Flag]`` (``artifacts``: name -> path of that
    run, ``record``: its catalog record, :func:`~dualhuman_builder.workspace.runner.stage_record`)."""

    name: str
    stage: str
    check: Callable[..., list[Flag]]
    what: str


GATES: tuple[Gate, ...] = (
    Gate("sync_warnings", "sync", _sync_warnings, "the sync report's warnings"),
    Gate("root_drift", "sync", _root_drift, "the suit's position drift against the trackers"),
    Gate("tracker_loss", "fuse", _tracker_loss, "share of frames each tracker was lost"),
    Gate("fit_residuals", "fit", _fit_residuals, "distance from the fitted bodies to their trackers"),
    Gate("penetration", "fit", _penetration, "the bodies' overlap after the collision passes (the fit summary)"),
    Gate("foot_slide", "fit", _foot_slide, "feet sliding in stance"),
    Gate("contact_flicker", "contacts", _contact_flicker, "contact labels toggling within a few frames"),
    Gate("render_completeness", "render", _render_completeness, "every view's images of every frame"),
)
GATE_NAMES = tuple(g.name for g in GATES)


def evaluate_take(ws, take: str, config: str | Path | Mapping | None = None) -> tuple[list[Flag], dict[str, Any]]:
    """``(flags, check)`` of ``take`` without storing them: every gate whose stage's run is done;
    ``check`` has ``evaluated`` (gate names), ``skipped`` (gate -> why) and ``stages`` (stage ->
    ``ended_at`` of the run read)."""
    from dualhuman_builder.workspace.runner import stage_record

    cfg = load_config(config)
    ws.take(take)  # an unknown take: a clear error
    flags: list[Flag] = []
    check: dict[str, Any] = {"evaluated": [], "skipped": {}, "stages": {}}
    ended: dict[str, str | None] = {}
    for gate in GATES:
        gc = cfg[gate.name]
        if not gc.get("enabled", True):
            check["skipped"][gate.name] = "disabled in the config"
            continue
        rec = stage_record(ws, gate.stage, take)
        if rec is None or rec["status"] != "done":
            check["skipped"][gate.name] = f"{gate.stage} {'has not run' if rec is None else 'is ' + rec['status']}"
            continue
        arts = {name: ws.root / a["path"] for name, a in rec["artifacts"].items()}
        check["evaluated"].append(gate.name)
        check["stages"][gate.stage] = ended[gate.stage] = rec["ended_at"]
        try:
            found = gate.check(ws, take, gc, arts, rec)
        except (DualhumanError, OSError, ValueError, KeyError, TypeError, IndexError, AttributeError) as e:
            why = e.message if isinstance(e, DualhumanError) else f"{type(e).__name__}: {e}"
            found = [Flag(gate.name, gate.stage, None, None, f"could not evaluate the gate on the {gate.stage} stage's "
                                                             f"artifacts ({why}); run `dualhuman status {ws.root} --verify`")]  # fmt: skip
        flags.extend(found)
    return flags, check


def check_take(ws, take: str, config: str | Path | Mapping | None = None) -> list[Flag]:
    """Evaluate every gate of ``take`` whose stage is done (:func:`evaluate_take`), store the flags
    in the catalog in place of the take's previous ones, and return them. ``config``: a TOML file or
    a mapping overriding the bundled thresholds (:func:`load_config`)."""
    from dualhuman_builder.workspace.catalog import replace_flags

    if ws.readonly:
        raise WorkspaceError("cannot store quality flags: the workspace was opened read-only", path=ws.root)
    flags, check = evaluate_take(ws, take, config)
    rows = [{**f.as_dict(), "stage_ended_at": check["stages"].get(f.stage)} for f in flags]
    replace_flags(ws.conn, ws._take_id(take), rows, check)
    return flags


def stored_flags(ws, take: str | None = None) -> dict[str, dict]:
    """The stored verdicts by take (:func:`~dualhuman_builder.workspace.catalog.take_flags`)."""
    from dualhuman_builder.workspace.catalog import take_flags

    return take_flags(ws.conn, None if take is None else ws._take_id(take))
