"""Synthetic datasets: many varied simulated takes in one workspace, reproducible from a seed.

:func:`plan_synthetic` draws the plan of ``N`` takes from :class:`SynthOptions` (numbers only,
no body model: the same options give the same plan, byte for byte): a pool of actors over statures,
genders and build (anny phenotypes within the adult ranges of :data:`STATURE_M` and :data:`BUILD`),
studio days (``takes_per_day`` takes each: one pair of them, one draw of the simulated devices and
so one set of tracker mounts, one device error preset, and a calibration take), each take's
interaction type (shuffled rounds over the chosen types, so each comes up equally often), scene
seed, tempo (:data:`TEMPO`), approach distance (:data:`APPROACH_SPREAD_M` about the type's own),
duration, and its split (train or test, when actors or types are held out). A share of the takes are long ``session`` takes that chain interactions
(:mod:`.session`). :func:`make_synthetic` writes the plan to ``WS/synth.json``, registers the
actors, and makes the takes:

* ``path="full"``: each day's calibration take, then each take's ``scene``, ``devices`` and
  ``capture`` stages, as ``dualhuman sim take`` does, labelled from its scene and recording its
  day's calibration take as ``mounts_from``; ``dualhuman run WS`` then runs sync ... sheet, each
  take's sync with its day's tracker mounts (as a studio records one calibration take per day,
  :doc:`decision 0013 <docs/decisions/0013-calibration-take.md>`). A take whose
  stages the catalog records done is skipped, so a second call resumes. With ``export``, the takes
  fitted so far are exported with the plan's split.
* ``path="ground-truth"``: scene -> export, no devices and no fit: each scene (kept in
  ``WS/synth/scenes/TAKE-gN.npz``, N the generator's version, so a second call resumes) gives the
  ground-truth bodies and, by the contacts stage's own computation on them, the contacts; every
  sequence's ``meta.source`` and the manifest's ``source`` say ``"ground-truth"``. With
  ``SynthOptions.render``, each scene's bodies are also rendered by the render stage's own
  :func:`~dualhuman_builder.render.stage.render_sequence` from a ring of cameras
  (:data:`GROUND_TRUTH_RENDER`, each take's ring jittered with its scene seed) into
  ``WS/synth/renders/TAKE-gN``, and exported as a fitted take's renders are (``cameras.json``,
  ``renders/``, with the image targets the export writer computes); a scene rendered before with the
  same settings is not rendered again.

Why days: the trackers' mounts are the studio's, strapped once per day; a take synced without a
calibration take knows the trackers' shared offset, and the body's root with it, only as well
as the trackers' site prior allows, which the sync reports as a warning and the quality gates flag. A day's pair keeps its order
(the simulated devices draw each tracker's mount per actor slot), so a ``dance_turn`` is drawn only in
a day whose first actor is the taller (the leader turns the partner under the joined hands).

Not varied: handedness (every scene type's choreography fixes which hands act: a right-hand
handshake, A's right palm against B's left in a high five...), so the plan has none.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.sim.scenes import MAX_DRAWS, NATURAL_DURATION, SCENE_TYPES, SESSION_TYPE

#: The plan's file in the workspace, its format name and version.
PLAN_FILE = "synth.json"
PLAN_FORMAT, PLAN_VERSION = "dualhuman-synth-plan", 2
#: Where the ground-truth path keeps its scenes (under the workspace).
SCENES_DIR = "synth/scenes"
#: The two ways through: every stage (``dualhuman run`` after), or scene straight to the export.
PATHS = ("full", "ground-truth")
#: Device error presets of the plan: ``mixed`` gives half the takes (rounded down) ``realistic``, the rest ``ideal``.
SYNTH_PRESETS = ("ideal", "realistic", "mixed")
#: Statures (m, sole to crown) per gender: the adult ranges the scene generator draws its own actors
#: from (:func:`~dualhuman_builder.sim.scenes.random_adult_shapes`), within which every scene type
#: meets its quality contract.
STATURE_M = {"female": (1.55, 1.80), "male": (1.58, 1.92)}
#: anny phenotype ranges of the build (:mod:`dualhuman_builder.body.shape`): ``age`` young (2/3: ~25
#: years) to middle-aged adults, and muscle, weight and proportions about anny's average (0.5),
#: as :func:`~dualhuman_builder.sim.scenes.random_adult_shapes` draws them.
BUILD = {"age": (0.62, 0.85), "muscle": (0.3, 0.7), "weight": (0.3, 0.7), "proportions": (0.35, 0.65)}
#: Tempo range (x the choreography's speed): +-15 % keeps the walk-in, reach and release within the
#: paces the choreographies are written for (their steps are timed, not their speed).
TEMPO = (0.85, 1.15)
#: Each type's own approach distance (m, pelvis to pelvis at the start: the choreographies'
#: defaults in :mod:`.scenes`); ``dance_turn`` starts holding hands (its distance is the
#: partners' reach, not an approach), so it is not varied.
APPROACH_M = {"handshake": 1.8, "hug": 1.8, "high_five": 1.8, "push": 1.9, "pat_on_back": 1.5}
#: The approach distance is drawn within this many metres of the type's own: the approach walk
#: has a fixed time, so +-0.2 m changes its pace by about a step's length, and the nearest start
#: stays well beyond the distance at which the type's contact happens (a scene refuses a start
#: nearer than that: the take is then reported failed).
APPROACH_SPREAD_M = 0.2
#: Length (s) of a long take by default, and the shortest one (:data:`~dualhuman_builder.sim.session.MIN_DURATION_S`).
LONG_DURATION_S, MIN_LONG_DURATION_S = 60.0, 10.0
#: Types whose actor 0 acts and actor 1 reacts (the pusher, the one who pats, the leader of the
#: turn): exported with roles ``("actor", "reactor")``.
ONE_SIDED = ("push", "pat_on_back", "dance_turn")
#: Takes of one studio day by default: a pair records a few interactions after its calibration take.
TAKES_PER_DAY = 6
#: Most takes one plan holds (its JSON stays a few MB).
MAX_TAKES = 100_000
#: Contents of the export of the ground-truth path (renders too with ``SynthOptions.render``).
GROUND_TRUTH_EXPECT = ("motion", "contacts", "text")
#: Where the ground-truth path keeps its renders (under the workspace), and its record of a finished render.
RENDERS_DIR, RENDER_RECORD = "synth/renders", ".synth-render.json"
#: The ground-truth path's camera ring: radius (m) around the pair's mean pelvis, camera height (m)
#: above the floor, horizontal field of view (degrees), as the render stage's defaults; the template.
GROUND_TRUTH_RENDER = {"radius_m": 3.0, "height_m": 1.4, "fov_deg": 50.0, "template": "studio"}


class SynthError(DualhumanError, ValueError):
    """A synthetic dataset's options are invalid, or the workspace holds another plan."""


@dataclass(frozen=True)
class SynthOptions:
    """What to plan. ``takes``: how many (>= 1); ``seed``: of every draw; ``types``: the interaction
    types drawn from (:data:`~dualhuman_builder.sim.scenes.SCENE_TYPES`); ``preset``: device errors
    (:data:`SYNTH_PRESETS`); ``fps``: of the ground truth; ``long_share``: share of the takes that
    are long ``session`` takes (rounded to a whole number of takes); ``long_duration``: their length
    (s); ``takes_per_day``: takes of one studio day (one pair, one device draw and preset, one
    calibration take); ``actors``: size of the actor pool (None: two per day, between 4 and 32);
    ``hold_out_actors``: this many drawn actors, and every take with one of them, go to test;
    ``hold_out_types``: every take of these types goes to test (and every long take, which chains
    all types); ``speed``: the simulated devices play this many times faster than real time while
    the full path records them. ``render`` (ground-truth path only): render each scene from a ring
    of ``render_views`` cameras at ``render_size`` x ``render_size`` pixels, every ``render_every``-th
    frame, ``render_spp`` samples per pixel; the render settings are not part of the plan (the
    scenes do not depend on them), the export's manifest records them. ``max_draws`` (ground-truth
    path): the most draws of each interaction scene's variation before its take fails
    (:func:`~dualhuman_builder.sim.scenes.make_scene`); not part of the plan either."""

    takes: int
    seed: int = 0
    types: tuple[str, ...] = SCENE_TYPES
    preset: str = "ideal"
    fps: float = 30.0
    long_share: float = 0.1
    long_duration: float = LONG_DURATION_S
    takes_per_day: int = TAKES_PER_DAY
    actors: int | None = None
    hold_out_actors: int = 0
    hold_out_types: tuple[str, ...] = ()
    speed: float = 1.0
    render: bool = False
    render_size: int = 128
    render_views: int = 4
    render_every: int = 5
    render_spp: int = 4
    max_draws: int = MAX_DRAWS

    def render_settings(self) -> dict[str, Any] | None:
        """The renders' settings (``size``, ``views``, ``every``, ``spp`` and :data:`GROUND_TRUTH_RENDER`),
        None without ``render``; :class:`SynthError` for settings out of range."""
        if not self.render:
            return None
        limits = {"render_size": (16, 4096, "--render-size", "pixels"), "render_views": (1, 64, "--render-views", "views"),
                  "render_every": (1, 10_000, "--render-every", "frames"),
                  "render_spp": (1, 4096, "--render-spp", "samples per pixel")}  # fmt: skip
        for name, (lo, hi, flag, unit) in limits.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise SynthError(f"{name.replace('_', ' ')} {v!r} is out of range", fix=f"pass {flag} from {lo} to {hi} {unit}")
        return {"size": int(self.render_size), "views": int(self.render_views), "every": int(self.render_every),
                "spp": int(self.render_spp), **GROUND_TRUTH_RENDER}  # fmt: skip

    def pool_size(self) -> int:
        return self.actors if self.actors is not None else min(32, max(4, 2 * self.days()))

    def days(self) -> int:
        """How many studio days the takes fill."""
        return -(-int(self.takes) // int(self.takes_per_day))

    def arguments(self) -> dict[str, Any]:
        """The options as the plan records them (the default pool size resolved)."""
        d = {k: v for k, v in asdict(self).items() if not k.startswith("render") and k != "max_draws"}  # how, not what
        d.update(takes=int(self.takes), seed=int(self.seed), hold_out_actors=int(self.hold_out_actors),
                 types=list(self.types), hold_out_types=list(self.hold_out_types), actors=int(self.pool_size()),
                 fps=float(self.fps), long_share=float(self.long_share), long_duration=float(self.long_duration),
                 speed=float(self.speed), takes_per_day=int(self.takes_per_day))  # fmt: skip
        return d


def check_options(o: SynthOptions) -> None:
    """Raise :class:`SynthError` (with a fix) for options no plan can be drawn from."""
    if isinstance(o.takes, bool) or not isinstance(o.takes, (int, np.integer)) or not 1 <= o.takes <= MAX_TAKES:
        raise SynthError(f"a synthetic dataset has 1 to {MAX_TAKES} takes, not {o.takes!r}",
                         fix=f"pass --takes from 1 to {MAX_TAKES}")  # fmt: skip
    if isinstance(o.takes_per_day, bool) or not isinstance(o.takes_per_day, (int, np.integer)) \
            or not 1 <= o.takes_per_day <= 1000:  # fmt: skip
        raise SynthError(f"a studio day has 1 to 1000 takes, not {o.takes_per_day!r}",
                         fix=f"pass --takes-per-day from 1 to 1000 ({TAKES_PER_DAY} by default)")  # fmt: skip
    if isinstance(o.seed, bool) or not isinstance(o.seed, (int, np.integer)) or o.seed < 0:
        raise SynthError(f"the seed must be a whole number >= 0, not {o.seed!r}", fix="pass --seed 0 or another")
    for name in ("types", "hold_out_types"):
        if isinstance(getattr(o, name), str) or not all(isinstance(t, str) for t in getattr(o, name)):
            raise SynthError(f"{name} must be a sequence of type names, not {getattr(o, name)!r}",
                             fix="name them as a list, e.g. ('hug', 'handshake')")  # fmt: skip
    if not o.types:
        raise SynthError("no interaction type to draw from", fix=f"name some of {', '.join(SCENE_TYPES)} with --types")
    for t in (*o.types, *o.hold_out_types):
        if t in (SESSION_TYPE, "calibration"):
            fix = ("long takes come from --long-share" if t == SESSION_TYPE else
                   "make a studio day's calibration take with `dualhuman sim take WS --take CAL --type calibration`")
            raise SynthError(f"{t!r} is not an interaction type to draw", fix=fix)
        if t not in SCENE_TYPES:
            raise SynthError(f"unknown interaction type {t!r}", fix=f"choose from {', '.join(SCENE_TYPES)}")
    if len(set(o.types)) != len(o.types):
        raise SynthError(f"--types names a type twice: {list(o.types)}", fix="name each type once")
    outside = [t for t in o.hold_out_types if t not in o.types]
    if outside:
        raise SynthError(f"held-out types {outside} are not among the drawn types {list(o.types)}",
                         fix="hold out only types named by --types")  # fmt: skip
    if o.preset not in SYNTH_PRESETS:
        raise SynthError(f"unknown device error preset {o.preset!r}", fix=f"choose one of {', '.join(SYNTH_PRESETS)}")
    if not (isinstance(o.fps, (int, float)) and math.isfinite(o.fps) and 1.0 <= o.fps <= 240.0):
        raise SynthError(f"fps {o.fps!r} is out of range", fix="pass --fps between 1 and 240 (30 is the default)")
    if not (isinstance(o.long_share, (int, float)) and 0.0 <= o.long_share <= 1.0):
        raise SynthError(f"--long-share {o.long_share!r} is not a share", fix="pass a number from 0 to 1, e.g. 0.1")
    if not (isinstance(o.long_duration, (int, float)) and MIN_LONG_DURATION_S <= o.long_duration <= 3600.0):
        raise SynthError(f"long takes of {o.long_duration!r} s are out of range",
                         fix=f"pass --long-duration from {MIN_LONG_DURATION_S:g} to 3600 s")  # fmt: skip
    if not (isinstance(o.speed, (int, float)) and 0.1 <= o.speed <= 20.0):
        raise SynthError(f"capture speed {o.speed!r} is out of range", fix="pass --speed from 0.1 to 20")
    if isinstance(o.max_draws, bool) or not isinstance(o.max_draws, (int, np.integer)) or not 1 <= o.max_draws <= 64:
        raise SynthError(f"max draws {o.max_draws!r} is out of range", fix="pass --max-draws from 1 to 64")
    pool = o.pool_size()
    if isinstance(pool, bool) or not isinstance(pool, (int, np.integer)) or not 2 <= pool <= 999:
        raise SynthError(f"an actor pool of {pool!r} cannot make pairs", fix="pass --actors from 2 to 999")
    if isinstance(o.hold_out_actors, bool) or not isinstance(o.hold_out_actors, (int, np.integer)) \
            or not 0 <= o.hold_out_actors < pool:  # fmt: skip
        raise SynthError(f"cannot hold out {o.hold_out_actors} of {pool} actors",
                         fix=f"pass --hold-out-actors from 0 to {pool - 1} (or a larger pool with --actors)")  # fmt: skip


def _draw(rng: np.random.Generator, lo_hi: tuple[float, float], digits: int = 3) -> float:
    return round(float(rng.uniform(*lo_hi)), digits)


def plan_synthetic(options: SynthOptions) -> dict[str, Any]:
    """The plan of ``options`` (JSON-able; the same options give the same plan): ``arguments``,
    ``ranges``, ``actors`` (name, stature m, gender, anny build values, held out), ``takes`` (take,
    sequence, type, seed, actors, tempo, approach distance m or None, duration s, preset, fps,
    split or None, day, device seed, ``mounts_from``: the day's calibration take), ``days`` (day,
    calibration take and its scene seed, actors in order, device seed, preset) and ``split`` (None without hold-outs: the export then draws it). Raises
    :class:`SynthError` for invalid options, and for hold-outs that leave train or test empty."""
    check_options(options)
    o = options
    r_actors, r_takes, r_preset, r_split = (np.random.default_rng(s) for s in np.random.SeedSequence(o.seed).spawn(4))
    n_pool = o.pool_size()
    width = max(2, len(str(n_pool)))
    actors = []
    for i in range(n_pool):
        gender = ("female", "male")[int(r_actors.integers(0, 2))]
        actors.append({"name": f"synth-{i + 1:0{width}d}", "stature_m": _draw(r_actors, STATURE_M[gender]),
                       "gender": gender, **{k: _draw(r_actors, v) for k, v in BUILD.items()}})  # fmt: skip
    n, per_day, n_days = int(o.takes), int(o.takes_per_day), o.days()
    n_long = int(round(o.long_share * n))
    long = set(r_takes.choice(n, n_long, replace=False).tolist()) if n_long else set()
    presets = {"ideal": ["ideal"] * n_days, "realistic": ["realistic"] * n_days}.get(o.preset)
    if presets is None:  # mixed: half the days realistic (rounded down), at drawn places
        presets = ["ideal"] * n_days
        for k in r_preset.permutation(n_days)[: n_days // 2]:
            presets[int(k)] = "realistic"
    days, takes, rounds = [], [], []
    digits = max(3, len(str(n_days)))
    for d in range(n_days):
        pair = [int(i) for i in r_takes.choice(n_pool, 2, replace=False)]
        if tuple(o.types) == ("dance_turn",):  # nothing else to dance: the taller one leads every day
            pair.sort(key=lambda i: -actors[i]["stature_m"])
        day = {"day": f"D{d + 1:0{digits}d}", "calibration_take": f"C{d + 1:0{digits}d}",
               "actors": [actors[i]["name"] for i in pair], "device_seed": int(r_takes.integers(0, 2**31 - 1)),
               "calibration_seed": int(r_takes.integers(0, 2**31 - 1)), "preset": presets[d]}  # fmt: skip
        leader_taller = actors[pair[0]]["stature_m"] >= actors[pair[1]]["stature_m"]
        for k in range(d * per_day, min(n, (d + 1) * per_day)):
            if k in long:
                kind = SESSION_TYPE
            else:
                # shuffled rounds: each type equally often. The taller one leads a dance turn: a day whose
                # first actor is shorter takes the next type, and the turn waits for a day that can dance it
                can = [i for i, t in enumerate(rounds) if t != "dance_turn" or leader_taller]
                while not can:
                    rounds += [o.types[j] for j in r_takes.permutation(len(o.types))]
                    can = [i for i, t in enumerate(rounds) if t != "dance_turn" or leader_taller]
                kind = rounds.pop(can[0])
            seed = int(r_takes.integers(0, 2**31 - 1))
            tempo = _draw(r_takes, TEMPO)
            approach = None
            if kind in APPROACH_M:
                approach = _draw(r_takes, (APPROACH_M[kind] - APPROACH_SPREAD_M, APPROACH_M[kind] + APPROACH_SPREAD_M))
            duration = float(o.long_duration) if kind == SESSION_TYPE else round(NATURAL_DURATION[kind] / tempo, 3)
            takes.append({"take": f"S{k + 1:04d}", "sequence": kind, "type": kind, "seed": seed, "actors": day["actors"],
                          "tempo": tempo, "approach_distance_m": approach, "duration_s": duration,
                          "preset": day["preset"], "fps": float(o.fps), "split": None, "day": day["day"],
                          "device_seed": day["device_seed"], "mounts_from": day["calibration_take"]})  # fmt: skip
        days.append(day)
    held_actors = sorted(actors[int(i)]["name"] for i in r_split.choice(n_pool, o.hold_out_actors, replace=False))
    for a in actors:
        a["held_out"] = a["name"] in held_actors
    split = None
    if held_actors or o.hold_out_types:
        for t in takes:
            out = bool(set(t["actors"]) & set(held_actors)) or t["type"] in o.hold_out_types or (
                t["type"] == SESSION_TYPE and bool(o.hold_out_types))  # a session chains every type
            t["split"] = "test" if out else "train"
        counts = {s: sum(t["split"] == s for t in takes) for s in ("train", "test")}
        for s, other in (("train", "test"), ("test", "train")):
            if not counts[s]:
                fix = ("hold out fewer actors or types, draw more takes (--takes), or a larger actor pool (--actors)"
                       if s == "train" else "hold out more actors or types, or draw more takes (--takes)")
                raise SynthError(f"the hold-outs (actors {held_actors}, types {list(o.hold_out_types)}) put every "
                                 f"one of the {n} takes in {other}: the {s} split would be empty", fix=fix)
        split = {"held_out_actors": held_actors, "held_out_types": list(o.hold_out_types), **counts}
    approach = {t: [round(d - APPROACH_SPREAD_M, 3), round(d + APPROACH_SPREAD_M, 3)] for t, d in APPROACH_M.items()}
    ranges = {"stature_m": {g: list(v) for g, v in STATURE_M.items()}, "build": {k: list(v) for k, v in BUILD.items()},
              "tempo": list(TEMPO), "approach_distance_m": approach, "long_take_types": list(SCENE_TYPES)}  # fmt: skip
    return {"format": PLAN_FORMAT, "version": PLAN_VERSION, "arguments": o.arguments(), "ranges": ranges,
            "not_varied": {"handedness": "fixed by each scene type's choreography (e.g. a right-hand handshake)"},
            "actors": actors, "days": days, "takes": takes, "split": split}  # fmt: skip


def plan_bytes(plan: dict) -> bytes:
    """The plan as ``synth.json`` holds it (sorted keys, so the same plan is the same bytes)."""
    return (json.dumps(plan, indent=1, sort_keys=True) + "\n").encode("utf-8")


def load_plan(ws_root: str | Path) -> dict | None:
    """The plan recorded in ``WS/synth.json``, or None when there is none; :class:`SynthError` when
    the file is not a plan."""
    path = Path(ws_root) / PLAN_FILE
    if not path.exists():
        return None
    try:
        plan = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as e:
        raise SynthError(f"{path} is not a readable synthetic dataset plan ({type(e).__name__})",
                         fix="move it away and run `dualhuman synth` again") from None  # fmt: skip
    if not isinstance(plan, dict) or plan.get("format") != PLAN_FORMAT:
        raise SynthError(f"{path} is not a synthetic dataset plan", fix="move it away and run `dualhuman synth` again")
    if plan.get("version") != PLAN_VERSION or not isinstance(plan.get("arguments"), dict):
        raise SynthError(f"{path} is a plan of version {plan.get('version')}; this toolkit reads version "
                         f"{PLAN_VERSION}", fix="use the toolkit that wrote it, or another workspace")  # fmt: skip
    return plan


def plan_splits(plan: dict) -> dict[str, str]:
    """``{take: "train" | "test"}`` of a plan with hold-outs (empty without: the export draws the split)."""
    return {t["take"]: t["split"] for t in plan["takes"] if t.get("split")}


def record_plan(ws_root: Path, plan: dict) -> None:
    """Write ``plan`` to ``WS/synth.json``, or check that the one there is the same; :class:`SynthError`
    naming the arguments that differ."""
    from dualhuman_builder.fileio import atomic_path

    old = load_plan(ws_root)
    if old is None:
        with atomic_path(ws_root / PLAN_FILE) as tmp:
            tmp.write_bytes(plan_bytes(plan))
        return
    if old == plan:
        return
    was, now = old.get("arguments", {}), plan["arguments"]
    diff = [f"{k} {was.get(k)!r} -> {now.get(k)!r}" for k in sorted(set(was) | set(now)) if was.get(k) != now.get(k)]
    what = "; ".join(diff) if diff else "the same arguments, but another plan (written by another toolkit version)"
    raise SynthError(f"{ws_root / PLAN_FILE} holds the plan of other arguments: {what}",
                     fix="run `dualhuman synth` with the arguments that plan records, or use another workspace")  # fmt: skip


def _scene_params(t: dict) -> dict:
    """The ``scene`` stage's parameters of planned take ``t`` (:class:`~dualhuman_builder.sim.scenes.SceneParams`
    fields); an interaction's duration is its natural length at the tempo (None)."""
    p = {"type": t["type"], "seed": t["seed"], "fps": t["fps"], "tempo": t["tempo"]}
    if t["approach_distance_m"] is not None:
        p["approach_distance"] = t["approach_distance_m"]
    if t["type"] == SESSION_TYPE:
        p["duration"] = t["duration_s"]
    return p


def _register_actors(ws, plan: dict, model, log: Callable[[str], None]) -> dict[str, tuple[tuple, dict]]:
    """Register the plan's actors with their anny shapes (solved from stature, gender and build)
    where the workspace lacks them; :class:`SynthError` for a name registered otherwise. Returns
    ``{name: ((name, stature m, gender), shape)}``."""
    from dualhuman_builder.body.shape import gender_value, shape_for_stature

    known = {a.name: a for a in ws.actors()}
    out = {}
    for a in plan["actors"]:
        build = {k: a[k] for k in BUILD}
        have = known.get(a["name"])
        same = have is not None and have.shape is not None and have.gender == a["gender"] and \
            have.height_m is not None and abs(have.height_m - a["stature_m"]) < 1e-9 and \
            all(abs(float(have.shape.get(k, -1.0)) - v) < 1e-9 for k, v in build.items()) and \
            abs(float(have.shape.get("gender", -1.0)) - gender_value(a["gender"])) < 1e-9  # fmt: skip
        if have is not None and not same:
            raise SynthError(f"actor {a['name']!r} is registered in this workspace with another body than the plan's",
                             fix="use a new workspace for this synthetic dataset")  # fmt: skip
        if have is None:
            shape = shape_for_stature(model, a["stature_m"], a["gender"], **build)
            have = ws.add_actor(a["name"], a["stature_m"], a["gender"], shape=shape, shape_source="synth")
            log(f"actor {a['name']}: {a['stature_m']:.2f} m {a['gender']}, build {build}")
        out[a["name"]] = ((a["name"], float(a["stature_m"]), a["gender"]), dict(have.shape))
    return out


@dataclass
class SynthResult:
    """What :func:`make_synthetic` did: the ``plan``, the takes ``made`` now, the studio days'
    ``calibrations`` (made now or before), ``skipped`` (takes made before), ``failed`` (take -> error: no scene met the quality contract), and the export's
    ``manifest`` (None without one)."""

    plan: dict
    made: list[str] = field(default_factory=list)
    calibrations: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    manifest: dict | None = None
    seconds: float = 0.0


def _describe(t: dict) -> str:
    how = f"tempo {t['tempo']:.2f}"
    if t["approach_distance_m"] is not None:
        how += f", approach {t['approach_distance_m']:.2f} m"
    if t["type"] == SESSION_TYPE:
        how = f"{t['duration_s']:g} s, " + how
    split = f", {t['split']}" if t["split"] else ""
    return f"{t['take']} {t['type']} ({' + '.join(t['actors'])}, {how}, {t['preset']}{split})"


def make_synthetic(workspace: str | Path, options: SynthOptions, *, path: str = "full",
                   export: str | Path | None = None, include_flagged: bool = False, model=None,
                   files: Callable | None = None, log: Callable[[str], None] = print,
                   progress: Callable[[str], None] | None = None) -> SynthResult:  # fmt: skip
    """Plan (:func:`plan_synthetic`) and make a synthetic dataset in ``workspace`` (created if
    missing); see the module docstring for the two ``path`` values. ``export``: the export folder
    (required for ``ground-truth``; with ``full``, the takes fitted so far are exported).
    ``files`` (ground-truth path): ``files(ws, plan, actors, render, log, max_draws=N)`` yields ``(t, made)`` for
    every planned take in plan order, ``made`` as :func:`ground_truth_files` returns it (default: made
    here, one after the other; :func:`dualhuman_builder.batch.synth.make_synthetic` makes them in
    worker processes).
    ``progress`` gets one line per take (default: ``log``), ``log`` the details. A take whose scene
    meets no quality contract is listed in ``failed`` and the others go on. Raises
    :class:`SynthError` for invalid options or when ``WS/synth.json`` holds another plan."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.workspace import Workspace

    t0 = time.perf_counter()
    say = progress or log
    if path not in PATHS:
        raise SynthError(f"unknown path {path!r}", fix=f"choose one of {', '.join(PATHS)}")
    if path == "ground-truth" and export is None:
        raise SynthError("the ground-truth path writes an export: it needs its folder",
                         fix="pass --export OUT (a new or empty folder, or an earlier export to update)")  # fmt: skip
    plan = plan_synthetic(options)
    render = options.render_settings()
    if options.max_draws != MAX_DRAWS and path != "ground-truth":
        raise SynthError("--max-draws bounds the ground-truth path's scene draws; the full path's scene stage draws "
                         f"up to {MAX_DRAWS}", fix="pass --path ground-truth, or leave --max-draws out")  # fmt: skip
    if render is not None and path != "ground-truth":
        raise SynthError("--render renders the ground-truth path's scenes; the full path renders its fitted takes in "
                         "`dualhuman run`", fix="pass --path ground-truth, or leave --render out")  # fmt: skip
    root = Path(workspace)
    result = SynthResult(plan)
    with Workspace.init(root) as ws:
        record_plan(ws.root, plan)
        if path == "full":
            ws.add_rig(RIGS_DIR / "sim.toml")
        model = model or get_body_model()
        actors = _register_actors(ws, plan, model, log)
        n = len(plan["takes"])
        if path == "full":
            days = {d["day"]: d for d in plan["days"]}
            for k, t in enumerate(plan["takes"], 1):
                day = days.pop(t["day"], None)
                if day is not None:  # the day's calibration take comes before its first take
                    _make_calibration(ws, day, actors, options, model, log, say, result)
                _make_full(ws, t, actors, options, model, log, say, f"[{k}/{n}]", result)
            if export is not None:
                result.manifest = export_fitted(ws, export, plan, include_flagged=include_flagged, log=log)
        else:
            items = []
            if files is not None:
                made = files(ws, plan, actors, render, log, max_draws=options.max_draws)
            else:
                made = ((t, ground_truth_files(ws.root, t, [actors[a][1] for a in t["actors"]], model, log, render,
                                               max_draws=options.max_draws)) for t in plan["takes"])  # fmt: skip
            for k, (t, m) in enumerate(made, 1):
                item = _ground_truth_item(ws, t, m, say, f"[{k}/{n}]", result, render=render)
                if item is not None:
                    items.append(item)
            result.manifest = _export_ground_truth(ws, items, export, plan, result, log, render=render)
    result.seconds = time.perf_counter() - t0
    return result


def _make_full(ws, t: dict, actors: dict, options: SynthOptions, model, log, say, counter: str,
               result: SynthResult) -> None:  # fmt: skip
    """The ``scene``, ``devices`` and ``capture`` stages of planned take ``t``, and its labels from the scene."""
    from dualhuman_builder.sim.stage import simulate_take

    take = t["take"]
    meta = {"simulated": True, "calibration": False, "preset": t["preset"], "speed": float(options.speed),
            "device_seed": t["device_seed"], "mounts_from": t["mounts_from"],
            "synth": {"seed": options.seed, "type": t["type"], "split": t["split"], "day": t["day"]}}  # fmt: skip
    if take in ws.takes():
        have = ws.take(take)
        if have.meta.get("synth") != meta["synth"] or list(have.actors) != list(t["actors"]):
            raise SynthError(f"take {take!r} exists in this workspace and is not this plan's",
                             fix="use a new workspace for this synthetic dataset")  # fmt: skip
    else:
        ws.add_take(take, rig="sim", actors=list(t["actors"]), meta=meta)
    pair = [actors[a][0] for a in t["actors"]]
    shapes = [actors[a][1] for a in t["actors"]]
    t1 = time.perf_counter()
    try:
        ran = simulate_take(ws, take, t["sequence"], _scene_params(t), pair, shapes, speed=float(options.speed),
                            model=model, log=log, preset=t["preset"], device_seed=t["device_seed"])  # fmt: skip
    except ValueError as e:  # no draw met the contract (SceneContractError), or the scene refused its parameters
        result.failed[take] = getattr(e, "message", str(e))
        say(f"{counter} {_describe(t)}: FAILED: {result.failed[take]}")
        return
    _annotate_from_scene(ws, take, t)
    if all(r.skipped for r in ran.values()):
        result.skipped.append(take)
        say(f"{counter} {_describe(t)}: made before")
    else:
        result.made.append(take)
        say(f"{counter} {_describe(t)}: made in {time.perf_counter() - t1:.1f} s")


def _make_calibration(ws, day: dict, actors: dict, options: SynthOptions, model, log, say,
                      result: SynthResult) -> None:  # fmt: skip
    """The studio day's calibration take (a bow, a twist, a turn on the spot: the ``calibration``
    scene) with the day's pair and device draw; its sync gives the day's takes their tracker mounts."""
    from dualhuman_builder.sim.stage import simulate_take

    take = day["calibration_take"]
    meta = {"simulated": True, "calibration": True, "preset": day["preset"], "speed": float(options.speed),
            "device_seed": day["device_seed"], "synth": {"seed": options.seed, "type": "calibration", "day": day["day"]}}
    if take in ws.takes():
        have = ws.take(take)
        if have.meta.get("synth") != meta["synth"] or list(have.actors) != list(day["actors"]):
            raise SynthError(f"take {take!r} exists in this workspace and is not this plan's",
                             fix="use a new workspace for this synthetic dataset")  # fmt: skip
    else:
        ws.add_take(take, rig="sim", actors=list(day["actors"]), meta=meta)
    params = {"type": "calibration", "seed": day["calibration_seed"], "fps": float(options.fps)}
    t1 = time.perf_counter()
    try:
        ran = simulate_take(ws, take, "calibration", params, [actors[a][0] for a in day["actors"]],
                            [actors[a][1] for a in day["actors"]], speed=float(options.speed), model=model, log=log,
                            preset=day["preset"], device_seed=day["device_seed"])  # fmt: skip
    except ValueError as e:
        result.failed[take] = getattr(e, "message", str(e))
        say(f"day {day['day']}: calibration take {take}: FAILED: {result.failed[take]}")
        return
    done = all(r.skipped for r in ran.values())
    result.calibrations.append(take)
    say(f"day {day['day']}: calibration take {take} ({' + '.join(day['actors'])}, {day['preset']}): "
        + ("made before" if done else f"made in {time.perf_counter() - t1:.1f} s"))


def _annotate_from_scene(ws, take: str, t: dict) -> None:
    """Store the scene's labels and texts as the take's annotation (once), with actor 0 as the
    actor of a one-sided type (:data:`ONE_SIDED`)."""
    from dualhuman_builder.labels import Annotation, check_annotation, load_vocabulary
    from dualhuman_builder.sim.stage import SCENE, SCENE_ANNOTATOR, SEQUENCE_FILE
    from dualhuman_builder.tracks import InteractionSequence

    if ws.annotations(take):
        return
    gt = InteractionSequence.load(SCENE.artifact(ws, take, SEQUENCE_FILE, t["sequence"]))
    actor = t["actors"][0] if t["type"] in ONE_SIDED else None
    ann = Annotation(take, t["sequence"], SCENE_ANNOTATOR, tuple(gt.labels), tuple(gt.text), actor=actor,
                     symmetric=False if actor else None)  # fmt: skip
    ws.annotate([check_annotation(ann, load_vocabulary(ws.root), ws.take(take).actors)])


def ground_truth_files(root: str | Path, t: dict, shapes: list[dict], model=None, log: Callable[[str], None] = print,
                       render: dict | None = None, max_draws: int = MAX_DRAWS) -> dict[str, Any]:  # fmt: skip
    """Make planned take ``t``'s files of the ground-truth path under the workspace ``root``: its
    scene (``WS/synth/scenes/TAKE-gN.npz``, kept when made before with the same parameters) and,
    with ``render``, its render (:func:`_render_ground_truth`). ``shapes``: the pair's anny
    phenotypes, in the take's actor order. Files only, no catalog: so that worker processes can
    make many takes at once (:mod:`dualhuman_builder.batch.synth`). Returns ``{"take", "generated"
    (bool), "scene_s", "render_s"}`` (``render_s`` None when not rendered now), or with ``failed``
    (the reason) when no draw met the scene's quality contract or the scene refused its parameters.
    A scene's generation is deterministic, so such a failure is recorded beside the scene
    (``TAKE-gN.failed.json``, with the parameters and ``max_draws``) and answered again, without
    drawing, until it is asked for with other parameters or more draws."""
    from dualhuman_builder.errors import FormatError
    from dualhuman_builder.sim.generate import generate_scene
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION, Scene, SceneParams, _params_dict

    take, root = t["take"], Path(root)
    params = SceneParams(shapes=(dict(shapes[0]), dict(shapes[1])), names=tuple(t["actors"]), **_scene_params(t))
    file = root / SCENES_DIR / f"{take}-g{GENERATOR_VERSION}.npz"  # another generator makes other scenes
    t1 = time.perf_counter()
    asked = json.loads(json.dumps(_params_dict(params)))  # as a file stores them
    scene = None
    if file.exists():
        try:
            scene = Scene.load(file)
        except (FormatError, OSError, ValueError, KeyError):
            scene = None
        if scene is not None and _params_dict(scene.params) != asked:
            scene = None
    out: dict[str, Any] = {"take": take, "generated": scene is None, "scene_s": 0.0, "render_s": None}
    if scene is None:
        memo = file.with_name(f"{file.stem}.failed.json")
        try:
            before = json.loads(memo.read_text())
        except (OSError, ValueError):
            before = None
        if isinstance(before, dict) and before.get("params") == asked and before.get("max_draws", 0) >= max_draws:
            return {**out, "failed": f"{before.get('error')} (failed before: {memo.name}; delete it to draw again)"}
        if model is None:
            from dualhuman_builder.body.model import get_body_model

            model = get_body_model()
        try:
            scene = generate_scene(params, model=model, log=log, max_draws=max_draws)
        except ValueError as e:  # no draw met the contract (SceneContractError), or the scene refused its parameters
            error = getattr(e, "message", str(e))
            memo.parent.mkdir(parents=True, exist_ok=True)
            memo.write_text(json.dumps({"params": asked, "max_draws": max_draws, "error": error}, indent=1))
            return {**out, "failed": error}
        file.parent.mkdir(parents=True, exist_ok=True)
        scene.save(file)
        memo.unlink(missing_ok=True)  # made with more draws than a record of failure had
    out["scene_s"] = time.perf_counter() - t1
    if render is not None:
        seq = Scene.load(file).sequence
        out["render_s"] = _render_ground_truth(root, t, seq, render, log)[1]
    return out


def _ground_truth_item(ws, t: dict, made: dict, say, counter: str, result: SynthResult, render: dict | None = None):
    """Planned take ``t``'s :class:`~dualhuman_builder.export.items.ExportItem` from its files
    (``made``: :func:`ground_truth_files`'s answer), with its contacts computed by the contacts
    stage's own code; None (the take in ``result.failed``) when its scene was not made."""
    from dualhuman_builder.contacts.compute import compute_contacts
    from dualhuman_builder.export.items import ExportItem
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION, Scene

    take = t["take"]
    if "failed" in made:
        result.failed[take] = made["failed"]
        say(f"{counter} {_describe(t)}: FAILED: {made['failed']}")
        return None
    file = ws.root / SCENES_DIR / f"{take}-g{GENERATOR_VERSION}.npz"
    contacts = compute_contacts(Scene.load(file).sequence, workers=1)
    seq = Scene.load(file).sequence  # without the vertices the contacts cached: only poses stay in memory until the export
    render_dir, rendered = None, ""
    if render is not None:
        render_dir = ws.root / RENDERS_DIR / f"{take}-g{GENERATOR_VERSION}"
        fresh = made.get("render_s")
        rendered = f", rendered in {fresh:.1f} s" if fresh is not None else ", rendered before"
    (result.made if made["generated"] else result.skipped).append(take)
    say(f"{counter} {_describe(t)}: " + (f"made in {made['scene_s']:.1f} s" if made["generated"] else "made before")
        + rendered)
    roles = ("actor", "reactor") if t["type"] in ONE_SIDED else None
    drawn = {k: t[k] for k in ("type", "seed", "tempo", "approach_distance_m", "duration_s", "preset")}
    meta = {"source": "ground-truth", "take": take, "synth": drawn}
    if render is not None:
        meta["render"] = {**render, "jitter_seed": int(t["seed"])}
    return ExportItem(take, seq, subjects=tuple(t["actors"]), roles=roles, contacts=contacts, meta=meta,
                      render_dir=render_dir)  # fmt: skip


def _render_ground_truth(root: Path, t: dict, seq, render: dict, log) -> tuple[Path, float | None]:
    """Render planned take ``t``'s ground-truth ``seq`` into ``WS/synth/renders/TAKE-gN`` with the
    settings ``render`` (:meth:`SynthOptions.render_settings`): a ring of ``views`` cameras around the
    pair (:func:`~dualhuman_builder.render.stage.stage_cameras`, jittered with the take's scene seed),
    every ``every``-th frame. Returns ``(folder, seconds)``; seconds is None when the folder already
    holds a finished render of the same sequence and settings (:data:`RENDER_RECORD`). A render cut
    short resumes; a folder of other settings is rendered afresh."""
    import hashlib
    import shutil

    from dualhuman_builder.render.stage import render_sequence, select_frames, stage_cameras
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION

    out = Path(root) / RENDERS_DIR / f"{t['take']}-g{GENERATOR_VERSION}"
    h = hashlib.sha256(json.dumps({**render, "jitter_seed": int(t["seed"])}, sort_keys=True).encode())
    for a in seq.actors:
        for arr in (a.pose, a.transl, a.shape):
            h.update(np.ascontiguousarray(arr).tobytes())
    key = h.hexdigest()
    record = out / RENDER_RECORD
    try:
        doc = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        doc = None
    if isinstance(doc, dict) and doc.get("key") == key and doc.get("complete") is True:
        return out, None
    if out.exists() and not (isinstance(doc, dict) and doc.get("key") == key):
        shutil.rmtree(out)  # another sequence or other settings: none of its files may be exported
    out.mkdir(parents=True, exist_ok=True)
    record.write_text(json.dumps({"key": key, "complete": False}))
    t1 = time.perf_counter()
    frames = select_frames(seq.num_frames, render["every"])
    cams = stage_cameras(seq, render["views"], render["size"], render["radius_m"], render["height_m"], render["fov_deg"],
                         jitter_seed=int(t["seed"]), frames=frames)  # fmt: skip
    render_sequence(seq, out, cams, template=render["template"], spp=render["spp"], every=render["every"], log=log)
    record.write_text(json.dumps({"key": key, "complete": True, "settings": render}))
    return out, time.perf_counter() - t1


def _summary(plan: dict, result: SynthResult | None = None) -> dict:
    """The manifest's ``synth`` entry: the plan's arguments and split, and the takes that failed."""
    out = {"plan": PLAN_FILE, "arguments": plan["arguments"], "split": plan["split"]}
    if result is not None:
        out["failed"] = dict(sorted(result.failed.items()))
    return out


def _export_ground_truth(ws, items: list, export, plan: dict, result: SynthResult, log,
                         render: dict | None = None) -> dict:  # fmt: skip
    """Export the ground-truth ``items`` with the plan's split (drawn with its seed without hold-outs),
    marked ``source: ground-truth``; with ``render``, the renders are expected and the manifest's
    ``synth.render`` records their settings (each sequence's ``meta.render`` adds its ring's jitter seed)."""
    from dualhuman_builder.export.writer import export_dataset
    from dualhuman_builder.labels import load_vocabulary

    if not items:
        raise SynthError(f"no scene of the {len(plan['takes'])} planned takes met the quality contract: nothing to "
                         "export", fix="try another --seed or a higher --fps")  # fmt: skip
    ids = {it.seq_id for it in items}
    splits = {k: v for k, v in plan_splits(plan).items() if k in ids}
    summary = _summary(plan, result)
    if render is not None:
        summary["render"] = {**render, "jitter": "each take's ring is jittered with its scene seed (sequence meta.render)"}
    expect = GROUND_TRUTH_EXPECT + (("renders",) if render is not None else ())
    return export_dataset(items, export, seed=plan["arguments"]["seed"], progress=log,
                          vocabulary=load_vocabulary(ws.root), expect=expect, splits=splits or None,
                          extra={"source": "ground-truth", "synth": summary})  # fmt: skip


def export_fitted(ws, export, plan: dict, *, include_flagged: bool = False, log: Callable[[str], None] = print) -> dict:
    """Export the plan's takes that have a complete fit (as ``dualhuman export`` does, leaving out
    those the quality gates flagged unless ``include_flagged``) with the plan's split; every
    sequence's ``meta.source`` and the manifest's ``source`` say ``"fitted"``. Returns the manifest
    (plus ``left_out``: planned takes without a fit)."""
    from dualhuman_builder.export.collect import quality_verdicts, workspace_items
    from dualhuman_builder.export.writer import export_dataset
    from dualhuman_builder.labels import load_vocabulary

    names = [t["take"] for t in plan["takes"] if t["take"] in ws.takes()]
    vocabulary = load_vocabulary(ws.root)
    items, left_out = workspace_items(ws, names, vocabulary)
    if left_out:
        log(f"WARNING: {len(left_out)} planned take(s) without a complete fit, left out: {left_out[:10]}"
            f"{' ...' if len(left_out) > 10 else ''} (`dualhuman run {ws.root}` fits them)")  # fmt: skip
    if not items:
        raise SynthError("no take of the plan has a complete fit: nothing to export", path=ws.root,
                         fix=f"run `dualhuman run {ws.root}` first")  # fmt: skip
    items, quality = quality_verdicts(ws, items, include_flagged, log)
    if not items:
        raise SynthError(f"every fitted take of the plan is flagged by the quality gates: "
                         f"{sorted(quality['left_out'])}", path=ws.root,
                         fix="look at them (`dualhuman review WS`), or export them with --include-flagged")  # fmt: skip
    for it in items:
        it.meta = {**it.meta, "source": "fitted"}
    ids = {it.seq_id for it in items}
    splits = {k: v for k, v in plan_splits(plan).items() if k in ids}
    manifest = export_dataset(items, export, seed=plan["arguments"]["seed"], progress=log, vocabulary=vocabulary,
                              splits=splits or None,
                              extra={"source": "fitted", "quality": quality, "synth": _summary(plan)})  # fmt: skip
    manifest["left_out"] = left_out
    return manifest


def describe_plan(plan: dict, path: str = "full") -> list[str]:
    """A few lines about a plan: takes per type, preset and studio days (``path`` full only: the
    ground-truth path has no devices), split, the actor pool."""
    takes = plan["takes"]
    by_type: dict[str, int] = {}
    for t in takes:
        by_type[t["type"]] = by_type.get(t["type"], 0) + 1
    presets = {p: sum(t["preset"] == p for t in takes) for p in ("ideal", "realistic")}
    g = {s: sum(a["gender"] == s for a in plan["actors"]) for s in ("female", "male")}
    stat = [a["stature_m"] for a in plan["actors"]]
    lines = [f"{len(takes)} takes: " + ", ".join(f"{k} {v}" for k, v in sorted(by_type.items()))]
    if path == "full":
        lines.append(f"devices: {presets['ideal']} ideal, {presets['realistic']} realistic, over {len(plan['days'])} "
                     f"studio day(s), each with its calibration take")  # fmt: skip
    lines.append(f"actors: {len(plan['actors'])} ({g['female']} female, {g['male']} male), "
                 f"{min(stat):.2f}-{max(stat):.2f} m")  # fmt: skip
    if plan["split"]:
        s = plan["split"]
        lines.append(f"split: {s['train']} train, {s['test']} test (held out: actors {s['held_out_actors'] or 'none'}, "
                     f"types {s['held_out_types'] or 'none'})")  # fmt: skip
    else:
        lines.append("split: drawn by the export (no hold-outs)")
    return lines
