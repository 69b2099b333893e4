"""Ground-truth two-person interaction scenes.

``make_scene(SceneParams(type="handshake", seed=3))`` builds two anny bodies of different shapes
performing a close interaction, from keyframed controls (pelvis, footsteps, palm targets, gaze)
solved with closed-form IK (:mod:`.performer`), then corrects every contact against the meshes:
for each frame of a contact phase the palms are moved along the contact normal until the measured
mesh gap is :data:`CONTACT_GAP` (so hands meet without passing through each other). The result
holds the :class:`~dualhuman_builder.tracks.InteractionSequence`, the signed distances of every
vertex of each body to the other body (the ground-truth contacts), the phases of the motion and
the stance masks of the feet. Every returned scene meets the quality contract
(:func:`contract_failures`): a draw of the variation that breaks it is repaired where its type
knows how, or drawn again (:func:`make_scene`), and none is returned broken.

Layout: actor 0 starts at the origin facing +Z, actor 1 ``approach_distance`` metres away facing
it (except where a type says otherwise); the floor is y = 0.

Types (:data:`SCENE_TYPES`): ``handshake``, ``hug``, ``high_five``, ``push``, ``pat_on_back``,
``dance_turn``; and ``calibration`` (:data:`CALIBRATION_TYPE`), the calibration motion of a studio day
with no interaction. Each is a choreography function below; all share the same timing vocabulary
(:mod:`.timeline`) and are scaled by ``tempo``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.sim.ik import normalize, rot_y
from dualhuman_builder.sim.performer import SIDES, ArmTrack, Controls, FootTrack, Performer
from dualhuman_builder.sim.timeline import Step, foot_track, keyframes, window

SCENE_TYPES = ("handshake", "hug", "high_five", "push", "pat_on_back", "dance_turn")
#: The calibration motion of a studio day (:func:`calibration`): no interaction, each actor on their own
#: turns every tracked segment, so the trackers' mounts can be solved and carried over to the
#: day's other takes (``dualhuman sync --mounts-from``). Not one of :data:`SCENE_TYPES`.
CALIBRATION_TYPE = "calibration"
#: A long take that chains the interactions with walking and idling between them
#: (:mod:`dualhuman_builder.sim.session`; ``duration`` default 60 s). Not one of :data:`SCENE_TYPES`.
SESSION_TYPE = "session"
#: Every type :class:`SceneParams` accepts.
ALL_TYPES = (*SCENE_TYPES, CALIBRATION_TYPE, SESSION_TYPE)
#: Gap (m) the contact correction aims for between touching surfaces.
CONTACT_GAP = 0.003
#: Distance (m) under which a vertex counts as in contact (the contacts stage's default).
CONTACT_THRESHOLD = 0.02
#: Largest palm move (m) per correction pass: far-off gaps are closed over several passes, so a
#: palm never overshoots into the partner.
MAX_CORRECTION_STEP = 0.02
#: Time (s) over which a contact's correction eases in before its contact frames and out after
#: them (on its guard frames), instead of switching on and off in one frame.
CONTACT_EASE_S = 0.4
#: Time (s) the torsos' correction is held at its contact-frame value after (and before) the
#: embrace, before it eases: the arms, still wrapped when the torsos start to part, need it.
TORSO_HOLD_S = 0.2
#: Most contact-correction passes (each re-measures only the frames that have not settled).
MAX_CORRECTION_PASSES = 14
#: Most frames per second the contact correction measures after its first pass, away from frames
#: found too close (the gap errors between them are interpolated in time; every frame is corrected).
MEASURE_FPS = 15.0
#: Gap error (m) within which a frame whose error changes sign from pass to pass is left as it is.
GAP_TOLERANCE = 0.003
#: Band (m) within which signed distances are computed and stored; NaN beyond.
DISTANCE_BAND = 0.05
#: Most draws of a scene's variation :func:`make_scene` tries before it gives up on the quality
#: contract (each a full generation; a draw breaks it rarely, so the chance that all of them do is small).
MAX_DRAWS = 8
#: torch CPU threads while a scene is generated: its body-model calls are many small batches, which
#: run faster on one thread than split over a loaded machine's cores (``docs/design/scenes.md``; the same
#: answer on any machine); a process generating scenes in parallel runs one per core instead.
TORCH_THREADS = 1
SCENE_VERSION = 1
#: Version of the generator: bumped whenever the same parameters generate different scenes, so
#: that cached ``scene`` stages recompute (the changes are in CHANGELOG.md).
GENERATOR_VERSION = 5


class SceneContractError(DualhumanError, ValueError):
    """No draw of a scene's variation met the quality contract (:func:`make_scene`). A ValueError
    too, as every other refusal of a scene's parameters is."""


@dataclass
class SceneParams:
    """What to generate. ``shapes``: two anny phenotype dicts, or None to draw two different
    adults from ``seed``; ``approach_distance``: pelvis-to-pelvis metres at the start (None: the
    type's default); ``tempo``: >1 is faster; ``duration``: seconds (None: the type's natural
    length at this tempo; longer pads the end with standing, shorter is an error); ``names``: the
    actors' names in the sequence."""

    type: str = "handshake"
    seed: int = 0
    shapes: tuple[dict, dict] | None = None
    approach_distance: float | None = None
    tempo: float = 1.0
    duration: float | None = None
    fps: float = 30.0
    names: tuple[str, str] = ("actor0", "actor1")

    def __post_init__(self):
        if self.type not in ALL_TYPES:
            raise ValueError(f"unknown scene type {self.type!r}; choose one of {', '.join(ALL_TYPES)}")
        if not self.tempo > 0 or not self.fps > 0:
            raise ValueError("tempo and fps must be positive")


@dataclass
class ContactSpec:
    """A contact the correction enforces: ``actor``'s ``side`` palm against the partner (its
    ``partner_side`` palm, or its body when None), or with ``side`` None the two torsos (head,
    neck and trunk), whose gap the pelvises close or open. On ``frames (T,)`` the gap is brought to
    :data:`CONTACT_GAP`; on ``guard (T,)`` frames (approach and release) the correction eases in
    and out over :data:`CONTACT_EASE_S` and only keeps the gap from closing below it. Palms move
    along ``normal (T, 3)``, the direction from this palm towards the partner surface; the
    per-frame offsets (m, ``(T,)``) are smoothed so the correction adds no jerk."""

    actor: int
    side: str | None  # None: the two torsos, corrected by moving both pelvises
    frames: np.ndarray
    normal: np.ndarray
    partner_side: str | None = None
    guard: np.ndarray | None = None
    offset: np.ndarray | None = field(default=None, repr=False)
    base: tuple | None = field(default=None, repr=False)
    settled: np.ndarray | None = field(default=None, repr=False)
    floor: np.ndarray | None = field(default=None, repr=False)
    left: np.ndarray | None = field(default=None, repr=False)
    last: tuple | None = field(default=None, repr=False)


@dataclass
class Choreography:
    controls: list[Controls]
    stance: list[dict[str, np.ndarray]]
    phases: dict[str, tuple[float, float]]
    contact_phases: list[tuple[float, float]]
    contacts: list[ContactSpec]
    labels: tuple[str, ...]
    text: tuple[str, ...]


@dataclass
class Scene:
    """A generated scene: the sequence, ground-truth distances and the choreography's timing.

    ``distances[i]`` ``(T, V)`` float16: signed distance (m) of each vertex of actor ``i`` to the
    other body's surface, negative inside (by the winding number, however deep), NaN farther
    outside than :data:`DISTANCE_BAND`; ``stance[i][side]``
    ``(T,)`` bool: that foot is planted; ``phases``: name -> (start, end) seconds;
    ``contact_phases``: intervals (s) during which the bodies must touch.
    """

    params: SceneParams
    sequence: Any  # InteractionSequence
    distances: tuple[np.ndarray, np.ndarray]
    stance: list[dict[str, np.ndarray]]
    phases: dict[str, tuple[float, float]]
    contact_phases: list[tuple[float, float]]
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.sequence.num_frames) / self.sequence.fps

    def contact_labels(self, threshold: float = CONTACT_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
        """Per-vertex contact ``(T, V)`` bool for each actor: distance below ``threshold`` or inside."""
        return tuple(np.nan_to_num(d.astype(np.float32), nan=np.inf) < threshold for d in self.distances)

    def contact_phase_mask(self) -> np.ndarray:
        t = self.times
        m = np.zeros(len(t), dtype=bool)
        for a, b in self.contact_phases:
            m |= (t >= a) & (t <= b)
        return m

    def save(self, path: str | Path) -> Path:
        from dualhuman_builder.fileio import save_npz

        arrays = dict(self.sequence.to_arrays("seq."))
        for i in (0, 1):
            arrays[f"gt.distances{i}"] = self.distances[i]
            for s in SIDES:
                arrays[f"gt.stance{i}{s}"] = self.stance[i][s]
        meta = {"sequence": self.sequence.to_meta(), "params": _params_dict(self.params), "phases": self.phases,
                "contact_phases": self.contact_phases, "stats": self.stats}  # fmt: skip
        return save_npz(path, "Scene", SCENE_VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | Path) -> "Scene":
        from dualhuman_builder.fileio import load_npz
        from dualhuman_builder.tracks import InteractionSequence

        arrays, meta = load_npz(path, "Scene", SCENE_VERSION)
        seq = InteractionSequence.from_arrays(arrays, meta["sequence"], "seq.")
        p = dict(meta["params"])
        p["shapes"] = tuple(p["shapes"]) if p.get("shapes") else None
        p["names"] = tuple(p.get("names", ("actor0", "actor1")))
        return cls(SceneParams(**p), seq, (arrays["gt.distances0"], arrays["gt.distances1"]),
                   [{s: arrays[f"gt.stance{i}{s}"] for s in SIDES} for i in (0, 1)],
                   {k: tuple(v) for k, v in meta["phases"].items()}, [tuple(x) for x in meta["contact_phases"]],
                   meta.get("stats", {}))  # fmt: skip


def _params_dict(p: SceneParams) -> dict:
    return {"type": p.type, "seed": p.seed, "shapes": list(p.shapes) if p.shapes else None,
            "approach_distance": p.approach_distance, "tempo": p.tempo, "duration": p.duration, "fps": p.fps,
            "names": list(p.names)}  # fmt: skip


# ============================================================================ generation
def random_adult_shapes(model, rng: np.random.Generator) -> tuple[dict, dict]:
    """Two different adults: statures 1.55-1.92 m, random gender, build and age (young to middle)."""
    from dualhuman_builder.body.shape import shape_for_stature

    shapes = []
    for _ in range(2):
        gender = float(rng.integers(0, 2))
        stature = rng.uniform(1.58, 1.92) if gender == 0.0 else rng.uniform(1.55, 1.80)
        shapes.append(shape_for_stature(model, float(stature), gender, age=float(rng.uniform(0.62, 0.85)),
                                        muscle=float(rng.uniform(0.3, 0.7)), weight=float(rng.uniform(0.3, 0.7)),
                                        proportions=float(rng.uniform(0.35, 0.65))))  # fmt: skip
    return shapes[0], shapes[1]


def _stature_of(model, shape) -> float:
    from dualhuman_builder.body.shape import stature

    return stature(model, model.shape_tensor(shape))


def make_scene(params: SceneParams, model=None, log: Callable[[str], None] | None = None,
               max_draws: int = MAX_DRAWS) -> Scene:  # fmt: skip
    """Generate the scene ``params`` describes (deterministic for a given seed), meeting the quality
    contract (:func:`contract_failures`) or raising :class:`SceneContractError`.

    The variation (the two adults, unless ``params.shapes`` gives them, and each choreography's
    random spacing and timing) is drawn from ``seed``; a draw whose scene breaks the contract is
    replaced by the next, from an rng derived from ``(seed, draw)``, up to ``max_draws`` draws.
    ``stats["draws"]`` records how many it took (1: the seed's own draw). Runs on
    :data:`TORCH_THREADS` torch threads (restored after)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(TORCH_THREADS)
    try:
        return _make_scene(params, model, log, max_draws)
    finally:
        torch.set_num_threads(threads)


def _make_scene(params: SceneParams, model, log: Callable[[str], None] | None, max_draws: int) -> Scene:
    from dualhuman_builder.body.model import get_body_model

    if params.type == SESSION_TYPE:
        raise ValueError("a session is made of interaction scenes: make it with "
                         "dualhuman_builder.sim.generate.generate_scene (or sim.session.make_session)")  # fmt: skip
    if max_draws < 1:
        raise ValueError(f"max_draws must be at least 1, not {max_draws}")
    t_start = time.perf_counter()
    model = model or get_body_model()
    broken = []
    for draw in range(max_draws):
        seed = params.seed if draw == 0 else [params.seed, draw]
        scene = _generate(params, model, np.random.default_rng(seed), log)
        failures = contract_failures(scene.stats)
        repaired = False
        if failures and _repairs(params.type):  # the same draw again, with the choreography's repair
            if log:
                log(f"draw {draw + 1} breaks the quality contract ({'; '.join(failures)}); repairing it")
            scene = _generate(params, model, np.random.default_rng(seed), log, repair=True)
            failures, repaired = contract_failures(scene.stats), True
        if not failures:
            scene.stats = {"generation_s": round(time.perf_counter() - t_start, 2), "draws": draw + 1,
                           "repaired": repaired, **scene.stats}  # fmt: skip
            return scene
        broken.append(failures)
        if log:
            log(f"draw {draw + 1} of {max_draws} breaks the quality contract ({'; '.join(failures)}); drawing again")
    raise SceneContractError(
        f"no {params.type} scene for seed {params.seed} at {params.fps:g} fps met the quality contract in {max_draws} "
        f"draws (" + " | ".join(f"draw {k + 1}: {'; '.join(f)}" for k, f in enumerate(broken)) + ")",
        fix="try another seed, other shapes or a higher fps, or allow more draws (make_scene(..., max_draws=N))")


def _repairs(kind: str) -> bool:
    """Whether the choreography of ``kind`` takes ``repair=True``: a variant of its motion that fixes
    what breaks the contract on some draws, tried on a draw that breaks it before drawing again."""
    import inspect

    return "repair" in inspect.signature(CHOREOGRAPHIES[kind]).parameters


def _generate(params: SceneParams, model, rng: np.random.Generator, log: Callable[[str], None] | None,
              repair: bool = False) -> Scene:  # fmt: skip
    """One draw of the scene: the shapes (unless given) and the choreography's variation from ``rng``
    (``repair``: the choreography's repaired variant, see :func:`_repairs`), then IK, contact
    correction and penetration repair; ``stats`` holds :func:`quality_summary`."""
    shapes = params.shapes or random_adult_shapes(model, rng)
    if params.type == "dance_turn" and params.shapes is None:
        shapes = tuple(sorted(shapes, key=lambda s: -_stature_of(model, s)))  # the taller one leads
    performers = [Performer(model, s) for s in shapes]
    natural = NATURAL_DURATION[params.type] / params.tempo
    duration = params.duration if params.duration is not None else natural
    if duration < natural - 1e-9:
        raise ValueError(f"a {params.type} at tempo {params.tempo} lasts {natural:.2f} s; duration {duration} s is too short")
    t = np.arange(int(round(duration * params.fps))) / params.fps
    extra = {"repair": True} if repair else {}
    chor = CHOREOGRAPHIES[params.type](t * params.tempo, performers, params, rng, **extra)
    chor = _rescale_time(chor, params.tempo)

    poses = [p.solve(c) for p, c in zip(performers, chor.controls)]
    _make_reachable(performers, chor, poses)
    for it in range(MAX_CORRECTION_PASSES):
        worst, what, measured = _correct_contacts(model, performers, chor, params.fps)
        if log:
            log(f"contact correction pass {it + 1}: largest gap error {1000 * worst:.1f} mm ({what or 'none'}), "
                f"{measured} frames measured")
        if worst < 5e-4:
            break
    poses = [p.solve(c) for p, c in zip(performers, chor.controls)]
    seq = _sequence(model, performers, poses, chor, params)
    distances = ground_truth_distances(seq)
    # elbow swivels out of the partner; passes after the first only while the contract's penetration
    # is still broken (each starts from the swivels the earlier ones chose)
    from dualhuman_builder.sim.quality import penetration_depth

    for k in range(SWIVEL_PASSES):
        if k and penetration_depth(distances).max() <= MAX_PENETRATION_M:
            break
        poses, changed = _resolve_by_swivel(model, performers, chor, poses, seq, distances, log)
        if not len(changed):
            break
        seq = _sequence(model, performers, poses, chor, params)
        distances = ground_truth_distances(seq, frames=changed, previous=distances)
    scene = Scene(params, seq, distances, chor.stance, chor.phases, chor.contact_phases)
    scene.stats = quality_summary(scene)
    return scene


def _sequence(model, performers, poses, chor: Choreography, params: SceneParams):
    import roma
    import torch

    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    tracks = []
    for i, (p, (local, transl)) in enumerate(zip(performers, poses)):
        pose = roma.rotmat_to_rotvec(torch.tensor(local)).numpy()
        tracks.append(BodyTrack.from_model(model, pose, transl, p.sk.shape, params.fps, actor=params.names[i]))
    return InteractionSequence(tuple(tracks), take=f"sim-{params.type}-{params.seed}", labels=chor.labels,
                               text=chor.text, meta={"scene": _params_dict(params)})  # fmt: skip


def ground_truth_distances(seq, frames=None, previous=None) -> tuple[np.ndarray, np.ndarray]:
    """Signed vertex-to-body distances ``(T, V)`` float16 (m) for both actors of ``seq`` (only
    ``frames`` recomputed, the rest copied from ``previous``, when given): the banded warp query
    (pseudonormal sign, NaN beyond :data:`DISTANCE_BAND`), then inside/outside re-decided by the
    generalised winding number (:func:`~dualhuman_builder.sim.quality.sign_by_winding`), which
    stays right where a posed body crosses itself, and which also reports vertices deeper inside
    than the band."""
    from dualhuman_builder.sim.pairquery import get_fast_pair
    from dualhuman_builder.sim.quality import sign_by_winding

    pair = get_fast_pair()
    va, vb = seq.actors[0].vertices(), seq.actors[1].vertices()
    if previous is None:
        da, db = np.empty(va.shape[:2], np.float16), np.empty(vb.shape[:2], np.float16)
        frames = range(len(va))
    else:
        da, db = previous[0].copy(), previous[1].copy()
    frames = np.asarray(list(frames), dtype=np.int64)
    overlap = np.zeros(len(frames), bool)
    for k, f in enumerate(frames):
        boxes = pair.boxes(va[f]), pair.boxes(vb[f])
        a, b = pair(va[f], vb[f], DISTANCE_BAND, boxes=boxes)
        da[f], db[f] = a, b
        # a vertex inside the other body lies in the box around it, and if any does, so does one
        # within the band of its surface (the surface is connected, and an edge that crosses the
        # other's surface has an end within half its length, under 3 cm on anny, of it): where
        # the boxes are apart or no vertex is within the band, every vertex is outside, and the
        # winding number has nothing to decide
        (lo_a, hi_a), (lo_b, hi_b) = ((x[:, 0].min(0), x[:, 1].max(0)) for x in boxes)
        apart = not (np.all(lo_a <= hi_b) and np.all(lo_b <= hi_a))
        overlap[k] = not apart and bool(np.isfinite(a).any() or np.isfinite(b).any())
    sign_by_winding((da, db), va, vb, frames[overlap])
    outside = frames[~overlap]
    if len(outside):
        covered = _winding_covered()
        for d in (da, db):
            x = d[outside]
            x[:, covered] = np.abs(x[:, covered])
            d[outside] = x
    return da, db


def _winding_covered() -> np.ndarray:
    """The vertices whose inside/outside :func:`~dualhuman_builder.sim.quality.sign_by_winding` decides."""
    from dualhuman_builder.sim.quality import _winding_term

    return _winding_term().obstacle_vertices


def _rescale_time(c: Choreography, tempo: float) -> Choreography:
    """Choreographies are written in 'tempo 1' seconds; report their timing in real seconds."""
    c.phases = {k: (a / tempo, b / tempo) for k, (a, b) in c.phases.items()}
    c.contact_phases = [(a / tempo, b / tempo) for a, b in c.contact_phases]
    return c


def _correct_contacts(model, performers, chor: Choreography, fps: float):
    """One pass of contact correction (see :class:`ContactSpec`): per frame, the gap between the
    palm and the partner (the smallest signed distance of either hand's vertices) is measured and
    the palm target moves along the contact normal by the gap error (both palms half of it for a
    palm-to-palm contact). Offsets accumulate over passes and are smoothed in time. On guard
    frames the offset eases from the adjacent contact frames' offset to none over
    :data:`CONTACT_EASE_S` (:func:`_ease_out`; ``fps`` converts it to frames; the torsos' offset is
    first held for :data:`TORSO_HOLD_S`), never below what
    keeps the gap at :data:`CONTACT_GAP` there (``spec.floor``: the offset that each guard
    frame's last measurement says would leave exactly that gap). The easing keeps a correction
    from switching on or off in one frame, which would make the pelvises jump at each end of an
    embrace and could leave an arm inside the partner at the release
    (docs/decisions/0022-ground-truth-scenes.md). Poses only the frames it measures (from the
    controls it moves). Returns the largest gap error measured before this pass (m), whose it
    was, and how many frames it measured."""
    import roma
    import torch
    from scipy.ndimage import gaussian_filter1d

    from dualhuman_builder.sim.pairquery import get_fast_pair

    if not chor.contacts:
        return 0.0, "", 0
    T = chor.controls[0].frames
    # frames still to measure: those of a contact that have not settled (see below)
    active = [(c.frames | (c.guard if c.guard is not None else False)) & (True if c.settled is None else ~c.settled)
              & (True if c.left is None else ~c.left) for c in chor.contacts]  # fmt: skip
    # of those, the frames measured: all on the first pass; after it a grid of at most
    # MEASURE_FPS, the ends of each run of frames to measure, and every frame near one found more
    # than GAP_TOLERANCE too close on the last pass (a palm can cut through the partner on a
    # single frame); the others' errors are interpolated between them
    stride = max(1, int(fps // MEASURE_FPS))
    sampled = []
    for spec, act in zip(chor.contacts, active):
        if spec.last is None:
            sampled.append(act)
            continue
        ends = act & ~(np.roll(act, 1) & np.roll(act, -1))
        ends[[0, -1]] = act[[0, -1]]
        close = np.convolve(spec.last[1], np.ones(2 * stride - 1), mode="same") > 0
        sampled.append(act & ((np.arange(T) % stride == 0) | ends | close))
    frames = np.flatnonzero(np.any(sampled, axis=0))
    if not len(frames):
        return 0.0, "", 0
    verts = []
    for p, c in zip(performers, chor.controls):
        local, transl = p.solve(c.take(frames))  # a frame's pose depends on its own controls only
        with torch.no_grad():
            out = model(roma.rotmat_to_rotvec(torch.tensor(local)).float(), torch.tensor(p.sk.shape),
                        torch.tensor(transl, dtype=torch.float32))  # fmt: skip
        verts.append(out.vertices.numpy())
    fast = get_fast_pair()
    hands = np.concatenate([_hand_vertices(model, s) for s in SIDES])  # only palms are corrected
    palms = [(n, spec) for n, spec in enumerate(chor.contacts) if spec.side is not None]
    dists, partner_near = [], {}
    for k, f in enumerate(frames):
        # each body's hands, and each body's vertices near the other's hands (a chest pressing
        # into a palm is as much a penetration as the palm pressing into the chest)
        near = []
        for i in (0, 1):
            box = verts[1 - i][k][hands]
            lo, hi = box.min(0) - DISTANCE_BAND, box.max(0) + DISTANCE_BAND
            near.append(np.flatnonzero(np.all((verts[i][k] >= lo) & (verts[i][k] <= hi), axis=1)))
        # of those, only what a palm contact measured on this frame reads: its palm, and the
        # partner's vertices near that palm
        need = ([], [])
        for n, spec in palms:
            if not sampled[n][f]:
                continue
            mine = _hand_vertices(model, spec.side)
            v = verts[spec.actor][k][mine]
            lo, hi = v.min(0) - DISTANCE_BAND, v.max(0) + DISTANCE_BAND
            theirs = near[1 - spec.actor]
            theirs = theirs[np.all((verts[1 - spec.actor][k][theirs] >= lo) & (verts[1 - spec.actor][k][theirs] <= hi), axis=1)]
            partner_near[(n, k)] = theirs
            need[spec.actor].append(mine)
            need[1 - spec.actor].append(theirs)
        need_a, need_b = (np.concatenate(x) if x else np.zeros(0, dtype=np.int64) for x in need)
        dists.append(fast(verts[0][k], verts[1][k], DISTANCE_BAND, need_a=need_a, need_b=need_b))
    worst, worst_what = 0.0, ""
    for n, (spec, act) in enumerate(zip(chor.contacts, active)):
        torso = spec.side is None
        if torso:  # the pelvises carry the torsos
            track, partner = chor.controls[spec.actor], chor.controls[1 - spec.actor]
            field_name = "root"
        else:
            track = chor.controls[spec.actor].arms[spec.side]
            partner = chor.controls[1 - spec.actor].arms[spec.partner_side] if spec.partner_side else None
            field_name = "palm"
        if spec.base is None:
            spec.base = (getattr(track, field_name).copy(), None if partner is None else getattr(partner, field_name).copy())
            spec.offset = np.zeros(T)
            spec.floor = np.full(T, -np.inf)
            spec.left = np.zeros(T, bool)
            spec.last = (np.full(T, np.nan), np.zeros(T, bool))
        err = np.zeros(T)
        for k, f in enumerate(frames):
            if not sampled[n][f]:
                continue
            d_mine, d_theirs = dists[k][spec.actor], dists[k][1 - spec.actor]
            if torso:  # trunk against trunk only: hands resting on a back are not a torso collision
                gap = _trunk_gap(model, verts[0][k], verts[1][k])
                err[f] = CONTACT_GAP - gap
                continue
            mine = _hand_vertices(model, spec.side)
            gap = np.nanmin(d_mine[mine], initial=DISTANCE_BAND)
            # the partner's vertices that are near this palm
            gap = min(gap, np.nanmin(d_theirs[partner_near[(n, k)]], initial=DISTANCE_BAND))
            err[f] = CONTACT_GAP - gap  # > 0: too close, move apart; < 0: too far, move together
        between = np.flatnonzero(act & ~sampled[n])
        if len(between):
            at = np.flatnonzero(sampled[n])
            err[between] = np.interp(between, at, err[at])
        guard = (spec.guard if spec.guard is not None else np.zeros(T, bool)) & ~spec.frames
        # a frame whose gap error changed sign from the previous pass, within GAP_TOLERANCE both
        # times, oscillates about the gap (the palms and torsos of an embrace move each other):
        # it is left where it is and no longer measured
        last_err = spec.last[0]
        driven = act & np.isfinite(last_err) & (spec.frames | (last_err > 0))  # guard frames: only pushed apart
        done = driven & (err * last_err < 0) & (np.abs(err) <= GAP_TOLERANCE) & (np.abs(last_err) <= GAP_TOLERANCE)
        spec.left |= done
        err[done] = 0.0
        spec.last = (np.where(act & ~done, err, np.nan), act & (err > GAP_TOLERANCE))
        # guard frames measured now: the offset that would leave exactly CONTACT_GAP there, a
        # lower bound on theirs (far ones: far below; re-measured every pass, so never stale)
        measured = guard & act
        spec.floor[measured] = (spec.offset + np.minimum(err, MAX_CORRECTION_STEP))[measured]
        err[guard] = np.maximum(err[guard], 0.0)
        spec_worst = max(float(np.abs(err[spec.frames]).max(initial=0.0)), float(err[guard].max(initial=0.0)))
        if spec_worst > worst:
            worst, worst_what = spec_worst, ("torsos" if torso else f"actor {spec.actor} {spec.side} palm")
        need = spec.offset + np.clip(err, -MAX_CORRECTION_STEP, MAX_CORRECTION_STEP)
        hold = TORSO_HOLD_S * fps if torso else 0.0
        need[guard] = np.maximum(_ease_out(need, spec.frames, guard, CONTACT_EASE_S * fps, hold), spec.floor)[guard]
        smooth = gaussian_filter1d(need, 1.0)
        smooth[spec.frames] = need[spec.frames]  # contact frames: exactly what each needs
        smooth[guard] = np.maximum(smooth[guard], spec.floor[guard])
        # a frame is settled when its gap was right and its offset barely moved
        settled = act & (np.abs(err) < 5e-4) & (np.abs(smooth - spec.offset) < 2e-4)
        spec.settled = settled if spec.settled is None else (spec.settled & (np.abs(smooth - spec.offset) < 2e-4)) | settled
        spec.offset = smooth
        share = 0.5 if partner is not None else 1.0
        getattr(track, field_name)[:] = spec.base[0] - share * spec.offset[:, None] * spec.normal
        if partner is not None:
            getattr(partner, field_name)[:] = spec.base[1] + share * spec.offset[:, None] * spec.normal
    return worst, worst_what, len(frames)


def _ease_out(values: np.ndarray, frames: np.ndarray, guard: np.ndarray, ramp: float, hold: float = 0.0) -> np.ndarray:
    """``values (T,)`` on the ``frames (T,)`` mask carried onto the ``guard (T,)`` frames, held for
    ``hold`` frames and then faded to 0 over ``ramp`` frames (minimum-jerk) from the nearest
    contact frame on either side (a frame between two contact intervals blends both). Frames
    outside ``guard`` get 0."""
    from dualhuman_builder.sim.timeline import minjerk

    T = len(values)
    out = np.zeros(T)
    idx = np.flatnonzero(frames)
    if not len(idx) or not guard.any():
        return out
    g = np.flatnonzero(guard)
    ramp = max(float(ramp), 1.0)
    total, weight = np.zeros(len(g)), np.zeros(len(g))
    k = np.searchsorted(idx, g)
    for nearest, valid in ((idx[np.maximum(k - 1, 0)], k > 0), (idx[np.minimum(k, len(idx) - 1)], k < len(idx))):
        w = np.where(valid, 1.0 - minjerk(np.maximum(np.abs(g - nearest) - hold, 0.0) / ramp), 0.0)
        total += w * values[nearest]
        weight += w
    out[g] = total / np.maximum(weight, 1.0)
    return out


def _make_reachable(performers, chor: Choreography, poses, frac: float = 0.95) -> None:
    """Pull the meeting points of palm-to-palm contacts where both arms can put them: the wrists
    each palm needs (given its wanted orientation) within ``frac`` of the arm's reach from its
    shoulder, by alternating projections onto the two spheres. The contact correction then only
    ever moves palms that actually follow their targets."""
    from dualhuman_builder.sim.ik import map_frames

    for spec in chor.contacts:
        if spec.side is None or spec.partner_side is None:
            continue  # only palm-to-palm contacts share a point; a palm short of a body just stops short
        arms = [(spec.actor, spec.side)] + ([(1 - spec.actor, spec.partner_side)] if spec.partner_side else [])
        tracks = [chor.controls[i].arms[side] for i, side in arms]
        centre = np.mean([tr.palm for tr in tracks], axis=0)
        spheres = []  # centres and radii of the sphere the shared contact point must lie in, per arm
        for (i, side), tr in zip(arms, tracks):
            local, transl = poses[i]
            perf = performers[i]
            hand = perf.hand[side]
            shoulder = perf.shoulder(local, transl, side)
            fingers = tr.fingers if tr.fingers is not None else tr.palm - shoulder
            R = map_frames(hand.fingers0, hand.normal0, fingers, tr.palm_normal)
            wrist_from_point = (tr.palm - centre) - np.einsum("tij,j->ti", R, hand.palm_offset)
            spheres.append((shoulder - wrist_from_point, frac * perf.arms[side].reach))
        x = centre.copy()
        for _ in range(10):
            for c, r in spheres:
                v = x - c
                n = np.linalg.norm(v, axis=1, keepdims=True)
                x = np.where(n > r, c + v * (r / np.maximum(n, 1e-9)), x)
        for tr in tracks:
            tr.palm[:] = x + (tr.palm - centre)


#: Elbow swivel angles (radians) tried when an arm passes through the partner.
SWIVEL_CANDIDATES = (0.0, 0.3, -0.3, 0.7, -0.7, 1.2, -1.2)
#: Most passes of :func:`_resolve_by_swivel` (a pass sees the other arms where the earlier passes put them).
SWIVEL_PASSES = 3


def _arm_vertices(model, side: str) -> np.ndarray:
    from dualhuman_builder.body.regions import load_regions

    regions = load_regions(model)
    name = "left" if side == "L" else "right"
    return np.concatenate([regions.vertices_of(f"{name}_{part}") for part in ("upper_arm", "forearm", "hand")])


def add_swivel_turns(swivel: np.ndarray | None, turns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An arm's swivel ``(T,)`` radians (None: none yet) plus one pass's ``turns (T,)`` (0 where the
    pass left the frame alone), smoothed in time (Gaussian, 1.5 frames) but never below the turn a
    frame needed. The turns are added to the swivel the arm had when the pass chose them, once: each
    pass tries its candidates about that swivel. Returns the new swivel and the frames it moved."""
    from scipy.ndimage import gaussian_filter1d

    smooth = gaussian_filter1d(np.asarray(turns, dtype=np.float64), 1.5)
    keep = (turns != 0) & (np.abs(turns) > np.abs(smooth))
    smooth[keep] = turns[keep]
    return (smooth if swivel is None else swivel + smooth), np.abs(smooth) > 1e-4


def _resolve_by_swivel(model, performers, chor: Choreography, poses, seq, distances, log=None,
                       threshold: float = 0.0035):  # fmt: skip
    """Remove penetrations that involve an arm by turning its elbow about the shoulder-palm axis
    (the palm, and so every contact, stays put). For each frame where the bodies interpenetrate by
    more than ``threshold`` m (from ``distances``), each arm with vertices inside or within 1 cm of
    the partner tries :data:`SWIVEL_CANDIDATES` and keeps the one leaving the least penetration
    between that arm and the partner; the chosen angles are then smoothed in time (never below
    what a frame needed). Returns the new poses and the frames whose poses changed."""
    import roma
    import torch

    from dualhuman_builder.sim.pairquery import get_fast_pair

    pair = get_fast_pair()
    T = chor.controls[0].frames
    depth = -np.minimum(*(np.nan_to_num(d.astype(np.float32), nan=1.0).min(1) for d in distances))
    flagged = np.flatnonzero(depth > threshold)
    if not len(flagged):
        return poses, np.zeros(0, dtype=int)
    for i, (perf, c) in enumerate(zip(performers, chor.controls)):  # make every arm's track explicit
        local, transl = poses[i]
        for s in SIDES:
            if c.arms[s] is None:
                c.arms[s] = perf.relaxed_arm(local, transl, c.heading, s)
    verts = [np.array(seq.actors[i].vertices()) for i in (0, 1)]
    arms = {(i, s): _arm_vertices(model, s) for i in (0, 1) for s in SIDES}
    chosen = {key: np.zeros(T) for key in arms}
    for f in flagged:
        for (i, s), vidx in arms.items():
            d_own = distances[i][f][vidx].astype(np.float32)
            if not (np.nan_to_num(d_own, nan=1.0) < 0.01).any():
                continue
            ctrl = chor.controls[i].take([f] * len(SWIVEL_CANDIDATES))
            base = 0.0 if ctrl.arms[s].swivel is None else ctrl.arms[s].swivel[0]
            ctrl.arms[s].swivel = base + np.array(SWIVEL_CANDIDATES)
            local, transl = performers[i].solve(ctrl)
            with torch.no_grad():
                cand = model(roma.rotmat_to_rotvec(torch.tensor(local)).float(), torch.tensor(performers[i].sk.shape),
                             torch.tensor(transl, dtype=torch.float32)).vertices.numpy()  # fmt: skip
            other = verts[1 - i][f]
            scores = []
            for k, v in enumerate(cand):
                # this arm against the partner, and the partner's vertices near this arm against us
                lo, hi = v[vidx].min(0) - 0.02, v[vidx].max(0) + 0.02
                near = np.flatnonzero(np.all((other >= lo) & (other <= hi), axis=1))[::2]
                x_arm, x_other = pair(v, other, DISTANCE_BAND, vidx, near)
                pen = -min(np.nanmin(x_arm, initial=1.0), np.nanmin(x_other, initial=1.0))
                scores.append(max(pen, 0.0) + 0.002 * abs(SWIVEL_CANDIDATES[k]))
            best = int(np.argmin(scores))
            if best:  # the turn this pass adds to the swivel the arm already had
                chosen[(i, s)][f] = SWIVEL_CANDIDATES[best]
                verts[i][f] = cand[best]
    changed = np.zeros(T, dtype=bool)
    for (i, s), turns in chosen.items():
        if turns.any():
            track = chor.controls[i].arms[s]
            track.swivel, moved = add_swivel_turns(track.swivel, turns)
            changed |= moved
    if log:
        log(f"elbow swivel moved {sum(int((a != 0).sum()) for a in chosen.values())} arm-frames out of the partner")
    if not changed.any():
        return poses, np.zeros(0, dtype=int)
    return [p.solve(c) for p, c in zip(performers, chor.controls)], np.flatnonzero(changed)


_HAND_CACHE: dict[str, np.ndarray] = {}


_TRUNK: dict = {}


def _trunk_gap(model, va: np.ndarray, vb: np.ndarray) -> float:
    """Smallest signed distance (m) between the two trunks (head, neck, torso), each against the
    other's trunk surface only (every other vertex queried; the trunk mesh is open at the arms
    and legs, far from where torsos meet)."""
    from dualhuman_builder.geometry.distance import MeshDistance

    if not _TRUNK:
        from dualhuman_builder.body.regions import load_regions

        regions = load_regions(model)
        parts = ("head", "neck", "chest", "upper_back", "abdomen", "lower_back", "pelvis_front", "buttocks")
        verts = np.concatenate([regions.vertices_of(p) for p in parts])
        faces = model.faces.cpu().numpy()
        keep = np.isin(faces, verts).all(axis=1)
        _TRUNK["vertices"] = verts[::2]
        _TRUNK["meshes"] = [MeshDistance(faces[keep], model.num_vertices) for _ in (0, 1)]
    q = _TRUNK["vertices"]
    gaps = []
    for mesh, mine, other in zip(_TRUNK["meshes"], (va, vb), (vb, va)):
        mesh.update(other)
        gaps.append(np.nanmin(mesh.query(mine[q], DISTANCE_BAND), initial=DISTANCE_BAND))
    return float(min(gaps))


def _hand_vertices(model, side: str) -> np.ndarray:
    if side not in _HAND_CACHE:
        from dualhuman_builder.body.regions import load_regions

        _HAND_CACHE[side] = load_regions(model).vertices_of(("left" if side == "L" else "right") + "_hand")
    return _HAND_CACHE[side]


# ============================================================================ quality
def quality_summary(scene: Scene) -> dict[str, float]:
    """The scene contract's measures: max penetration (m), max stance-foot slide per frame (m),
    min gap during contact phases (m), share of contact-phase frames with contact."""
    from dualhuman_builder.sim.quality import foot_sliding, joint_limit_violations

    # a chunk of frames at a time, so a long take (a 10-minute session) needs no float32 copy of its (T, V) distances
    T, chunk = scene.sequence.num_frames, 1024
    min_d = np.empty(T, np.float32)
    for s in range(0, T, chunk):
        rows = [np.nan_to_num(d[s : s + chunk].astype(np.float32), nan=np.inf).min(1) for d in scene.distances]
        min_d[s : s + chunk] = np.minimum(*rows)
    pen = np.maximum(-np.where(np.isfinite(min_d), min_d, 0.0), 0.0)  # the deepest vertex inside the other body
    mask = scene.contact_phase_mask()
    in_contact = min_d < CONTACT_THRESHOLD
    slide = max(foot_sliding(tr, scene.stance[i]) for i, tr in enumerate(scene.sequence.actors))
    return {
        "max_penetration_m": float(pen.max()),
        "max_stance_slide_m": float(slide),
        "contact_frames_share": float(in_contact[mask].mean()) if mask.any() else 1.0,
        "min_gap_in_contact_phase_m": float(min_d[mask].max()) if mask.any() else 0.0,
        "joint_limit_violations": {f"actor{i} {k}": round(v, 1) for i, tr in enumerate(scene.sequence.actors)
                                   for k, v in joint_limit_violations(tr).items()},  # fmt: skip
    }


def describe_scene(scene: Scene) -> dict:
    """``{"summary": str, "lines": [str], "data": dict}``: what ``dualhuman scene info`` prints."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.body.shape import stature

    seq, p = scene.sequence, scene.params
    model = get_body_model()
    heights = [round(stature(model, model.shape_tensor(np.array(a.shape)[None])), 3) for a in seq.actors]
    stats = scene.stats
    data = {"params": _params_dict(p), "frames": seq.num_frames, "fps": seq.fps, "duration_s": seq.num_frames / seq.fps,
            "statures_m": heights, "phases": scene.phases, "contact_phases": scene.contact_phases,
            "labels": list(seq.labels), "text": list(seq.text), "quality": stats,
            "contract_failures": contract_failures(stats) if stats else []}  # fmt: skip
    summary = (f"{p.type} seed {p.seed}: {seq.num_frames} frames at {seq.fps:g} fps ({data['duration_s']:.2f} s), "
               f"actors {heights[0]:.2f} m and {heights[1]:.2f} m")  # fmt: skip
    lines = ["phases: " + ", ".join(f"{k} {a:.2f}-{b:.2f} s" for k, (a, b) in scene.phases.items()),
             "contact phases: " + (", ".join(f"{a:.2f}-{b:.2f} s" for a, b in scene.contact_phases) or "none")]  # fmt: skip
    if stats:
        lines.append(f"max penetration {1000 * stats['max_penetration_m']:.1f} mm, max stance-foot slide "
                     f"{1000 * stats['max_stance_slide_m']:.2f} mm/frame, contact on "
                     f"{100 * stats['contact_frames_share']:.0f} % of contact-phase frames, "
                     f"{len(stats.get('joint_limit_violations', {}))} joint-limit violations")  # fmt: skip
        lines.append("quality contract: " + ("met" if not data["contract_failures"] else "BROKEN: " + "; ".join(data["contract_failures"])))
        if "generation_s" in stats:
            draws = stats.get("draws", 1)
            which = "the seed's own draw" if draws == 1 else f"draw {draws} (the earlier ones broke the contract)"
            how = ", with its type's repair" if stats.get("repaired") else ""
            lines.append(f"generated in {stats['generation_s']:.1f} s, on {which}{how}")
    return {"summary": summary, "lines": lines, "data": data}


#: The scene quality contract (``dualhuman scene make`` checks it; the tests assert it).
MAX_PENETRATION_M = 0.005
MAX_STANCE_SLIDE_M = 0.005


def contract_failures(stats: dict) -> list[str]:
    """What of the quality contract the measures of :func:`quality_summary` break (empty: none):
    penetration at most :data:`MAX_PENETRATION_M`, stance-foot slide at most
    :data:`MAX_STANCE_SLIDE_M` per frame, contact on every contact-phase frame, every joint within
    its anatomical limits."""
    out = []
    if stats["max_penetration_m"] > MAX_PENETRATION_M:
        out.append(f"bodies interpenetrate by {1000 * stats['max_penetration_m']:.1f} mm (limit {1000 * MAX_PENETRATION_M:g})")
    if stats["max_stance_slide_m"] > MAX_STANCE_SLIDE_M:
        out.append(f"a planted foot slides {1000 * stats['max_stance_slide_m']:.1f} mm in a frame (limit {1000 * MAX_STANCE_SLIDE_M:g})")
    if stats["contact_frames_share"] < 1.0:
        out.append(f"contact on only {100 * stats['contact_frames_share']:.1f} % of the contact-phase frames")
    for k, v in stats.get("joint_limit_violations", {}).items():
        out.append(f"{k} beyond its limit ({v:.1f} deg)")
    return out


# ============================================================================ choreographies
# Each takes (t, performers, params, rng) with t in tempo-1 seconds and returns a Choreography.
# Actor 0 is "A", actor 1 "B". Body-frame offsets are (left, up, forward) metres from the pelvis.


def _head_of(perf: Performer, root: np.ndarray) -> np.ndarray:
    """Approximate eye point of an actor whose pelvis follows ``root (T, 3)``."""
    return root + np.array([0.0, 0.93 * perf.stature - perf.floor_offset, 0.0])


def _walk(t, perf: Performer, start_xz, end_xz, heading: float, t0: float, t1: float, lead: str = "R",
          max_step: float = 0.32):  # fmt: skip
    """Walk from pelvis position ``start_xz`` to ``end_xz`` (world x, z) between ``t0`` and ``t1``
    facing ``heading``: the feet leapfrog in steps of at most ``max_step`` m of pelvis travel,
    ``lead`` foot first, and end side by side; the pelvis is lowered wherever a leg could not
    reach. Returns root (T, 3), feet, stance masks."""
    h = perf.standing_height()
    start = np.array([start_xz[0], h, start_xz[1]], dtype=np.float64)
    end = np.array([end_xz[0], h, end_xz[1]], dtype=np.float64)
    root = keyframes(t, [t0, t1], [start, end])
    halves = max(1, int(np.ceil(np.linalg.norm(end - start) / max_step)))
    other = "L" if lead == "R" else "R"
    plan = [(lead if j % 2 else other, j / halves) for j in range(1, halves + 1)]
    plan.append((other if halves % 2 else lead, 1.0))  # the last foot joins the other
    dt = (t1 - t0) / len(plan)
    R = rot_y(np.array(heading))
    feet, stance = {}, {}
    for s in SIDES:
        r = perf.sk.rest[perf.sk.index(f"foot.{s}")]
        lateral = R @ np.array([r[0], 0.0, r[2]])
        p0, p1 = start + lateral, end + lateral
        steps = [Step(s, t0 + k * dt, t0 + (k + 1) * dt, tuple((p0 + f * (p1 - p0))[[0, 2]]), heading)
                 for k, (foot, f) in enumerate(plan) if foot == s and np.linalg.norm(p1 - p0) > 1e-6]  # fmt: skip
        pos, yaw, st = foot_track(t, (p0[0], p0[2]), heading, perf.ankle_height[s], steps, s)
        feet[s], stance[s] = FootTrack(pos, yaw), st
    root = perf.reachable_root(Controls(root, np.full(len(t), heading), feet), fps=1.0 / (t[1] - t[0]))
    return root, feet, stance


def _relaxed(perf: Performer, c: Controls, side: str) -> ArmTrack:
    local, transl = perf.solve(Controls(c.root, c.heading, c.feet, c.trunk, pelvis=c.pelvis))
    return perf.relaxed_arm(local, transl, c.heading, side)


def _arm(perf: Performer, c: Controls, side: str, w: np.ndarray, palm, pole, normal, fingers, flat: bool = False,
         detour=None) -> ArmTrack:  # fmt: skip
    """An arm that blends (weight ``w (T,)``) from hanging relaxed to the given targets; ``flat``
    opens the hand flat as it reaches; ``detour`` ``(T, 3)`` bows the palm's path out by that
    vector halfway (reaching round a partner rather than through it)."""
    T = c.frames
    tile = lambda v: np.broadcast_to(np.asarray(v, dtype=np.float64), (T, 3)).copy()  # noqa: E731
    relaxed = _relaxed(perf, c, side)
    w3 = w[:, None]
    bow = 0.0 if detour is None else 4.0 * w3 * (1 - w3) * np.broadcast_to(detour, (T, 3))
    return ArmTrack(
        palm=(1 - w3) * relaxed.palm + w3 * tile(palm) + bow,
        pole=normalize((1 - w3) * relaxed.pole + w3 * tile(pole)),
        palm_normal=normalize((1 - w3) * relaxed.palm_normal + w3 * tile(normal) + 1e-6 * relaxed.pole),
        fingers=normalize((1 - w3) * relaxed.fingers + w3 * tile(fingers)),
        flat=np.clip(w, 0.0, 1.0) if flat else None,
    )


def _mask(t, *intervals) -> np.ndarray:
    m = np.zeros(len(t), dtype=bool)
    for a, b in intervals:
        m |= (t >= a) & (t <= b)
    return m


def _face_to_face(t, perfs, d0: float, d1: float, t0: float, t1: float, lateral: float = 0.0, lead: str = "R"):
    """A at z=0 and B at z=d0 walk towards each other until their pelvises are d1 apart; each
    ends shifted ``lateral`` m to its own left. Returns per-actor (root, feet, stance) and headings."""
    heads = (0.0, np.pi)
    walks = [
        _walk(t, perfs[0], (0.0, 0.0), (lateral, 0.5 * (d0 - d1)), heads[0], t0, t1, lead),
        _walk(t, perfs[1], (0.0, d0), (-lateral, d0 - 0.5 * (d0 - d1)), heads[1], t0, t1, lead),
    ]
    return walks, heads


def _controls(t, walks, heads, perfs, trunk=None) -> tuple[list[Controls], list]:
    controls = []
    for i, (root, feet, _) in enumerate(walks):
        c = Controls(root, np.full(len(t), heads[i]), feet, trunk=None if trunk is None else trunk[i])
        c.look_at = _head_of(perfs[1 - i], walks[1 - i][0])
        controls.append(c)
    return controls, [w[2] for w in walks]


def handshake(t, perfs, params, rng) -> Choreography:
    """Walk up to each other and shake right hands: palms side by side, three shakes."""
    pa, pb = perfs
    d0 = params.approach_distance or 1.8
    # each upper arm hangs ~25 degrees forward and the forearm points ahead: the palms meet about
    # an upper arm below the shoulders and a forearm in front of them
    ahead, heights = [], []
    for p in perfs:
        sh = p.sk.rest[p.sk.index("upperarm01.R")] + [0.0, p.floor_offset, 0.0]
        a = np.radians(25.0 + rng.uniform(-5, 5))
        heights.append(sh[1] - p.arms["R"].l1 * np.cos(a))
        ahead.append(sh[2] + p.arms["R"].l1 * np.sin(a) + 0.9 * (p.arms["R"].l2 + np.linalg.norm(p.hand["R"].palm_offset)))
    h = float(np.mean(heights))
    d1 = sum(ahead)
    _check_distance(d0, d1, "handshake")
    walks, heads = _face_to_face(t, perfs, d0, d1, 0.3, 1.3)
    lean = np.outer(window(t, 1.0, 3.6, 0.5), [0.10, 0.0, 0.0])
    controls, stance = _controls(t, walks, heads, perfs, [lean, lean])
    meet = np.array([rng.uniform(-0.02, 0.02), h, 0.5 * d0])
    shake = 0.035 * np.sin(2 * np.pi * 2.4 * (t - 1.9)) * window(t, 1.9, 2.9, 0.2)
    w = window(t, 1.0, 3.5, 0.6)
    for i, c in enumerate(controls):
        sign = -1.0 if i == 0 else 1.0  # A's palm on the -X side, facing +X; B's on +X facing -X
        palm = np.tile(meet + [sign * 0.004, 0.0, 0.0], (len(t), 1))
        palm[:, 1] += shake
        fwd = 1.0 if i == 0 else -1.0
        c.arms["R"] = _arm(perfs[i], c, "R", w, palm, [sign * 0.6, -1.0, -0.3 * fwd], [-sign, 0.0, 0.0],
                           [0.0, -0.25, fwd])  # fmt: skip
    specs = [ContactSpec(0, "R", _mask(t, (1.6, 2.9)), np.tile([1.0, 0.0, 0.0], (len(t), 1)), partner_side="R",
                         guard=_mask(t, (1.2, 3.4)))]  # fmt: skip
    return Choreography(controls, stance, {"approach": (0.3, 1.3), "reach": (1.0, 1.6), "grip": (1.6, 2.9),
                                           "release": (2.9, 3.5)}, [(1.65, 2.85)], specs, ("handshake",),
                        ("Two people walk up to each other and shake hands.",))  # fmt: skip


def high_five(t, perfs, params, rng) -> Choreography:
    """Walk up and slap A's right palm against B's left palm above head height."""
    pa, pb = perfs
    d0 = params.approach_distance or 1.8
    # the slap happens with the forearms upright: palms about a forearm above the shoulders and an
    # upper arm in front of them, so the wrists need little bend to hold the palms vertical
    x = -0.22 + rng.uniform(-0.03, 0.03)  # A's right side, B's left side
    shoulders = [p.sk.rest[p.sk.index(f"upperarm01.{s}")] + [0.0, p.floor_offset, 0.0] for p, s in ((pa, "R"), (pb, "L"))]
    h = np.mean([sh[1] for sh in shoulders]) + 0.30 + rng.uniform(-0.02, 0.02)
    d1 = sum(sh[2] + 0.85 * p.arms[s].l1 for sh, p, s in zip(shoulders, perfs, ("R", "L")))
    _check_distance(d0, d1, "high five")
    walks, heads = _face_to_face(t, perfs, d0, d1, 0.2, 1.2)
    controls, stance = _controls(t, walks, heads, perfs)
    meet = np.array([x, h, 0.5 * d0])
    tc = 1.6  # the slap
    w = keyframes(t, [0.9, tc, tc + 0.2, tc + 0.8], [0.0, 1.0, 1.0, 0.0])
    for i, c in enumerate(controls):
        side = "R" if i == 0 else "L"
        fwd = 1.0 if i == 0 else -1.0
        palm = np.tile(meet + [0.0, 0.0, -fwd * 0.004], (len(t), 1))
        c.arms[side] = _arm(perfs[i], c, side, w, palm, [-0.8, -1.0, -0.2 * fwd], [0.0, 0.0, fwd], [0.0, 1.0, 0.0],
                            flat=True)
    specs = [ContactSpec(0, "R", _mask(t, (tc - 0.02, tc + 0.22)), np.tile([0.0, 0.0, 1.0], (len(t), 1)),
                         partner_side="L", guard=_mask(t, (tc - 0.3, tc + 0.5)))]  # fmt: skip
    return Choreography(controls, stance, {"approach": (0.2, 1.2), "raise": (0.9, tc), "slap": (tc, tc + 0.2),
                                           "lower": (tc + 0.2, tc + 0.8)}, [(tc, tc + 0.2)], specs, ("high_five",),
                        ("Two people walk up to each other and give each other a high five.",))  # fmt: skip


def push(t, perfs, params, rng, repair: bool = False) -> Choreography:
    """A walks up and shoves B in the chest with both palms; B staggers back a step. ``repair``
    (a draw whose palms lose B's chest as it goes back): A's pelvis follows through over its
    planted feet by what its arms fall short of the chest (:func:`_follow_through`)."""
    pa, pb = perfs
    d0 = params.approach_distance or 1.9
    reach = 0.45 * pa.stature / 1.75
    chest_up = 0.72 * pb.stature - pb.floor_offset
    front = np.mean([pb.surface_offset("front", s * 0.09, chest_up)[2] for s in (-1, 1)])
    d1 = front + reach + rng.uniform(-0.02, 0.02)
    _check_distance(d0, d1, "push")
    tc, tp = 1.5, 1.9  # contact, end of the shove
    # A walks in; B stands, then is pushed back a step (right foot back first)
    a_root, a_feet, a_stance = _walk(t, pa, (0.0, 0.0), (0.0, d0 - d1), 0.0, 0.2, 1.4, "R")
    shove = 0.28 + rng.uniform(-0.03, 0.03)
    b_root, b_feet, b_stance = _step_back(t, pb, d0, shove, tc + 0.05, tc + 0.75)
    walks = [(a_root, a_feet, a_stance), (b_root, b_feet, b_stance)]
    heads = (0.0, np.pi)
    a_lean = np.outer(keyframes(t, [1.0, tc, tp, tp + 0.6], [0.0, 0.12, 0.22, 0.0]), [1.0, 0.0, 0.0])
    b_lean = np.outer(keyframes(t, [tc, tc + 0.25, tp + 0.7], [0.0, -0.18, 0.0]), [1.0, 0.0, 0.0])
    controls, stance = _controls(t, walks, heads, perfs, [a_lean, b_lean])
    w = keyframes(t, [0.9, tc, tp, tp + 0.6], [0.0, 1.0, 1.0, 0.0])

    def reach_out(c):  # A's palms on B's chest, following B's chest as it is shoved back and leans away
        for side, sign in SIDES.items():
            off = pb.surface_offset("front", -sign * 0.09, chest_up)  # B's left/right mirrored to A's
            palm = pb.attached_point(controls[1], "spine01", off)
            c.arms[side] = _arm(pa, c, side, w, palm, [sign * 0.5, -1.0, -0.3], [0.0, 0.0, 1.0],
                                [-sign * 0.2, 1.0, 0.1])  # fmt: skip

    reach_out(controls[0])
    if repair:
        c = controls[0]
        c.root = _follow_through(t, pa, c, _mask(t, (tc, tp)), tp, 0.6)
        c.arms = {"L": None, "R": None}
        reach_out(c)
    specs = []
    for side in SIDES:
        specs.append(ContactSpec(0, side, _mask(t, (tc, tp)), np.tile([0.0, 0.0, 1.0], (len(t), 1)),
                                 guard=_mask(t, (tc - 0.4, tp + 0.6))))  # fmt: skip
    return Choreography(controls, stance, {"approach": (0.2, 1.4), "shove": (tc, tp), "stagger": (tc + 0.05, tc + 0.75)},
                        [(tc + 0.02, tp - 0.02)], specs, ("push",),
                        ("One person walks up to another and pushes them away with both hands.",))  # fmt: skip


def _follow_through(t, perf: Performer, c: Controls, frames: np.ndarray, t_end: float, ease_s: float,
                    margin: float = 0.01) -> np.ndarray:  # fmt: skip
    """A pelvis track ``(T, 3)`` that carries ``c``'s palms onto their targets on ``frames (T,)``:
    ``c.root`` moved forward (along the heading) by the most either palm's solved position falls
    short of its target there (plus ``margin`` m), never moving back during those frames, and back
    over ``ease_s`` s after ``t_end``; widened and smoothed over 0.15 s (so it starts a little before
    the palms need it, without a jolt); lowered where the planted feet need it
    (:meth:`~.performer.Performer.reachable_root`)."""
    from scipy.ndimage import gaussian_filter1d, maximum_filter1d

    from dualhuman_builder.sim.timeline import minjerk

    local, transl = perf.solve(c)
    heads, glob = perf.sk.fk(local, transl)
    ahead = perf.body_dir(c.heading, (0.0, 0.0, 1.0))
    short = np.zeros(len(t))
    for side in SIDES:
        i = perf.sk.index(f"wrist.{side}")
        palm = heads[:, i] + np.einsum("tij,j->ti", glob[:, i], perf.hand[side].palm_offset)
        short = np.maximum(short, ((c.arms[side].palm - palm) * ahead).sum(-1))
    idx = np.flatnonzero(frames)
    follow = np.zeros(len(t))
    if len(idx) and short[idx].max() > 0:
        follow[idx] = np.maximum.accumulate(np.maximum(short[idx] + margin, 0.0))
        after = t > t[idx[-1]]
        follow[after] = follow[idx[-1]] * (1.0 - minjerk((t[after] - t_end) / ease_s))
        width = max(1, int(round(0.15 / (t[1] - t[0]))))
        follow = gaussian_filter1d(maximum_filter1d(follow, 2 * width + 1), width / 2.0)
    root = np.asarray(c.root) + follow[:, None] * ahead
    return perf.reachable_root(Controls(root, c.heading, c.feet), fps=1.0 / (t[1] - t[0]))


def _step_back(t, perf: Performer, z: float, shove: float, t0: float, t1: float):
    """B (facing -Z at pelvis z) is pushed back by ``shove`` m (towards +Z): right foot back, then left."""
    h = perf.standing_height()
    heading = np.pi
    root = keyframes(t, [t0 - 0.05, t0 + 0.25, t1], [[0.0, h, z], [0.0, h - 0.02, z + 0.6 * shove], [0.0, h, z + shove]])
    R = rot_y(np.array(heading))
    feet, stance = {}, {}
    for s, (a, b) in (("R", (t0, t0 + 0.5 * (t1 - t0))), ("L", (t0 + 0.5 * (t1 - t0), t1))):
        r = perf.sk.rest[perf.sk.index(f"foot.{s}")]
        p0 = np.array([0.0, 0.0, z]) + R @ np.array([r[0], 0.0, r[2]])
        p1 = p0 + [0.0, 0.0, shove]
        pos, yaw, st = foot_track(t, (p0[0], p0[2]), heading, perf.ankle_height[s],
                                  [Step(s, a, b, (p1[0], p1[2]), heading, lift=0.04)], s)  # fmt: skip
        feet[s], stance[s] = FootTrack(pos, yaw), st
    root = perf.reachable_root(Controls(root, np.full(len(t), heading), feet), fps=1.0 / (t[1] - t[0]))
    return root, feet, stance


def pat_on_back(t, perfs, params, rng) -> Choreography:
    """A walks up beside B from behind and pats B's upper back three times."""
    pa, pb = perfs
    d0 = params.approach_distance or 1.5
    side_gap = 0.52 + 0.5 * (pa.stature - 1.7) * 0.3 + rng.uniform(-0.02, 0.02)
    a_root, a_feet, a_stance = _walk(t, pa, (side_gap, -d0), (side_gap, -0.12), 0.0, 0.2, 1.4, "L")
    hb = pb.standing_height()
    b_root = np.tile([0.0, hb, 0.0], (len(t), 1))
    b_feet = pb.standing_feet(b_root, np.zeros(len(t)))
    walks = [(a_root, a_feet, a_stance), (b_root, b_feet, {s: np.ones(len(t), bool) for s in SIDES})]
    heads = (0.0, 0.0)
    controls, stance = _controls(t, walks, heads, perfs)
    controls[0].trunk = np.outer(window(t, 1.3, 3.6, 0.4), [0.05, -0.15, -0.05])  # turn towards B
    up = 0.74 * pb.stature - pb.floor_offset
    back = pb.surface_offset("back", 0.06, up)
    target = pb.attached_point(controls[1], "spine01", back)
    pats = [1.9 + 0.45 * k for k in range(3)]
    lift = np.zeros(len(t))
    for k in range(len(pats) - 1):  # the palm leaves the back between pats
        lift += 0.06 * np.sin(np.pi * np.clip((t - pats[k]) / (pats[k + 1] - pats[k]), 0, 1))
    palm = target - lift[:, None] * np.array([0.0, 0.0, 1.0])
    w = keyframes(t, [1.2, pats[0], pats[-1], pats[-1] + 0.7], [0.0, 1.0, 1.0, 0.0])
    c = controls[0]
    c.arms["R"] = _arm(pa, c, "R", w, palm, [0.3, -0.6, -1.0], [0.0, 0.0, 1.0], [-1.0, -0.2, 0.0])
    touch = [(p - 0.04, p + 0.04) for p in pats]
    specs = [ContactSpec(0, "R", _mask(t, *touch), np.tile([0.0, 0.0, 1.0], (len(t), 1)),
                         guard=_mask(t, (pats[0] - 0.6, pats[-1] + 0.8)))]  # fmt: skip
    return Choreography(controls, stance, {"approach": (0.2, 1.4), "pats": (pats[0], pats[-1])},
                        [(p - 0.02, p + 0.02) for p in pats], specs, ("pat_on_back",),
                        ("A person walks up beside another and pats them on the back.",))  # fmt: skip


def hug(t, perfs, params, rng, repair: bool = False) -> Choreography:
    """Walk up and hug. Partners within 8 cm of each other's height hug criss-cross (each right arm
    over the partner's left shoulder, each left arm under the partner's right arm); otherwise the
    taller one's arms go over the shoulders and the shorter one's under the arms. ``repair`` (a
    draw where an arm reaching in passes through the partner's arm still hanging there): the
    over-arms lead in and the under-arms follow beneath them. Palms rest on the
    partner's back near its sides (where arms of anny's length reach), torsos together, heads side
    by side (each turned to its own left). The torsos' gap is corrected by moving the pelvises."""
    pa, pb = perfs
    d0 = params.approach_distance or 1.8
    lateral = 0.05 + rng.uniform(-0.01, 0.01)  # each ends shifted this far to its own left
    # an "A-frame" hug: both lean in from the hips, so chests meet while feet stay apart. The
    # pelvis distance at which the leaning torsos just touch is refined by the torso correction.
    lean_angle = 0.20
    chest = [0.72 * p.stature - p.floor_offset for p in perfs]
    fronts = [p.surface_offset("front", 0.0, c, radius=0.06)[2] for p, c in zip(perfs, chest)]
    d1 = float(sum(f + c * np.sin(lean_angle) for f, c in zip(fronts, chest))) + 0.01
    _check_distance(d0, d1, "hug")
    walks, heads = _face_to_face(t, perfs, d0, d1, 0.2, 1.5, lateral=lateral)
    lean = np.outer(window(t, 1.2, 4.6, 0.5), [lean_angle, 0.0, 0.0])
    controls, stance = _controls(t, walks, heads, perfs, [lean, lean])
    embrace, near = _mask(t, (1.8, 3.8)), _mask(t, (1.2, 4.9))
    specs = []
    # who goes over whom: partners of similar height hug criss-cross (each right arm over the
    # partner's left shoulder, each left arm under the partner's right arm); otherwise the taller
    # one's arms both go over the shoulders and the shorter one's both under the arms
    tall = int(perfs[1].stature > perfs[0].stature)
    criss_cross = abs(perfs[0].stature - perfs[1].stature) < 0.08
    for i, c in enumerate(controls):
        roles = {"R": "over", "L": "under"} if criss_cross else {s: ("over" if i == tall else "under") for s in SIDES}
        me, other = perfs[i], perfs[1 - i]
        mid = int(np.searchsorted(t, 2.8))
        local, transl = me.solve(Controls(c.root, c.heading, c.feet, c.trunk, pelvis=c.pelvis).take([mid]))
        for side in ("R", "L"):
            role = roles[side]
            # palm height on the partner (fraction of its stature), elbow pole (left, up,
            # forward), and the (left, up, forward) metres the palm's path bows out halfway:
            # the arms open wide (as far as they reach), an over-arm high, an under-arm low
            level, pole, opening = {
                "over": (0.78, (SIDES[side], 0.4, -0.2), (SIDES[side] * 0.55, 0.83, 0.0)),
                "under": (0.66, (SIDES[side], -0.9, -0.2), (SIDES[side] * 0.83, -0.55, 0.0)),
            }[role]
            # the under-arm leads in and the over-arm follows from above (repaired: the over-arm
            # leads, the under-arm follows beneath it); after the embrace the over-arm lifts away
            # first, then the under-arm slides out
            first, second = (1.25, 1.0) if repair else (1.0, 1.25)
            w = window(t, first, 4.9, 0.6) if role == "under" else window(t, second, 4.45, 0.55)
            # the palm goes on the partner's back near its side, or — for an arm short for the
            # partner's girth (it wraps round, so it needs slack beyond the straight line) — on
            # the side of the partner's ribs
            shoulder = me.shoulder(local, transl, side)[0]
            reach = 0.85 * (me.arms[side].reach + np.linalg.norm(me.hand[side].palm_offset))
            up = level * other.stature - other.floor_offset
            partner_side = "left" if side == "R" else "right"
            sign = SIDES["L" if side == "R" else "R"]
            spots = [("back", a * sign) for a in (0.14, 0.17, 0.20)] + [(partner_side, f) for f in (-0.06, -0.02, 0.02)]
            for face, a in spots:
                try:
                    rest_point, rest_normal = other.surface_anchor(face, a, up)
                except ValueError:  # the trunk is narrower than that here
                    continue
                target, outward = other.attached_point(controls[1 - i], "spine01", rest_point, rest_normal)
                if np.linalg.norm(target[mid] - shoulder) <= reach:
                    break
            towards = -normalize(outward)  # from my palm into the partner's surface: the palm faces it
            # fingers along the surface, round towards the partner's spine
            inward = (controls[1 - i].root - target) * [1.0, 0.0, 1.0]
            fingers = normalize(inward - (inward * towards).sum(-1, keepdims=True) * towards)
            out = 0.25 * normalize(outward) + np.linalg.norm(opening) * me.body_dir(c.heading, opening)
            c.arms[side] = _arm(me, c, side, w, target, me.body_dir(c.heading, pole), towards, fingers, flat=True,
                                detour=out)  # fmt: skip
            specs.append(ContactSpec(i, side, embrace, towards, guard=near))
        # look over the partner's right shoulder: turn the head to one's own left
        c.look_at = me.body_point(c.root, c.heading, (0.45, 0.93 * me.stature - me.floor_offset, 0.6))
    specs.append(ContactSpec(0, None, embrace, np.tile([0.0, 0.0, 1.0], (len(t), 1)), guard=near))
    return Choreography(controls, stance, {"approach": (0.2, 1.5), "embrace": (1.8, 3.8), "release": (3.8, 4.4)},
                        [(1.85, 3.75)], specs, ("hug",), ("Two people walk up to each other and hug.",))  # fmt: skip


def dance_turn(t, perfs, params, rng) -> Choreography:
    """Partner-dance turn: A (the leader) and B face each other holding hands, A's left palm down
    on B's right palm up; A raises the joined hands over B's head (stepping in as far as its
    reach needs) and B turns once to its right under them in twelve small steps, B's palm pivoting under
    A's; then A steps back and they lower the hands."""
    pa, pb = perfs
    ha, hb = pa.standing_height(), pb.standing_height()
    d = params.approach_distance or 0.64 + rng.uniform(-0.02, 0.02)
    t0, t1, n_steps = 1.5, 4.3, 12
    # the raised hold: B's palm just above its head, within ~15 cm of its turning axis (so B's arm
    # reaches it whichever way B faces) on A's side (so A reaches it without stepping far in)
    high_b = np.array([0.06, pb.stature + 0.08, d - 0.13])
    high_a = high_b + [0.0, 0.004, 0.0]
    sh = pa.sk.rest[pa.sk.index("upperarm01.L")] + [0.0, pa.floor_offset, 0.0]
    reach = 0.93 * (pa.arms["L"].reach + np.linalg.norm(pa.hand["L"].palm_offset))
    horiz = reach**2 - (high_a[1] - sh[1]) ** 2 - (high_a[0] - sh[0]) ** 2
    if horiz <= 0:
        raise ValueError(f"the leader ({pa.stature:.2f} m) cannot reach over the follower ({pb.stature:.2f} m); "
                         "give actor 0 the taller shape")  # fmt: skip
    step_in = float(np.clip(high_a[2] - np.sqrt(horiz) - sh[2], 0.0, 0.4))
    if high_a[2] - (sh[2] + step_in) > np.sqrt(horiz) + 1e-6:
        raise ValueError(f"the leader ({pa.stature:.2f} m) cannot reach over the follower ({pb.stature:.2f} m) "
                         f"at {d:.2f} m; stand closer or give actor 0 the taller shape")  # fmt: skip
    # A: steps in (left foot, then right) while raising, steps back after the turn
    a_root = keyframes(t, [1.0, 1.5, t1, t1 + 0.5], [[0.0, ha, 0.0], [0.0, ha, step_in], [0.0, ha, step_in],
                                                  [0.0, ha, 0.0]])  # fmt: skip
    a_feet, a_stance = {}, {}
    for s, (a0, a1, b0, b1) in (("L", (1.0, 1.25, t1, t1 + 0.25)), ("R", (1.25, 1.5, t1 + 0.25, t1 + 0.5))):
        r = pa.sk.rest[pa.sk.index(f"foot.{s}")] + [SIDES[s] * 0.04, 0.0, 0.0]
        steps = [Step(s, a0, a1, (r[0], r[2] + step_in), 0.0), Step(s, b0, b1, (r[0], r[2]), 0.0)] if step_in > 0.01 else []
        pos, yaw, st = foot_track(t, (r[0], r[2]), 0.0, pa.ankle_height[s], steps, s)
        a_feet[s], a_stance[s] = FootTrack(pos, yaw), st
    a_root = pa.reachable_root(Controls(a_root, np.zeros(len(t)), a_feet), fps=1.0 / (t[1] - t[0]))
    # B: turns in place, the pelvis heading following its feet
    centre = np.array([0.0, hb, d])
    b_heading = keyframes(t, [t0, t1], [np.pi, -np.pi])  # a full turn to B's right (clockwise from above)
    b_feet, b_stance = {}, {}
    dt = (t1 - t0) / n_steps
    for s in SIDES:
        r = pb.sk.rest[pb.sk.index(f"foot.{s}")]
        place = lambda yaw, r=r: centre + rot_y(np.array(yaw)) @ np.array([r[0], 0.0, r[2]])  # noqa: E731
        steps = []
        for k in range(n_steps):  # right foot on even steps, left on odd; both end square
            if (k % 2 == 0) == (s == "R") or (k == n_steps - 1 and not steps[-1].t1 > t0 + k * dt):
                yaw = np.pi - (k + 1) * 2 * np.pi / n_steps
                p = place(yaw)
                steps.append(Step(s, t0 + k * dt, t0 + (k + 1) * dt, (p[0], p[2]), yaw, lift=0.03))
        p0 = place(np.pi)
        pos, yaw_t, st = foot_track(t, (p0[0], p0[2]), np.pi, pb.ankle_height[s], steps, s)
        b_feet[s], b_stance[s] = FootTrack(pos, yaw_t), st
    # the pelvis faces between the feet, so hips and ankles share each step's turn
    b_heading = 0.5 * (b_feet["L"].heading + b_feet["R"].heading)
    b_root = pb.reachable_root(Controls(np.tile(centre, (len(t), 1)), b_heading, b_feet), fps=1.0 / (t[1] - t[0]))
    controls = [Controls(a_root, np.zeros(len(t)), a_feet), Controls(b_root, b_heading, b_feet)]
    controls[1].look_at = _head_of(pa, a_root)
    # the hold: low between them, raised in front of B's face and over its head for the turn,
    # lowered the same way
    low_b = np.array([0.14, 0.56 * min(pa.stature, pb.stature), 0.5 * d])
    front = np.array([0.10, pb.stature + 0.02, 0.45 * d])  # up in front of B's face, before going over
    hold = keyframes(t, [0.4, 0.7, 1.1, t0, t1, t1 + 0.4, t1 + 0.8, t1 + 1.1],
                     [low_b, low_b, front, high_b, high_b, front, front, low_b])  # fmt: skip
    # A watches B, and the raised hands while B turns (its head tips back, clear of B's arm)
    controls[0].look_at = np.where(((t > t0 - 0.2) & (t < t1 + 0.2))[:, None], hold, _head_of(pb, b_root))
    w = keyframes(t, [0.0, 0.4, t1 + 1.1, t1 + 1.6], [0.0, 1.0, 1.0, 0.0])
    # B's fingers continue its reach (the shoulder-to-hold direction, levelled), so its wrist bends
    # as little as the flat palm allows, and turn with B, pivoting under A's palm
    def along_reach(perf, root, heading, side):
        shoulder = perf.body_point(root, heading, perf.sk.rest[perf.sk.index(f"upperarm01.{side}")])
        return normalize((hold - shoulder) * [1.0, 0.0, 1.0] + [0.0, 1e-3, 0.0])

    # A's fingers lie across B's palm (to A's right), clear of B's wrist and forearm
    across = np.cross(along_reach(pa, a_root, np.zeros(len(t)), "L"), [0.0, 1.0, 0.0])
    controls[0].arms["L"] = _arm(pa, controls[0], "L", w, hold + [0.0, 0.004, 0.0], [0.7, -1.0, -0.3],
                                 [0.0, -1.0, 0.0], across, flat=True)  # fmt: skip
    b_out = pb.body_dir(b_heading, (-1.0, -0.5, 0.0))  # B's right elbow out to its side
    controls[1].arms["R"] = _arm(pb, controls[1], "R", w, hold, b_out, [0.0, 1.0, 0.0],
                                 along_reach(pb, b_root, b_heading, "R"), flat=True)  # fmt: skip
    specs = [ContactSpec(1, "R", _mask(t, (0.45, t1 + 1.05)), np.tile([0.0, 1.0, 0.0], (len(t), 1)),
                         partner_side="L", guard=_mask(t, (0.1, t1 + 1.5)))]  # fmt: skip
    return Choreography(controls, [a_stance, b_stance], {"hold": (0.4, t1 + 1.1), "turn": (t0, t1)},
                        [(0.5, t1 + 1.0)], specs, ("dance_turn",),
                        ("Two dancers hold hands and one turns under the other's raised arm.",))  # fmt: skip


def calibration(t, perfs, params, rng) -> Choreography:
    """The calibration motion of a studio day, both actors at once, side by side ``approach_distance``
    (default 2 m) apart and never touching: from a relaxed stand each bows, bends to either side
    and twists its trunk (the pelvis tipping, rolling and turning with it over planted feet), nods,
    raises both arms forward, squats, opens the arms out to the sides, then turns once to its right
    on the spot in ten small steps. Every tracked segment tilts (which tells a tracker's
    mounting rotation from the suit's heading) and every one turns about the vertical (which
    tells a mount's offset from the suit's position drift); see :data:`CALIBRATION_TYPE`."""
    gap = params.approach_distance or 2.0
    if gap < 1.2:
        raise ValueError(f"calibration actors stand {gap:.2f} m apart; they need at least 1.2 m to move freely")
    T = len(t)
    t_turn0, t_turn1, n_steps = 6.2, 9.2, 10
    controls, stances = [], []
    for i, p in enumerate(perfs):
        centre = np.array([-gap * i, p.standing_height(), 0.0])  # B stands on A's right
        feet, stance = {}, {}
        dt = (t_turn1 - t_turn0) / n_steps
        for s in SIDES:
            r = p.sk.rest[p.sk.index(f"foot.{s}")]
            place = lambda yaw, r=r, c=centre: c + rot_y(np.array(yaw)) @ np.array([r[0], 0.0, r[2]])  # noqa: E731
            steps = []
            for k in range(n_steps):  # right foot on even steps, left on odd; the last one squares up
                if (k % 2 == 0) == (s == "R") or k == n_steps - 1:
                    yaw = -(k + 1) * 2 * np.pi / n_steps
                    q = place(yaw)
                    steps.append(Step(s, t_turn0 + k * dt, t_turn0 + (k + 1) * dt, (q[0], q[2]), yaw, lift=0.04))
            q0 = place(0.0)
            pos, yaw_t, st = foot_track(t, (q0[0], q0[2]), 0.0, p.ankle_height[s], steps, s)
            feet[s], stance[s] = FootTrack(pos, yaw_t), st
        heading = 0.5 * (feet["L"].heading + feet["R"].heading)
        # knees bent a little while the pelvis tips (a tipped pelvis lifts one hip or the other), then a
        # squat with the arms out in front (thighs, shins and feet turn each their own way)
        dip = keyframes(t, [0.2, 0.6, 4.1, 4.5, 4.9, 5.3, 5.7], [0.0, 0.05, 0.05, 0.03, 0.2, 0.2, 0.0])
        root = p.reachable_root(Controls(np.tile(centre, (T, 1)) - dip[:, None] * [0.0, 1.0, 0.0], heading, feet),
                                fps=1.0 / (t[1] - t[0]))  # fmt: skip
        # trunk (left, up, forward axes): bow, bend left and right, twist both ways
        trunk = keyframes(t, [0.5, 1.1, 1.6, 2.1, 2.6, 3.1, 3.6, 4.1, 4.5],
                          [[0, 0, 0], [0.45, 0, 0], [0, 0, 0], [0, 0, -0.25], [0, 0, 0.25], [0, 0, 0],
                           [0, 0.45, 0], [0, -0.45, 0], [0, 0, 0]])  # fmt: skip
        # the pelvis: tipped forward with the bow, rolled with the side bends, turned with the twists
        # (the feet stay put), then level
        pelvis = keyframes(t, [0.5, 1.1, 1.6, 2.1, 2.6, 3.1, 3.6, 4.1, 4.5],
                           [[0, 0, 0], [0.3, 0, 0], [-0.1, 0, 0], [0, 0, -0.2], [0, 0, 0.2], [0, 0, 0], [0, 0.3, 0],
                            [0, -0.3, 0], [0, 0, 0]])  # fmt: skip
        c = Controls(root, heading, feet, trunk=trunk, pelvis=pelvis)
        eye = _head_of(p, root)
        nod = keyframes(t, [3.9, 4.3, 4.8, 5.2], [0.0, -0.8, 0.6, 0.0])  # look down, then up
        c.look_at = eye + p.body_dir(heading, np.column_stack([np.zeros(T), nod, np.ones(T)]))
        # both arms: hanging, forward to shoulder height, out to the sides, down again
        w = keyframes(t, [4.4, 4.9, 5.7, 6.1], [0.0, 1.0, 1.0, 0.0])
        out = keyframes(t, [5.3, 5.7], [0.0, 1.0])
        for s, sign in SIDES.items():
            sh = p.sk.rest[p.sk.index(f"upperarm01.{s}")] + [0.0, p.floor_offset, 0.0]
            reach = 0.85 * (p.arms[s].reach + np.linalg.norm(p.hand[s].palm_offset))
            ahead = np.array([sh[0], sh[1], sh[2] + reach])
            side = np.array([sh[0] + sign * reach, sh[1], sh[2]])
            local = (1 - out)[:, None] * ahead + out[:, None] * side + [0.0, -p.floor_offset, 0.0]
            palm = p.body_point(root, heading, local)
            fingers = p.body_dir(heading, (1 - out)[:, None] * [0.0, 0.0, 1.0] + out[:, None] * [sign, 0.0, 0.0])
            c.arms[s] = _arm(p, c, s, w, palm, p.body_dir(heading, (sign * 0.3, -1.0, -0.3)),
                             p.body_dir(heading, (0.0, -1.0, 0.0)), fingers)  # fmt: skip
        controls.append(c)
        stances.append(stance)
    return Choreography(controls, stances, {"trunk": (0.5, 4.5), "nod": (3.9, 5.2), "arms": (4.4, 6.1), "squat": (4.5, 5.7),
                                            "turn": (t_turn0, t_turn1)}, [], [], ("calibration",),
                        ("Two people, apart, bow, bend, twist, squat, raise their arms and turn on the spot.",))  # fmt: skip


def _check_distance(d0: float, d1: float, what: str) -> None:
    if d0 < d1:
        raise ValueError(f"approach distance {d0:.2f} m is closer than the {what} distance {d1:.2f} m")


NATURAL_DURATION = {"handshake": 4.0, "hug": 5.2, "high_five": 3.2, "push": 3.6, "pat_on_back": 4.0, "dance_turn": 6.0,
                    "calibration": 9.6}
CHOREOGRAPHIES: dict[str, Callable[..., Choreography]] = {
    "handshake": handshake, "hug": hug, "high_five": high_five, "push": push, "pat_on_back": pat_on_back,
    "dance_turn": dance_turn, "calibration": calibration,
}  # fmt: skip
