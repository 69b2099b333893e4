"""Long takes: a session that chains interactions with walking and idling between them.

``make_scene(SceneParams(type="session", seed=3, duration=600))`` (``sim://session?seed=3&duration=600``)
draws two actors and has them meet again and again for ``duration`` seconds (default
:data:`DEFAULT_DURATION_S`): each meeting is one of the interaction scenes of :mod:`.scenes`
(:data:`~dualhuman_builder.sim.scenes.SCENE_TYPES`, drawn in shuffled rounds so every type comes
up equally often), generated on its own with the session's two shapes (who plays which role is
drawn; the taller one leads a dance turn) and placed in the room by a rotation about the vertical
and a shift on the floor. Each type is generated :data:`POOL_PER_TYPE` times at most; later
meetings of the type re-place those (so a 10-minute session generates 12 meetings, not 45).
Between two meetings the actors stand, step apart facing each other, stand (swaying a little),
walk to where the next meeting starts (turning to walk and turning back where the way is long)
and stand again. A meeting that breaks the scene contract is drawn again
with another seed, a walk that brings the actors too close is planned again; a session that still
breaks the contract is an error, never a result.

Why composed this way: a meeting's ground truth (contact correction, elbow swivel, distances)
stays exactly what its scene type generates, and a rigid move of both bodies changes none of its
distances, so only the walks need new distances; and the memory stays bounded by one meeting or
one walk at a time (the finished scene holds the poses and the ``(T, V)`` float16 distances:
about 1 GB for 10 minutes at 30 fps).

The joins are continuous: a meeting starts and ends standing still with relaxed arms; a walk
starts exactly at the pose the meeting ended in (same pelvis, same planted feet) and blends
arms, head and trunk into its own over :data:`BLEND_S`, and ends likewise at the next meeting's
first pose.

Timing is recorded in the scene's ``phases``: ``"NN TYPE"`` is meeting ``NN``'s interval (s),
``"NN TYPE PHASE"`` its own phases shifted into the session, ``"NN walk"`` the walk after it;
``contact_phases`` holds every meeting's contact phases; ``stats["interactions"]`` one record
per meeting (:func:`interactions`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from dualhuman_builder.sim.ik import rot_y
from dualhuman_builder.sim.performer import SIDES, Controls, FootTrack, Performer
from dualhuman_builder.sim.scenes import (CONTACT_THRESHOLD, DISTANCE_BAND, NATURAL_DURATION, SCENE_TYPES, Scene,
                                          SceneParams, _params_dict, contract_failures, make_scene, quality_summary,
                                          random_adult_shapes)  # fmt: skip
from dualhuman_builder.sim.timeline import Step, foot_track, keyframes, minjerk, window

#: Session length (s) when ``SceneParams.duration`` is None.
DEFAULT_DURATION_S = 60.0
#: Shortest session (s): one meeting and the stands around it.
MIN_DURATION_S = 10.0
#: Standing still (s) after each meeting's natural length, so that it ends at rest.
SEGMENT_PAD_S = 0.4
#: Time (s) over which a walk blends from the meeting's last pose into its own (and back into the next's first).
BLEND_S = 0.4
#: Longest pelvis travel (m) per half step, and largest turn (rad) per step of the walks.
MAX_STEP_M = 0.3
MAX_TURN = np.radians(30.0)
#: Duration (s) of one step of the walks.
STEP_S = 0.5
#: A move longer than this (m) is walked facing the way (turn, walk, turn); shorter ones are stepped.
LONG_MOVE_M = 0.9
#: Closest pelvis-to-pelvis distance (m, on the floor) a walk may bring the actors to, unless a
#: meeting's own start or end stands closer.
WALK_CLEARANCE_M = 0.7
#: Meeting draws (seeds) tried before a type is given up for another.
SEGMENT_TRIES = 4
#: Distinct draws of each type a session generates; its later meetings of that type re-place one of
#: them (cycling), rotated and shifted anew, with new walks between: a long session then costs the
#: generation of this many meetings per type, not of every meeting.
POOL_PER_TYPE = 2
#: Walk plans tried before the session fails.
WALK_TRIES = 12
#: Sway (m) of the pelvis while standing apart, and its period (s).
SWAY_M, SWAY_PERIOD_S = 0.012, 4.0
#: The room: meetings are placed with their midpoint within this radius (m) of the origin.
ROOM_RADIUS_M = 1.5


@dataclass
class _Stand:
    """Where an actor stands: pelvis ``xz`` (world x, z), ``height`` (m), ``heading`` (rad) and
    each foot's ankle ``(x, z)`` and yaw."""

    xz: np.ndarray
    height: float
    heading: float
    feet: dict[str, tuple[np.ndarray, float]]


def interactions(scene: Scene) -> list[dict]:
    """The meetings of a session scene: ``[{"index", "type", "seed", "start_s", "end_s",
    "contact_phases", "roles"}]`` in time order (``roles[j]``: the session actor playing the
    type's actor ``j``); for a single-interaction scene, one record spanning the scene."""
    if "interactions" in scene.stats:
        return [dict(x) for x in scene.stats["interactions"]]
    n = scene.sequence.num_frames / scene.sequence.fps
    return [{"index": 0, "type": scene.params.type, "seed": scene.params.seed, "start_s": 0.0, "end_s": n,
             "contact_phases": [list(c) for c in scene.contact_phases], "roles": [0, 1]}]  # fmt: skip


def make_session(params: SceneParams, model=None, log: Callable[[str], None] | None = None) -> Scene:
    """Generate the session ``params`` describes (type ``session``; deterministic for a seed)."""
    import roma
    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    t_start = time.perf_counter()
    say = log or (lambda _m: None)
    if params.approach_distance is not None:
        raise ValueError("a session places its meetings itself; it takes no approach distance")
    model = model or get_body_model()
    rng = np.random.default_rng(params.seed)
    shapes = params.shapes or random_adult_shapes(model, rng)
    perfs = [Performer(model, s) for s in shapes]
    fps = params.fps
    duration = DEFAULT_DURATION_S if params.duration is None else float(params.duration)
    if duration < MIN_DURATION_S:
        raise ValueError(f"a session lasts at least {MIN_DURATION_S:g} s; duration {duration:g} s is too short")
    T = int(round(duration * fps))
    J = len(model.bone_names)
    pose = np.zeros((2, T, J, 3), np.float32)
    transl = np.zeros((2, T, 3), np.float32)
    dist = [np.full((T, model.num_vertices), np.nan, np.float16) for _ in (0, 1)]
    stance = [{s: np.ones(T, bool) for s in SIDES} for _ in (0, 1)]
    phases: dict[str, tuple[float, float]] = {}
    contact_phases: list[tuple[float, float]] = []
    records: list[dict] = []

    def to_rotvec(local: np.ndarray) -> np.ndarray:
        return roma.rotmat_to_rotvec(torch.tensor(local)).numpy()

    def put_segment(seg: "_Segment", f0: int) -> None:
        n = seg.frames
        for j, i in enumerate(seg.roles):
            pose[i, f0:f0 + n], transl[i, f0:f0 + n] = seg.pose[j], seg.transl[j]
            dist[i][f0:f0 + n] = seg.scene.distances[j]
            for s in SIDES:
                stance[i][s][f0:f0 + n] = seg.scene.stance[j][s]

    types = _type_rounds(rng)
    pool: dict[str, list] = {}
    used: dict[str, int] = {}

    def draw(kind: str) -> "_Segment":
        """The next meeting of ``kind``: a new draw until the pool holds :data:`POOL_PER_TYPE`, then one of those."""
        have = pool.setdefault(kind, [])
        n = used.get(kind, 0)
        if len(have) < POOL_PER_TYPE:
            have.append(_draw_segment(kind, rng, shapes, perfs, params, model, say))
        used[kind] = n + 1
        return have[n % len(have)]

    # the first meeting, placed around the origin after a short stand
    seg = _place(draw(next(types)), rng.uniform(-np.pi, np.pi), np.zeros(2))
    lead_in = int(round(rng.uniform(0.5, 1.5) * fps))
    if lead_in + seg.frames + int(fps) > T:
        raise ValueError(f"a {duration:g} s session cannot hold its first meeting ({seg.frames / fps:.1f} s)")
    f = lead_in
    for i in (0, 1):
        j = seg.roles.index(i)
        pose[i, :f], transl[i, :f] = seg.pose[j][0], seg.transl[j][0]
    k = 0
    while True:
        put_segment(seg, f)
        a, b = f / fps, (f + seg.frames) / fps
        key = f"{k:02d} {seg.type}"
        phases[key] = (a, b)
        phases.update({f"{key} {name}": (a + p, a + q) for name, (p, q) in seg.scene.phases.items()})
        contact_phases += [(a + p, a + q) for p, q in seg.scene.contact_phases]
        records.append({"index": k, "type": seg.type, "seed": seg.seed, "start_s": a, "end_s": b,
                        "contact_phases": [[a + p, a + q] for p, q in seg.scene.contact_phases],
                        "roles": list(seg.roles)})  # fmt: skip
        say(f"meeting {k:02d}: {seg.type} (seed {seg.seed}) at {a:.1f}-{b:.1f} s")
        f += seg.frames
        ends = [seg.end_stand(i, perfs[i]) for i in (0, 1)]
        end_pose = [(seg.pose[seg.roles.index(i)][-1], seg.transl[seg.roles.index(i)][-1]) for i in (0, 1)]
        # the next meeting and the walk to it; or, when they no longer fit, the closing walk apart
        nxt, walk, cand = None, None, None
        if T - f > 6.0 * fps:
            for attempt in range(WALK_TRIES):
                if attempt and attempt % (WALK_TRIES // 3) == 0:
                    cand = None  # this meeting's start keeps failing: another meeting
                while cand is None:
                    try:
                        cand = draw(next(types))
                    except _NoSegment as e:
                        say(f"no draw of {e} met the contract; another type")
                if f + cand.frames + int(4 * fps) > T:
                    break  # it does not fit any more: close the session
                plan = _plan_walk(ends, rng)
                placed = _place(cand, plan.direction, plan.centre)
                starts = [placed.start_stand(i, perfs[i]) for i in (0, 1)]
                start_pose = [(placed.pose[placed.roles.index(i)][0], placed.transl[placed.roles.index(i)][0])
                              for i in (0, 1)]  # fmt: skip
                w = _walk_between(ends, plan.apart, starts, perfs, rng, fps, end_pose, start_pose, to_rotvec)
                if w is None:
                    say(f"walk to a {cand.type} brings the pelvises too close; planning again")
                    continue
                if f + w.frames + cand.frames + int(fps) > T:
                    break
                if _walk_contract_ok(model, w, perfs, fps, end_pose, start_pose):
                    nxt, walk = placed, w
                    break
                say(f"walk to a {cand.type}: bodies {1000 * w.closest:.0f} mm apart, a planted foot slides "
                    f"{1000 * w.slide:.1f} mm; planning again")  # fmt: skip
            else:
                raise ValueError(f"session seed {params.seed}: no walk to meeting {k + 1} kept the actors apart")
        if walk is None:  # the closing walk apart, then standing until the end
            for _ in range(WALK_TRIES):
                plan = _plan_walk(ends, rng)
                walk = _walk_between(ends, plan.apart, None, perfs, rng, fps, end_pose, None, to_rotvec, T - f)
                if walk is not None and _walk_contract_ok(model, walk, perfs, fps, end_pose):
                    break
                walk = None
            if walk is None:
                raise ValueError(f"session seed {params.seed}: the closing walk apart kept breaking the contract")
        for i in (0, 1):
            pose[i, f:f + walk.frames], transl[i, f:f + walk.frames] = walk.pose[i], walk.transl[i]
            dist[i][f:f + walk.frames] = walk.distances[i]
            for s in SIDES:
                stance[i][s][f:f + walk.frames] = walk.stance[i][s]
        phases[f"{k:02d} walk"] = (f / fps, (f + walk.frames) / fps)
        f += walk.frames
        if nxt is None:
            break
        seg, k = nxt, k + 1
    assert f == T, (f, T)
    tracks = tuple(BodyTrack.from_model(model, pose[i], transl[i], perfs[i].sk.shape, fps, actor=params.names[i])
                   for i in (0, 1))  # fmt: skip
    kinds = tuple(dict.fromkeys(r["type"] for r in records))
    seq = InteractionSequence(tracks, take=f"sim-session-{params.seed}", labels=kinds,
                              text=("Two people meet again and again, walking about between meetings: "
                                    + ", ".join(r["type"].replace("_", " ") for r in records) + ".",),
                              meta={"scene": _params_dict(params)})  # fmt: skip
    scene = Scene(params, seq, (dist[0], dist[1]), stance, phases, contact_phases)
    scene.stats = {"generation_s": round(time.perf_counter() - t_start, 2), **quality_summary(scene),
                   "interactions": records}  # fmt: skip
    failures = contract_failures(scene.stats)
    if failures:
        raise ValueError(f"session seed {params.seed} breaks the scene contract: " + "; ".join(failures))
    return scene


# ============================================================================ meetings
class _NoSegment(Exception):
    """No draw of a type met the contract."""


def _type_rounds(rng):
    while True:
        yield from (SCENE_TYPES[i] for i in rng.permutation(len(SCENE_TYPES)))


@dataclass
class _Segment:
    type: str
    seed: int
    scene: Scene
    roles: tuple[int, int]  # roles[j]: the session actor playing the scene's actor j
    pose: list  # per scene actor (T, J, 3) rotation vectors, placed in the room
    transl: list  # per scene actor (T, 3)

    @property
    def frames(self) -> int:
        return self.scene.sequence.num_frames

    def _stand(self, actor: int, perf: Performer, frame: int) -> _Stand:
        j = self.roles.index(actor)
        return _stand_of(perf, self.pose[j][frame], self.transl[j][frame])

    def end_stand(self, actor: int, perf: Performer) -> _Stand:
        return self._stand(actor, perf, -1)

    def start_stand(self, actor: int, perf: Performer) -> _Stand:
        return self._stand(actor, perf, 0)


def _draw_segment(kind: str, rng, shapes, perfs, params: SceneParams, model, say) -> _Segment:
    """A meeting of type ``kind`` that meets the contract, as its scene type generates it (not yet placed)."""
    if kind == "dance_turn":
        roles = (0, 1) if perfs[0].stature >= perfs[1].stature else (1, 0)  # the taller one leads
    else:
        roles = (0, 1) if rng.random() < 0.5 else (1, 0)
    for _ in range(SEGMENT_TRIES):
        seed = int(rng.integers(0, 2**31 - 1))
        p = SceneParams(type=kind, seed=seed, shapes=(shapes[roles[0]], shapes[roles[1]]), tempo=params.tempo,
                        duration=NATURAL_DURATION[kind] / params.tempo + SEGMENT_PAD_S, fps=params.fps,
                        names=(params.names[roles[0]], params.names[roles[1]]))  # fmt: skip
        try:
            scene = make_scene(p, model=model)
        except ValueError as e:
            say(f"{kind} seed {seed}: {e}; drawing again")
            continue
        failures = contract_failures(scene.stats)
        if failures:
            say(f"{kind} seed {seed} breaks the contract ({'; '.join(failures)}); drawing again")
            continue
        return _Segment(kind, seed, scene, roles, [np.array(a.pose) for a in scene.sequence.actors],
                        [np.array(a.transl) for a in scene.sequence.actors])  # fmt: skip
    raise _NoSegment(kind)


def _place(seg: _Segment, direction: float, centre) -> _Segment:
    """``seg`` turned about the vertical so that the line from session actor 1's starting pelvis to
    actor 0's points along ``direction`` (heading angle, rad), and shifted so the midpoint of the
    starting pelvises is at ``centre`` (x, z). Distances and stance do not change."""
    import roma
    import torch

    tr = [np.asarray(a.transl, np.float64) for a in seg.scene.sequence.actors]
    a0, a1 = tr[seg.roles.index(0)][0], tr[seg.roles.index(1)][0]
    theta = direction - np.arctan2(a0[0] - a1[0], a0[2] - a1[2])
    R = rot_y(np.array(theta))
    mid = 0.5 * (a0 + a1) * [1.0, 0.0, 1.0]
    shift = np.array([centre[0], 0.0, centre[1]]) - R @ mid
    pose, transl = [], []
    for a, t in zip(seg.scene.sequence.actors, tr):
        P = np.array(a.pose)
        root = roma.rotvec_to_rotmat(torch.tensor(P[:, 0], dtype=torch.float64)).numpy()
        P[:, 0] = roma.rotmat_to_rotvec(torch.tensor(R @ root)).numpy()
        pose.append(P.astype(np.float32))
        transl.append((t @ R.T + shift).astype(np.float32))
    return _Segment(seg.type, seg.seed, seg.scene, seg.roles, pose, transl)


def _stand_of(perf: Performer, pose: np.ndarray, transl: np.ndarray) -> _Stand:
    """Where an actor posed ``pose (J, 3)``, ``transl (3,)`` stands: pelvis, heading, ankles and foot yaws."""
    import roma
    import torch

    root = roma.rotvec_to_rotmat(torch.tensor(pose[0], dtype=torch.float64)).numpy()
    fwd = root @ [0.0, 0.0, 1.0]
    local = perf.sk.identity(1)
    local[0] = roma.rotvec_to_rotmat(torch.tensor(pose, dtype=torch.float64)).numpy()
    heads, _ = perf.sk.fk(local, np.asarray(transl, np.float64)[None])
    feet = {}
    for s in SIDES:
        ankle, toe = heads[0, perf.sk.index(f"foot.{s}")], heads[0, perf.sk.index(f"toe3-1.{s}")]
        r = perf.sk.rest[perf.sk.index(f"toe3-1.{s}")] - perf.sk.rest[perf.sk.index(f"foot.{s}")]
        d = toe - ankle
        feet[s] = (ankle[[0, 2]].copy(), float(np.arctan2(d[0], d[2]) - np.arctan2(r[0], r[2])))
    return _Stand(np.asarray(transl, np.float64)[[0, 2]].copy(), float(transl[1]), float(np.arctan2(fwd[0], fwd[2])),
                  feet)  # fmt: skip


# ============================================================================ walks
@dataclass
class _Plan:
    apart: list  # per actor: (x, z) where it stands after stepping apart
    direction: float  # heading angle of the line from actor 1's to actor 0's start at the next meeting
    centre: np.ndarray  # the midpoint of their starting pelvises (x, z)


def _plan_walk(ends: list[_Stand], rng) -> _Plan:
    """Step apart along the line between the actors, then meet again nearby: the next meeting's
    line is this one turned by up to 25 degrees, its midpoint drawn towards the room's centre,
    half the time a few steps away."""
    e0, e1 = ends[0].xz, ends[1].xz
    u = e0 - e1
    u = u / max(np.linalg.norm(u), 1e-9)
    apart = [e0 + u * rng.uniform(0.4, 0.9), e1 - u * rng.uniform(0.4, 0.9)]
    centre = 0.25 * (apart[0] + apart[1])
    if rng.random() < 0.5:  # walk somewhere else in the room
        a = rng.uniform(-np.pi, np.pi)
        centre = centre + rng.uniform(0.6, 1.5) * np.array([np.cos(a), np.sin(a)])
    r = np.linalg.norm(centre)
    if r > ROOM_RADIUS_M:
        centre = centre * (ROOM_RADIUS_M / r)
    return _Plan(apart, float(np.arctan2(u[0], u[1]) + rng.uniform(-0.45, 0.45)), centre)


@dataclass
class _Walk:
    frames: int
    pose: list  # per session actor (n, J, 3)
    transl: list  # (n, 3)
    stance: list  # per actor {side: (n,)}
    distances: list | None = None  # per actor (n, V) float16
    closest: float = float("inf")  # smallest distance (m) between the bodies over the walk
    slide: float = 0.0  # largest planted-foot slide (m per frame), joins with the meetings included


def _walk_between(ends, apart, starts, perfs, rng, fps, end_pose, start_pose, to_rotvec, frames: int | None = None):
    """The walk from the meeting that ended at ``ends`` (per actor :class:`_Stand`; ``end_pose``
    its poses) to the one starting at ``starts`` (``start_pose``), via ``apart``: stand, step
    apart facing each other, stand swaying, walk to the starts, stand. With ``starts`` None, the
    closing walk: step apart and stand until ``frames`` are filled. None when the plan cannot
    keep the actors apart or does not fit in ``frames``."""
    idle1, idle2, idle3 = rng.uniform(0.6, 1.8), rng.uniform(0.8, 2.5), rng.uniform(0.5, 1.2)
    face = [_heading_to(apart[i], apart[1 - i]) for i in (0, 1)]
    out_moves = [[(apart[i], face[i])] for i in (0, 1)]
    out_d = max(_moves_time(ends[i], out_moves[i]) for i in (0, 1))
    t_out = idle1
    t_in0 = t_out + out_d + idle2
    if starts is None:
        total = frames / fps
        if t_in0 > total:  # no room to step apart: stand
            out_moves = [[], []]
            t_in0 = total
        n = frames
        in_moves, t_in1 = [[], []], t_in0
    else:
        apart_stand = [_Stand(apart[i], ends[i].height, face[i], {}) for i in (0, 1)]
        in_moves = [_route(apart_stand[i], starts[i]) for i in (0, 1)]
        in_d = max(_moves_time(apart_stand[i], in_moves[i]) for i in (0, 1))
        t_in1 = t_in0 + in_d
        n = int(round((t_in1 + idle3) * fps))
    t = np.arange(n) / fps
    controls, stances = [], []
    for i, perf in enumerate(perfs):
        root_keys, heading_keys, steps = [], [], []
        cur = ends[i]
        # out: both start together; in: both arrive together
        cur = _add_moves(perf, cur, out_moves[i], t_out, root_keys, heading_keys, steps)
        d_in = _moves_time(cur, in_moves[i])
        n_out = len(steps)
        cur = _add_moves(perf, cur, in_moves[i], t_in1 - d_in, root_keys, heading_keys, steps)
        if starts is not None:  # each foot's last step lands exactly where the next meeting has it
            for s in SIDES:
                last = [k for k in range(n_out, len(steps)) if steps[k].foot == s]
                if last:
                    st = steps[last[-1]]
                    xz, yaw = starts[i].feet[s]
                    st.to, st.heading = (float(xz[0]), float(xz[1])), st.heading + _wrap(yaw - st.heading)
        root = np.tile([ends[i].xz[0], ends[i].height, ends[i].xz[1]], (n, 1)).astype(np.float64)
        heading = np.full(n, ends[i].heading)
        for (t0, t1, p0, p1), (_, _, h0, h1) in zip(root_keys, heading_keys):
            sel = t >= t0
            root[sel] = keyframes(t[sel], [t0, t1], [p0, p1])
            heading[sel] = keyframes(t[sel], [t0, t1], [h0, h1])
        if starts is not None:  # settle to the next meeting's pelvis height
            root[:, 1] = keyframes(t, [t_in1 - 0.3, t_in1], [root[0, 1], starts[i].height]) if n else root[:, 1]
        # a slight sway while standing apart
        sway = SWAY_M * np.sin(2 * np.pi * t / SWAY_PERIOD_S) * window(t, t_out + out_d, t_in0, 0.5)
        root += sway[:, None] * perf.body_dir(heading, (1.0, 0.0, 0.0))
        feet, st = {}, {}
        for s in SIDES:
            start_xz, start_yaw = ends[i].feet[s]
            pos, yaw, mask = foot_track(t, tuple(start_xz), start_yaw, perf.ankle_height[s], steps, s)
            feet[s], st[s] = FootTrack(pos, yaw), mask
        root = perf.reachable_root(Controls(root, heading, feet), fps=fps)
        controls.append(Controls(root, heading, feet))
        stances.append(st)
    # clearance: the pelvises never closer than the walk's own ends allow
    gap = np.linalg.norm((controls[0].root - controls[1].root)[:, [0, 2]], axis=1)
    allowed = min(WALK_CLEARANCE_M, gap[0] - 0.02, gap[-1] - 0.02)
    if gap.min() < allowed:
        return None
    # eyes: on the partner while standing, ahead while walking far
    for i, perf in enumerate(perfs):
        c = controls[i]
        partner = controls[1 - i].root + [0.0, 0.93 * perfs[1 - i].stature - perfs[1 - i].floor_offset, 0.0]
        eye_up = 0.93 * perf.stature - perf.floor_offset
        ahead = perf.body_point(c.root, c.heading, (0.0, eye_up, 2.0))
        far = np.clip((gap - 1.6) / 0.8, 0.0, 1.0)
        c.look_at = (1 - far)[:, None] * partner + far[:, None] * ahead
    poses, transls = [], []
    nb = max(1, int(round(BLEND_S * fps)))
    for i, perf in enumerate(perfs):
        local, tr = perf.solve(controls[i])
        P = to_rotvec(local).astype(np.float32)
        P = _blend(P, end_pose[i][0], np.arange(n), nb)
        if start_pose is not None:
            P = _blend(P, start_pose[i][0], n - 1 - np.arange(n), nb)
        poses.append(P)
        transls.append(tr.astype(np.float32))
    return _Walk(n, poses, transls, stances)


def _blend(P: np.ndarray, boundary: np.ndarray, k: np.ndarray, nb: int) -> np.ndarray:
    """Poses ``P (n, J, 3)`` (rotation vectors) blended towards ``boundary (J, 3)`` where ``k`` (frames
    from the boundary) is below ``nb``: weight 1 on the boundary at ``k = -1``, easing out by minimum jerk."""
    from scipy.spatial.transform import Rotation, Slerp  # noqa: F401

    w = 1.0 - minjerk((k + 1) / (nb + 1))
    sel = np.flatnonzero(w > 0)
    if not len(sel):
        return P
    out = P.copy()
    J = P.shape[1]
    qa = Rotation.from_rotvec(np.broadcast_to(boundary, (len(sel), J, 3)).reshape(-1, 3)).as_quat()
    qb = Rotation.from_rotvec(P[sel].reshape(-1, 3)).as_quat()
    qb *= np.sign((qa * qb).sum(-1, keepdims=True) + 1e-12)
    ww = np.repeat(w[sel], J)[:, None]
    q = ww * qa + (1 - ww) * qb
    out[sel] = Rotation.from_quat(q / np.linalg.norm(q, axis=-1, keepdims=True)).as_rotvec().reshape(len(sel), J, 3)
    return out


def _heading_to(a, b) -> float:
    d = np.asarray(b) - np.asarray(a)
    return float(np.arctan2(d[0], d[1]))


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def _route(cur: _Stand, goal: _Stand) -> list:
    """Moves ``[(xz, heading)]`` from ``cur`` to ``goal``: stepped when short, else turn, walk facing the way, turn."""
    d = np.asarray(goal.xz) - cur.xz
    if np.linalg.norm(d) <= LONG_MOVE_M:
        return [(goal.xz, goal.heading)]
    way = float(np.arctan2(d[0], d[1]))
    return [(cur.xz, way), (goal.xz, way), (goal.xz, goal.heading)]


def _n_halves(dist: float, turn: float) -> int:
    return max(1, int(np.ceil(dist / MAX_STEP_M - 1e-9)), int(np.ceil(abs(turn) / MAX_TURN - 1e-9)))


def _moves_time(cur: _Stand, moves: list) -> float:
    total, xz, h = 0.0, cur.xz, cur.heading
    for goal_xz, goal_h in moves:
        dist, turn = float(np.linalg.norm(np.asarray(goal_xz) - xz)), _wrap(goal_h - h)
        if dist > 1e-4 or abs(turn) > 1e-4:
            total += (_n_halves(dist, turn) + 1) * STEP_S
        xz, h = np.asarray(goal_xz), h + turn
    return total


def _add_moves(perf: Performer, cur: _Stand, moves: list, t0: float, root_keys, heading_keys, steps) -> _Stand:
    """Append the footsteps (:class:`Step`) and the pelvis's key spans of ``moves`` from ``t0``; the
    feet leapfrog (the one on the side of travel or turn leads) and end side by side."""
    xz, h = cur.xz, cur.heading
    for goal_xz, goal_h in moves:
        goal_xz = np.asarray(goal_xz, np.float64)
        dist, turn = float(np.linalg.norm(goal_xz - xz)), _wrap(goal_h - h)
        if dist < 1e-4 and abs(turn) < 1e-4:
            continue
        halves = _n_halves(dist, turn)
        side = (rot_y(np.array(-h)) @ np.array([*(goal_xz - xz)[:1], 0.0, *(goal_xz - xz)[1:]]))[0]  # + to my left
        lead = ("L" if turn > 0 else "R") if abs(turn) > 1e-3 and dist < 0.2 else ("L" if side > 0 else "R")
        other = "R" if lead == "L" else "L"
        plan = [(lead if j % 2 else other, j / halves) for j in range(1, halves + 1)]
        plan.append((other if halves % 2 else lead, 1.0))
        t1 = t0 + len(plan) * STEP_S
        for k, (foot, frac) in enumerate(plan):
            p = xz + frac * (goal_xz - xz)
            hf = h + frac * turn
            r = perf.sk.rest[perf.sk.index(f"foot.{foot}")]
            at = np.array([p[0], 0.0, p[1]]) + rot_y(np.array(hf)) @ np.array([r[0], 0.0, r[2]])
            steps.append(Step(foot, t0 + k * STEP_S, t0 + (k + 1) * STEP_S, (at[0], at[2]), hf, lift=0.05))
        y = cur.height
        root_keys.append((t0, t1, np.array([xz[0], y, xz[1]]), np.array([goal_xz[0], y, goal_xz[1]])))
        heading_keys.append((t0, t1, h, h + turn))
        xz, h, t0 = goal_xz, h + turn, t1
    return _Stand(xz, cur.height, h, {})


def _walk_contract_ok(model, walk: _Walk, perfs, fps: float, end_pose=None, start_pose=None) -> bool:
    """Check a walk: the planted feet (joined to ``end_pose``, the meeting's last pose before it,
    and ``start_pose``, the next one's first, per actor ``(pose, transl)``) slide well within the
    contract; then compute its ground-truth distances (only frames where the bodies come within the
    band: elsewhere NaN) and check that the bodies never interpenetrate, nor come closer than the
    contact threshold (or than the meetings at either end of the walk leave them)."""
    from dualhuman_builder.geometry.distance import get_pair_distance
    from dualhuman_builder.sim.quality import sign_by_winding
    from dualhuman_builder.tracks import BodyTrack

    from dualhuman_builder.sim.quality import foot_sliding
    from dualhuman_builder.sim.scenes import MAX_STANCE_SLIDE_M

    n = walk.frames
    tracks = [BodyTrack.from_model(model, walk.pose[i], walk.transl[i], perfs[i].sk.shape, fps) for i in (0, 1)]
    # planted feet, from the meeting's last frame to the next one's first: well within the contract
    for i in (0, 1):
        ends = [x for x in (end_pose, start_pose) if x is not None]
        P = np.concatenate([walk.pose[i], *[np.asarray(e[i][0])[None] for e in ends]])
        X = np.concatenate([walk.transl[i], *[np.asarray(e[i][1])[None] for e in ends]])
        order = np.r_[n, np.arange(n), n + 1] if start_pose is not None else np.r_[n, np.arange(n)]
        if end_pose is None:
            order = np.arange(n)
        joined = BodyTrack.from_model(model, P[order], X[order], perfs[i].sk.shape, fps)
        pad = [True] if end_pose is not None else []
        tail = [True] if start_pose is not None else []
        stance = {s: np.r_[pad, walk.stance[i][s], tail].astype(bool) for s in SIDES}
        walk.slide = max(walk.slide, foot_sliding(joined, stance))
    if walk.slide > 0.8 * MAX_STANCE_SLIDE_M:
        return False
    d = [np.full((n, model.num_vertices), np.nan, np.float16) for _ in (0, 1)]
    pair = get_pair_distance()
    chunk = 128
    for s in range(0, n, chunk):
        fr = np.arange(s, min(n, s + chunk))
        va, vb = (tr.compute(frames=fr)["vertices"] for tr in tracks)
        lo = np.maximum(va.min(1), vb.min(1)) - DISTANCE_BAND
        hi = np.minimum(va.max(1), vb.max(1)) + DISTANCE_BAND
        close = np.flatnonzero(np.all(lo <= hi, axis=1))
        if not len(close):
            continue
        da, db = np.full((len(fr), model.num_vertices), np.nan, np.float16), np.full_like(d[0][:len(fr)], np.nan)
        for k in close:
            da[k], db[k] = pair(va[k], vb[k], DISTANCE_BAND)
        sign_by_winding((da, db), va, vb, close)
        d[0][fr], d[1][fr] = da, db
    walk.distances = d
    # where it blends out of or into a meeting, the meeting's own distances hold; between, no touch
    low = np.minimum(*(np.nan_to_num(x.astype(np.float32), nan=np.inf).min(1) for x in d))
    # never closer than the contact threshold, or than the meetings left them (standing close after one)
    floor = min(CONTACT_THRESHOLD, float(low[0]) - 0.001, float(low[-1]) - 0.001)
    walk.closest = float(low.min(initial=np.inf))
    return bool(walk.closest >= max(floor, -0.001))
