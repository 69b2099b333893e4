"""The fit's settings: :class:`FitConfig`.

Units are SI (metres, seconds, radians unless a name says ``_deg``). Every ``sigma_*`` is a standard
deviation: its term is a squared residual over it, so a larger sigma is a weaker term. The collision
schedule these fields drive is described in ``docs/design/fit-collision.md``; the decision records
under ``docs/decisions/`` give each default's reason and ``benchmarks/bench_fit.py`` and
``benchmarks/bench_fit_accuracy.py`` measure its cost and accuracy.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FitConfig:
    """Windows, passes, term weights and the collision schedule of one fit (see the module docstring)."""

    #: ``"windows"``: windows fitted one after another, each with its own collision rounds
    #: (:mod:`~dualhuman_builder.fit.segment`); ``"take"``: the whole take as one problem with a per-frame
    #: collision schedule (:mod:`~dualhuman_builder.fit.take`; the window and segment settings do not apply)
    solver: str = "windows"
    #: frames per window (each window is one L-BFGS problem over both actors)
    window: int = 48
    #: frames a window shares with the one before it (it starts from that one's answer there)
    overlap: int = 4
    #: windows per segment (:func:`~dualhuman_builder.fit.layout.layout`): segments are fitted independently
    #: (in parallel when there are workers) and cross-faded over the ``2 overlap`` frames they share; 0: the
    #: whole take is one segment
    segment_windows: int = 2
    #: L-BFGS iterations of the skeleton pass (every term but the collision term)
    iterations: int = 30
    #: the collision term at all (it needs two actors)
    collision: bool = True
    #: L-BFGS iterations of each collision pass
    collision_iterations: int = 12
    #: L-BFGS iterations of each collision pass of the take solver (``solver = "take"``): one run moves
    #: every frame over a tolerance at once, and the frames share its curvature pairs and step length, so
    #: it needs more than a window's run (chosen on the tuning seeds, docs/decisions/0029-take-solver.md)
    take_iterations: int = 36
    #: the take solver's collision passes: ``"shared"``, one ``torch.optim.LBFGS`` run over every moving
    #: frame (one step length and curvature history for all); ``"runs"``, each block of moving frames its
    #: own L-BFGS run, all evaluated at once (:mod:`~dualhuman_builder.fit.block_lbfgs`)
    take_step: str = "shared"
    #: full collision rounds per window at most, while a frame is over a tolerance below. Each pass is
    #: weighted ``collision_weight_step`` times the one before: the hands' pass at ``collision_weight``,
    #: round 1 at x4, round 2 at x16 ... (docs/decisions/0015-collision-weight-schedule.md)
    collision_rounds: int = 6
    #: each collision pass's weight over the one before it. A larger step is faster but leaves a larger
    #: joint error and rougher motion (docs/decisions/0015-collision-weight-schedule.md;
    #: ``benchmarks/bench_fit.py`` measures both)
    collision_weight_step: float = 4.0
    #: a frame the full rounds start deeper than this (m) is weighted one step ahead of the others from
    #: round 1 on (0: off): past the robust loss's 1 cm scale (``CollisionTerm`` ``robust_sigma_m``) a
    #: vertex's push no longer grows with its depth, so such a frame would spend round 1 barely moving
    #: (docs/decisions/0015-collision-weight-schedule.md)
    collision_deep_m: float = 0.01
    #: a frame is settled when its deepest vertex is within this (m) ...
    collision_tolerance_m: float = 0.002
    #: ... and no more than this share of both bodies' vertices lies inside the other (any depth), so a
    #: palm resting a millimetre deep on the partner goes round again too
    collision_share_tolerance: float = 0.0005
    #: up to twice per window, frames a full round left over the tolerance and moved by less than 20 %
    #: (stuck: interlocked hands) start the next round from their neighbours' answer
    #: (docs/decisions/0017-undo-and-restart.md)
    collision_restart: bool = True
    #: a window the held rounds settle only after a stall, with its skeleton energy (every term but the
    #: collision term) over this many times the skeleton pass's, is fitted again the exact way and the
    #: lower-energy answer kept (0: off): held planes can settle a window by bending the bodies out of
    #: shape (docs/decisions/0016-held-contacts.md)
    collision_energy_ratio: float = 2.0
    #: the collision passes move the frames within this many seconds (s) of a frame the skeleton pass left
    #: in contact, and those between; the rest of the window keeps its skeleton pass (0: the whole window
    #: moves). The smoothness terms couple each frame to two neighbours on either side, so a push fades
    #: out over a few frames (docs/decisions/0015-collision-weight-schedule.md)
    collision_span_s: float = 0.3
    #: each collision pass holds the contacts located where it starts (an evaluation re-reads their
    #: positions only), with exact fallbacks where held rounds stall; False: every contact located at
    #: every evaluation (docs/decisions/0016-held-contacts.md; ``bench_fit_accuracy.py --compare-exact``)
    collision_hold_contacts: bool = True
    #: each full round moves only the frames the pass before it left over a tolerance and the two on
    #: either side of them (the frames their smoothness terms read); the settled ones are held, their
    #: collision term left out, and the check after the round measures only the frames it moved
    #: (docs/decisions/0015-collision-weight-schedule.md). False: every round moves the whole span
    collision_hold_settled: bool = True
    #: vertices outside the other body within this distance (m) are held with the contacts, so the held
    #: term sees them cross in
    collision_margin_m: float = 0.005
    #: the contact pass (:mod:`dualhuman_builder.fit.contact_pass`) pulls together the bodies of frames whose
    #: surfaces the collision passes left within this distance (m) of each other without touching: a contact
    #: the inputs support (0: off; at most the collision term's 1 cm pad)
    contact_reach_m: float = 0.008
    #: ... the nearest this many vertex pairs of each such frame ...
    contact_pairs: int = 4
    #: ... to this gap (m): touching, not penetrating ...
    contact_gap_m: float = 0.002
    #: ... each pair's gap beyond it a squared residual over this (m), against the skeleton energy
    sigma_contact_gap_m: float = 0.002
    #: L-BFGS iterations of the contact pass
    contact_iterations: int = 10
    #: orientation change of each driven bone against the retarget (deg)
    sigma_orientation_deg: float = 2.0
    #: tracker site against the tracker position (m)
    sigma_tracker_m: float = 0.004
    #: std per axis (m) of the suit's segment origins against anny's where the take does not measure it (a
    #: registered shape): sync's tracker offsets, measured on the suit's skeleton, are weighed with the
    #: protocol's sites by it (:mod:`dualhuman_builder.fit.mounts`; regression-predicted joint centres miss by
    #: 12-25 mm); 0: sync's offsets as they are (docs/decisions/0027-tracker-offsets-on-the-body.md)
    sigma_suit_skeleton_m: float = 0.025
    #: joint acceleration, m/s^2 (scaled to a per-frame second difference by fps)
    sigma_accel_m_s2: float = 4.0
    #: sole vertex below the floor (m)
    sigma_floor_m: float = 0.002
    #: horizontal step of a foot in stance between frames (m)
    sigma_slide_m: float = 0.002
    #: a foot in stance stands on the floor: its lowest sole vertex at height 0 (m); 0 turns the term
    #: off (then nothing but the trackers holds a standing body down)
    sigma_contact_m: float = 0.002
    #: the collision loss is a mean over both meshes' vertices (~27,000): this makes a vertex 2 mm deep
    #: cost about as much as a tracker 4 mm off
    collision_weight: float = 3e5
    #: a foot is in stance when its ankle moves slower than this (m/s) ...
    stance_speed_m_s: float = 0.15
    #: ... and its sole is within this height of the floor (m)
    stance_height_m: float = 0.03
    #: let the collision passes open the hands (thumb and fingers, :mod:`dualhuman_builder.body.hands`;
    #: docs/decisions/0014-hand-openings-and-torso-guard.md)
    hand_opening: bool = True
    #: prior on each opening (0 relaxed, 1 flat): opening a hand flat costs as much as a tracker 8 mm off
    sigma_hand_opening: float = 0.5
    #: second difference of the openings, per s^2 (scaled by fps like the joint acceleration)
    sigma_hand_opening_accel_s2: float = 40.0
    #: torch device of the fit's tensors (the collision queries run on the CPU either way;
    #: docs/decisions/0019-fit-on-cpu.md)
    device: str = "cpu"
    #: torch's intra-op CPU threads during the fit (the caller's setting is restored after); 0: leave it.
    #: With 1 a fit of the same inputs repeats exactly; with more, torch's multi-threaded CPU kernels round
    #: differently from run to run (docs/decisions/0018-segments-in-worker-processes.md;
    #: ``bench_fit.py --threads 2`` compares). The collision term's queries keep their own threads
    torch_threads: int = 1


#: the values of :attr:`FitConfig.solver`
SOLVERS = ("windows", "take")
#: the values of :attr:`FitConfig.take_step`
TAKE_STEPS = ("shared", "runs")


def solver_fields(name: str) -> dict:
    """The :class:`FitConfig` fields of a solver named ``name``: a :data:`SOLVERS` value (``take`` with
    :attr:`FitConfig.take_step`'s default), or ``take:<step>`` with a :data:`TAKE_STEPS` value (the
    benchmarks set the take solver's two steps side by side by these names). ValueError names the
    choices."""
    solver, _, step = name.partition(":")
    if solver not in SOLVERS or (step and (solver != "take" or step not in TAKE_STEPS)):
        raise ValueError(f"unknown fit solver {name!r}; choose one of {', '.join(SOLVERS)} or "
                         + ", ".join(f"take:{s}" for s in TAKE_STEPS))  # fmt: skip
    return {"solver": solver, **({"take_step": step} if step else {})}


def config_dict(cfg: FitConfig) -> dict:
    """Every field of ``cfg`` by name, in declaration order (for a track's metadata)."""
    return {k: getattr(cfg, k) for k in cfg.__dataclass_fields__}
