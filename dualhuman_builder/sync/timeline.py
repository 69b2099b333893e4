"""Sync stage: every stream of a take on one timeline, with the estimates and their uncertainty.

Timeline
    seconds on the **reference suit's** clock (the first actor's suit), 0 at its first sample;
    frames at ``fps`` over the span every suit covers. Another stream's device time maps onto it
    through the host clock: ``device -> host`` by its own robust lower-envelope line fit
    (:func:`~dualhuman_builder.sync.clock.fit_clock`: offset and drift, delayed packets rejected),
    then ``host -> reference device`` by the inverse of the reference's fit.

Trackers
    the host clock cannot see a difference of transport latency between the suit and the trackers,
    so each tracker's residual lag against the suit segment it is strapped to is measured by
    cross-correlating angular-speed magnitudes (independent of how the tracker is mounted,
    :func:`~dualhuman_builder.sync.lag.estimate_lag`); trackers of one source share a clock, so
    their lags are combined into one correction. Then each tracker's mounting rotation and offset on
    its segment, the suit's heading against the tracker world, the suit's position drift and its
    segments' misalignments along each tracker's chain are solved by least squares
    (:func:`~dualhuman_builder.sync.mount.calibrate_mounts`). With ``mounts_from`` (the sync of the
    studio day's calibration take), each tracker found there by serial, on the same segment of the
    same actor, keeps that take's mount (:class:`~dualhuman_builder.sync.mount_types.CarriedMounts`):
    a take whose actors hardly move then still gets its heading and its trackers' shared offset
    right. The calibration's lag per tracker source is the day's latency difference, and is
    averaged with the take's own (``docs/decisions/0013-calibration-take.md``).

Inputs come from :func:`~dualhuman_builder.capture.log.reader.read_columns`: suits
``suits/mvn/<c>/SuitFrame`` with channel metadata ``actor``; trackers ``.../TrackerSample`` with
``actor`` and ``segment`` (from the rig). A suit's 23 body segments are taken by name: segments
beyond them (a prop added mid-take, finger segments) are set aside and a sample that lacks a body
segment (a stray datagram with another segment count) is left out; the report's ``suit_segments``
counts both per channel, with a warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.rig import tracker_site
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.fileio import load_npz, save_npz
from dualhuman_builder.sync.priors import MISALIGNMENT_DEG
from dualhuman_builder.sync.resample import resample_linear, resample_quat

SYNC_VERSION = 1
#: A frame is valid only when samples on both sides lie within this many seconds of each other.
MAX_GAP_S = 0.05
#: Knot spacing (s) of the suit position drift solved with the mounts: the drift is slow, and
#: finer knots let it absorb the suit's limb errors and the mounts' offsets.
MOUNT_DRIFT_KNOTS_S = 1.0
#: Prior std per axis (deg) of each suit segment's constant misalignment, solved with the mounts
#: (:class:`~dualhuman_builder.sync.mount_types.SuitChain`; ``docs/decisions/0012-suit-chain-misalignments.md``).
CHAIN_PRIOR_DEG = MISALIGNMENT_DEG
_PARENT_INDEX = [MVN_SEGMENTS.index(MVN_PARENTS[g]) if MVN_PARENTS[g] else -1 for g in MVN_SEGMENTS]
#: Speed spread (std) below which a stream is too still for a lag: angular rad/s, linear m/s.
MIN_ANGULAR_MOTION = 0.02
MIN_LINEAR_MOTION = 0.02
#: A heading (suit world in the tracker world) less certain than this (1-sigma, deg) is reported.
HEADING_WARN_DEG = 1.0
#: The trackers' shared offset on their segments (where the root sits in the body) less certain
#: than this (1-sigma, mm) is reported: the fit's root inherits it (the goal is 10 mm).
COMMON_OFFSET_WARN_MM = 8.0


class SyncError(DualhumanError):
    """A take cannot be put on one timeline (no suit, too short, no motion to correlate...)."""


@dataclass
class ActorStreams:
    """One actor's streams on the timeline (``T`` frames).

    ``suit_rot (T, 23, 4)`` xyzw and ``suit_pos (T, 23, 3)`` m in the suit's world (MVN segment
    order), ``suit_valid (T,)``; trackers ``serials (K,)``, ``segments (K,)`` (MVN names),
    ``trk_rot (T, K, 4)``, ``trk_pos (T, K, 3)`` in the tracker world, ``trk_valid (T, K)``.
    ``mounts``: the :class:`~dualhuman_builder.sync.mount_types.MountCalibration` (None without trackers).
    """

    actor: str
    suit_rot: np.ndarray
    suit_pos: np.ndarray
    suit_valid: np.ndarray
    serials: tuple[str, ...] = ()
    segments: tuple[str, ...] = ()
    trk_rot: np.ndarray | None = None
    trk_pos: np.ndarray | None = None
    trk_valid: np.ndarray | None = None
    mounts: Any = None


@dataclass
class SyncResult:
    """``times_s (T,)`` frame times on the timeline; ``actors`` in rig order; ``report``: the
    JSON-able estimates (clocks, lags, mounts) with uncertainties."""

    fps: float
    times_s: np.ndarray
    actors: list[ActorStreams]
    report: dict = field(default_factory=dict)

    def actor(self, name: str) -> ActorStreams:
        """The streams of actor ``name``; KeyError naming the take's actors when there is none."""
        for a in self.actors:
            if a.actor == name:
                return a
        raise KeyError(f"no actor {name!r} in the synced take; it has {[a.actor for a in self.actors]}")

    def save(self, path: str | Path) -> Path:
        """One ``.npz`` (atomic, :func:`~dualhuman_builder.fileio.save_npz`): the arrays under
        ``<actor>/...``, each actor's mounts under ``<actor>/mount/<field>``, the report as metadata."""
        arrays: dict[str, np.ndarray] = {"times_s": self.times_s}
        for a in self.actors:
            p = f"{a.actor}/"
            arrays.update({p + "suit_rot": a.suit_rot, p + "suit_pos": a.suit_pos, p + "suit_valid": a.suit_valid})
            if a.serials:
                arrays.update({p + "trk_rot": a.trk_rot, p + "trk_pos": a.trk_pos, p + "trk_valid": a.trk_valid})
                if a.mounts is not None:
                    arrays.update({f"{p}mount/{k}": getattr(a.mounts, k) for k in a.mounts.__dataclass_fields__})
        meta = {"fps": self.fps, "actors": [{"actor": a.actor, "serials": list(a.serials), "segments": list(a.segments)}
                                            for a in self.actors], "report": self.report}  # fmt: skip
        return save_npz(path, "SyncResult", SYNC_VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | Path) -> "SyncResult":
        """A result written by :meth:`save`; FormatError for a missing, foreign or newer file."""
        from dualhuman_builder.sync.mount_types import MountCalibration

        arrays, meta = load_npz(path, "SyncResult", SYNC_VERSION, required=("times_s",))
        actors = []
        for info in meta["actors"]:
            p = f"{info['actor']}/"
            a = ActorStreams(info["actor"], arrays[p + "suit_rot"], arrays[p + "suit_pos"], arrays[p + "suit_valid"],
                             tuple(info["serials"]), tuple(info["segments"]))  # fmt: skip
            if a.serials:
                a.trk_rot, a.trk_pos, a.trk_valid = arrays[p + "trk_rot"], arrays[p + "trk_pos"], arrays[p + "trk_valid"]
                if f"{p}mount/rotations" in arrays:
                    a.mounts = MountCalibration(**{k: arrays[f"{p}mount/{k}"] for k in MountCalibration.__dataclass_fields__
                                                         if f"{p}mount/{k}" in arrays})  # fmt: skip
            actors.append(a)
        return cls(float(meta["fps"]), arrays["times_s"], actors, meta.get("report", {}))


# ------------------------------------------------------------------------------------------
@dataclass
class _Stream:
    """One suit or tracker channel of a take: ``device_ns``, ``host_ns`` ``(N,)`` float64 ns, its
    ``cols`` as :func:`~dualhuman_builder.capture.log.reader.read_columns` gives them."""

    key: str
    actor: str | None
    source: str
    device_ns: np.ndarray  # float64, device clock
    host_ns: np.ndarray
    cols: dict


def _suit_device_ns(cols: dict) -> np.ndarray:
    """MVN time codes are whole milliseconds; the sample counter is exact. A least-squares line of
    time code against counter gives each sample's device time without the 1 ms steps."""
    counter = np.asarray(cols["sample_counter"], dtype=np.float64)
    tc = np.asarray(cols["device_time_ns"], dtype=np.float64)
    if len(counter) >= 10 and np.ptp(counter) > 0:
        slope, icpt = np.polyfit(counter - counter[0], tc - tc[0], 1)
        if slope > 0:
            return tc[0] + icpt + slope * (counter - counter[0])
    return tc


def _body_columns(key: str, cols: dict) -> tuple[dict, dict]:
    """A suit channel's columns with only the body's 23 segments, in MVN order, picked by name;
    samples that lack one of them are left out. Returns ``(columns, counts)``: ``counts`` says how
    many samples were left out and which other segments (props, fingers, strays) were set aside,
    on how many samples (empty when every sample carries exactly the body)."""
    names = tuple(cols["segment_names"])
    lacking = [g for g in MVN_SEGMENTS if g not in names]
    if lacking:
        raise SyncError(f"{key}: no sample carries the body segments {lacking}",
                        fix="record the suit's full body (23 segments)")  # fmt: skip
    idx = np.array([names.index(g) for g in MVN_SEGMENTS])
    n = len(np.asarray(cols["host_time_ns"]))
    present = cols.get("segment_names__present")
    keep = np.ones(n, dtype=bool) if present is None else np.asarray(present)[:, idx].all(axis=1)
    out = {k: (v[keep] if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == n else v) for k, v in cols.items()
           if not k.startswith("segment_names__")}  # fmt: skip
    out["orientations"] = np.asarray(cols["orientations"])[keep][:, idx]
    out["positions"] = np.asarray(cols["positions"])[keep][:, idx]
    out["segment_names"] = tuple(MVN_SEGMENTS)
    counts: dict = {}
    extra = [g for g in names if g not in MVN_SEGMENTS]
    if extra:
        cols_extra = [names.index(g) for g in extra]
        others = np.asarray(present)[keep][:, cols_extra].any(axis=1) if present is not None else keep[keep]
        counts["segments_set_aside"] = extra
        counts["samples_with_them"] = int(others.sum())
    if not keep.all():
        counts["samples_left_out"] = int((~keep).sum())
    return out, counts


def _streams(columns: dict, notes: dict | None = None) -> tuple[list[_Stream], list[_Stream]]:
    """``(suits, trackers)`` of a take's columns: suits in MVN character order (their body
    segments only, :func:`_body_columns`; what was set aside goes to ``notes`` by channel),
    trackers bound to an actor's segment by the rig (others are left out)."""
    suits, trackers = [], []
    for key, ch in columns.items():
        meta = ch.metadata or {}
        if key.endswith("/SuitFrame") and ch.count:
            cols, counts = _body_columns(key, ch.columns)
            if counts and notes is not None:
                notes[key] = counts
            if not len(cols["host_time_ns"]):
                continue
            actor = meta.get("actor") or f"character{int(cols['character'][0])}"
            suits.append(_Stream(key, actor, meta.get("source", ""), _suit_device_ns(cols),
                                 np.asarray(cols["host_time_ns"], dtype=np.float64), cols))  # fmt: skip
        elif key.endswith("/TrackerSample") and ch.count and meta.get("actor") and meta.get("segment"):
            trackers.append(_Stream(key, meta["actor"], meta.get("source", ""),
                                    np.asarray(ch.columns["device_time_ns"], dtype=np.float64),
                                    np.asarray(ch.columns["host_time_ns"], dtype=np.float64), ch.columns))  # fmt: skip
    suits.sort(key=lambda s: (s.source, int(s.cols["character"][0])))  # MVN character order
    return suits, trackers


def describe_mount(m, k: int) -> dict:
    """Tracker ``k`` of a MountCalibration, for people: rotation vector (deg), offset (mm), fit
    residuals and 1-sigma uncertainties."""
    from scipy.spatial.transform import Rotation

    if not m.calibrated[k]:
        return {"calibrated": False}
    return {"rotation_deg": np.round(np.degrees(Rotation.from_quat(m.rotations[k]).as_rotvec()), 3).tolist(),
            "translation_mm": np.round(m.translations[k] * 1000, 2).tolist(),
            "rotation_rms_deg": round(float(m.rotation_rms_deg[k]), 3), "translation_rms_mm": round(float(m.translation_rms_m[k]) * 1000, 2),
            "rotation_std_deg": round(float(m.rotation_std_deg[k]), 4), "translation_std_mm": round(float(m.translation_std_m[k]) * 1000, 3),
            "rejected_samples": int(m.outliers[:, k].sum())}  # fmt: skip


def carry_mounts(calibration: SyncResult, actor: str, serials, segments, source: str = ""):
    """The :class:`~dualhuman_builder.sync.mount_types.CarriedMounts` of ``actor``'s trackers
    (``serials``, ``segments`` in this take's order) from ``calibration``, a calibration take's
    :class:`SyncResult`: a tracker is carried when the same actor wore the same serial on the same
    segment there and it was calibrated; the suit's chain misalignments come with them."""
    from dualhuman_builder.sync.mount_types import CarriedMounts

    try:
        cal = calibration.actor(actor)
    except KeyError:
        cal = None
    if cal is None or cal.mounts is None:
        return CarriedMounts.empty(len(serials), source)
    return CarriedMounts.from_calibration(cal.mounts, list(zip(cal.serials, cal.segments)), list(zip(serials, segments)), source)


def _carried_lags(calibration: SyncResult) -> dict:
    """Tracker source -> :class:`~dualhuman_builder.sync.lag.LagEstimate` that ``calibration`` (a
    calibration take's :class:`SyncResult`) used for it (its report's ``lags``); sources it measured
    no lag for are left out."""
    from dualhuman_builder.sync.lag import LagEstimate

    out = {}
    for key, v in (calibration.report.get("lags") or {}).items():
        if not key.startswith("source:") or not isinstance(v, dict) or v.get("lag_ms") is None:
            continue
        lag = float(v["lag_ms"]) * 1e6
        std = float(v["std_ms"]) * 1e6 if v.get("std_ms") is not None else float("nan")
        if np.isfinite(lag):
            out[key[len("source:"):]] = LagEstimate(lag_ns=lag, std_ns=std, peak=float(v.get("peak", float("nan"))),
                                                    n_windows=0, n_estimates=1)  # fmt: skip
    return out


def _report_carried(report: dict, actor: str, serials, carried, mounts, source: str, say) -> None:
    """``report["mounts_from"]``: which of ``actor``'s trackers kept the calibration take's mount,
    and warnings for those that could not."""
    from dualhuman_builder.sync.mount_rotation import MOVED_DEG

    entry = report.setdefault("mounts_from", {"take": source})
    kept = [s for s, c in zip(serials, mounts.carried) if c]
    moved = [s for s, r in zip(serials, mounts.carry_rejected) if r]
    missing = [s for s, c in zip(serials, carried.carried) if not c]
    entry[actor] = {"carried": kept, "strapped_again": moved, "not_in_calibration": missing}
    for s in moved:
        report.setdefault("warnings", []).append(
            f"{actor}: tracker {s} turned against its segment since {source} (rotation residuals over "
            f"{MOVED_DEG:g} deg with its mount from there): strapped again? Its mount was solved on this take alone")
    if missing:
        report.setdefault("warnings", []).append(
            f"{actor}: trackers {missing} have no mount in {source} (another serial, segment or actor); solved on this take alone")
    say(f"{actor}: {len(kept)} of {len(serials)} tracker mounts carried over from {source}")


def _ms(x: float) -> float:
    """Seconds ``x`` as milliseconds rounded to 0.1 us, for the report."""
    return round(float(x) * 1e3, 4)


def synchronise(columns: dict, fps: float = 30.0, actors: list[str] | None = None, use_trackers: bool = True,
                progress: Callable[[str], None] | None = None, suit_chain: bool = True,
                mounts_from: SyncResult | None = None, mounts_from_take: str = "") -> SyncResult:  # fmt: skip
    """Put a take's suits and trackers on one timeline at ``fps`` (see the module docstring).

    ``columns``: :func:`read_columns` of the take. ``actors``: which actors, in order (default: the
    suits' order); every one needs a suit. ``use_trackers=False`` ignores trackers (to measure what
    fusion buys). ``suit_chain`` (default True): solve each suit segment's constant misalignment on
    the chains from the pelvis to the trackers with the mounts
    (:class:`~dualhuman_builder.sync.mount_types.SuitChain`, prior :data:`CHAIN_PRIOR_DEG`); False
    leaves the suit's limb errors to the mounts and the drift. ``mounts_from``: the
    :class:`SyncResult` of the studio day's calibration take (named ``mounts_from_take`` in
    the report) whose mounts carry over (:func:`carry_mounts`); the report's ``mounts_from`` says
    which trackers kept theirs, and warns of those found strapped again or missing there. Its
    tracker lags carry over too, averaged with this take's own
    (:func:`~dualhuman_builder.sync.lag.with_carried_lag`; the report's ``lags`` keep both)."""
    from dualhuman_builder.sync.clock import fit_clock
    from dualhuman_builder.sync.lag import angular_speed, combine_lags, estimate_lag, linear_speed, with_carried_lag
    from dualhuman_builder.sync.mount import calibrate_mounts
    from dualhuman_builder.sync.mount_types import SuitChain

    say = progress or (lambda _m: None)
    if not fps > 0:
        raise SyncError(f"fps must be positive, got {fps}")
    layout_notes: dict = {}
    suits, trackers = _streams(columns, layout_notes)
    if not suits:
        raise SyncError("the take has no suit stream (suits/mvn/<character>/SuitFrame)",
                        fix="record the suits, or bind actors to MVN characters with --actor NAME=SOURCE#CHARACTER")  # fmt: skip
    by_actor = {s.actor: s for s in suits}
    names = list(actors) if actors else [s.actor for s in suits]
    missing = [a for a in names if a not in by_actor]
    if missing:
        raise SyncError(f"actors {missing} have no suit stream in the take; suits are worn by {sorted(by_actor)}",
                        fix="check the rig's actor bindings (character numbers)")  # fmt: skip
    if not use_trackers:
        trackers = []
    trackers = [t for t in trackers if t.actor in names]

    # ---- clocks
    report: dict[str, Any] = {"reference": by_actor[names[0]].key, "clocks": {}, "lags": {}, "mounts": {}}
    if layout_notes:
        report["suit_segments"] = layout_notes
        for key, c in layout_notes.items():
            if c.get("segments_set_aside"):
                report.setdefault("warnings", []).append(
                    f"{key}: {c['samples_with_them']} samples carry segments beyond the body's 23 "
                    f"({', '.join(c['segments_set_aside'])}: props?); the body segments are used, those set aside")
            if c.get("samples_left_out"):
                report.setdefault("warnings", []).append(
                    f"{key}: {c['samples_left_out']} samples lack body segments (another segment count); left out")
    fits = {}
    for s in [*suits, *trackers]:
        try:
            fits[s.key] = fit_clock(s.device_ns, s.host_ns)
        except ValueError as e:
            raise SyncError(f"{s.key}: cannot fit its clock: {e}") from None
    ref = by_actor[names[0]]
    ref_fit = fits[ref.key]
    ref0 = float(ref.device_ns[0])

    def to_timeline(key: str, device_ns: np.ndarray) -> np.ndarray:
        if key == ref.key:
            return (np.asarray(device_ns, dtype=np.float64) - ref0) * 1e-9
        return (ref_fit.to_device(fits[key].to_host(device_ns)) - ref0) * 1e-9

    # the span every suit covers
    t_suit = {s.actor: to_timeline(s.key, s.device_ns) for s in suits if s.actor in names}
    start = max(t[0] for t in t_suit.values())
    end = min(t[-1] for t in t_suit.values())
    if end - start < 2.0 / fps:
        raise SyncError(f"the suits overlap for {max(end - start, 0):.3f} s only; nothing to fit")
    k0 = int(np.ceil(start * fps - 1e-9))
    times = np.arange(k0, int(np.floor(end * fps + 1e-9)) + 1) / fps
    say(f"timeline: {len(times)} frames at {fps:g} fps ({times[0]:.3f}-{times[-1]:.3f} s on {ref.key})")

    # ---- tracker lags against their segments, combined per source (one clock per source)
    t_trk = {t.key: to_timeline(t.key, t.device_ns) for t in trackers}
    lags_by_source: dict[str, list] = {}
    for t in trackers:
        s = by_actor[t.actor]
        seg = MVN_SEGMENTS.index(columns[t.key].metadata["segment"])
        pos = np.asarray(t.cols["position"], np.float64)
        valid = np.asarray(t.cols["valid"], bool)
        seen = valid & ~np.all(pos == 0.0, axis=1)  # a tracker that lost tracking reports the origin
        ns_suit = np.round(t_suit[s.actor] * 1e9).astype(np.int64)
        ns_trk = np.round(t_trk[t.key] * 1e9).astype(np.int64)
        # two measurements per tracker: angular speeds (mount-independent), and linear speeds for
        # segments that translate more than they turn (an actor standing still but patting)
        pairs = ((t.key, angular_speed, s.cols["orientations"][:, seg], t.cols["orientation"], valid, MIN_ANGULAR_MOTION),
                 (f"{t.key} (position)", linear_speed, s.cols["positions"][:, seg], pos, seen, MIN_LINEAR_MOTION))  # fmt: skip
        for name, speed, of_suit, of_tracker, ok, min_motion in pairs:
            try:
                est = estimate_lag(*speed(ns_suit, of_suit), *speed(ns_trk, of_tracker, ok), min_motion=min_motion)
            except ValueError as e:
                report["lags"][name] = {"error": str(e)}
                continue
            report["lags"][name] = {"lag_ms": _ms(est.lag_ns * 1e-9), "std_ms": _ms(est.std_ns * 1e-9),
                                    "peak": round(float(est.peak), 4)}  # fmt: skip
            lags_by_source.setdefault(t.source, []).append(est)
    lag_s = {}
    carried_lags = _carried_lags(mounts_from) if mounts_from is not None else {}
    for source in sorted({t.source for t in trackers}):
        ests = lags_by_source.get(source, [])
        own = combine_lags(ests) if ests else None
        entry: dict[str, Any] = {"trackers": len(ests)}
        comb = own
        if source in carried_lags:
            comb, changed = with_carried_lag(own, carried_lags[source])
            took = mounts_from_take or "the calibration take"
            c = carried_lags[source]
            entry.update({"own_lag_ms": _ms(own.lag_ns * 1e-9) if own else None,
                          "own_std_ms": _ms(own.std_ns * 1e-9) if own else None,
                          "carried_lag_ms": _ms(c.lag_ns * 1e-9),
                          "carried_std_ms": _ms(c.std_ns * 1e-9) if np.isfinite(c.std_ns) else None,
                          "carried_from": took, "latency_changed": changed})  # fmt: skip
            if changed:
                report.setdefault("warnings", []).append(
                    f"trackers of source {source!r} lag the suits by {own.lag_ns * 1e-6:.2f} ms here against "
                    f"{c.lag_ns * 1e-6:.2f} ms in {took}: the latency changed (a source restarted?); this take's own lag is used")
            own_txt = f"{own.lag_ns * 1e-6:.2f} ms here" if own else "none measured here"
            say(f"trackers of {source!r}: lag {comb.lag_ns * 1e-6:.2f} ms ({own_txt}, {c.lag_ns * 1e-6:.2f} ms in {took})")
        if comb is None:
            continue
        lag_s[source] = comb.lag_ns * 1e-9
        report["lags"][f"source:{source}"] = {"lag_ms": _ms(lag_s[source]), "std_ms": _ms(comb.std_ns * 1e-9), **entry}
    sources_without = {t.source for t in trackers} - set(lag_s)
    if sources_without:
        report.setdefault("warnings", []).extend(
            f"no tracker of source {s!r} moved enough to measure its lag; host-clock alignment only" for s in sorted(sources_without))

    # ---- clocks against the timeline (device time at timeline 0 and drift), after the lag
    for s in [*suits, *trackers]:
        group = s.key if s in suits else f"source:{s.source}"
        if group in report["clocks"]:
            continue
        d = np.array([s.device_ns[0], s.device_ns[-1]])
        tl = to_timeline(s.key, d) - lag_s.get(s.source, 0.0) * (s in trackers)
        rate = (d[1] - d[0]) * 1e-9 / (tl[1] - tl[0])  # device seconds per timeline second
        offset_s = d[0] * 1e-9 - rate * tl[0]  # device reading at timeline 0
        f = fits[s.key]
        report["clocks"][group] = {"offset_s": round(float(offset_s), 7), "drift_ppm": round((rate - 1.0) * 1e6, 3),
                                   "host_fit": f.as_dict(), "lag_correction_ms": _ms(lag_s.get(s.source, 0.0)) if s in trackers else 0.0}  # fmt: skip

    # ---- resample
    out = []
    for name in names:
        s = by_actor[name]
        rot, ok_r = resample_quat(t_suit[name], np.asarray(s.cols["orientations"]), times, max_gap_s=MAX_GAP_S)
        pos, ok_p = resample_linear(t_suit[name], np.asarray(s.cols["positions"]), times, max_gap_s=MAX_GAP_S)
        a = ActorStreams(name, rot, pos, ok_r & ok_p)
        mine = [t for t in trackers if t.actor == name]
        if mine:
            K = len(mine)
            a.serials = tuple(t.key.split("/")[-2] for t in mine)  # trackers/vive/<serial>/TrackerSample
            a.segments = tuple(columns[t.key].metadata["segment"] for t in mine)
            a.trk_rot = np.full((len(times), K, 4), np.nan)
            a.trk_pos = np.full((len(times), K, 3), np.nan)
            a.trk_valid = np.zeros((len(times), K), bool)
            for k, t in enumerate(mine):
                tt = t_trk[t.key] - lag_s.get(t.source, 0.0)
                valid = np.asarray(t.cols["valid"], bool)
                a.trk_rot[:, k], ok1 = resample_quat(tt, np.asarray(t.cols["orientation"]), times, valid, MAX_GAP_S)
                a.trk_pos[:, k], ok2 = resample_linear(tt, np.asarray(t.cols["position"]), times, valid, MAX_GAP_S)
                a.trk_valid[:, k] = ok1 & ok2
            seg_idx = [MVN_SEGMENTS.index(g) for g in a.segments]
            usable = a.trk_valid & a.suit_valid[:, None]
            chain = SuitChain.of(np.nan_to_num(a.suit_rot), np.nan_to_num(a.suit_pos), seg_idx, _PARENT_INDEX,
                                 prior_deg=CHAIN_PRIOR_DEG) if suit_chain else None  # fmt: skip
            carried = carry_mounts(mounts_from, name, a.serials, a.segments, mounts_from_take) if mounts_from else None
            try:
                a.mounts = calibrate_mounts(times, np.nan_to_num(a.suit_rot[:, seg_idx]), np.nan_to_num(a.suit_pos[:, seg_idx]),
                                            np.nan_to_num(a.trk_rot), np.nan_to_num(a.trk_pos), usable,
                                            drift_knot_spacing_s=MOUNT_DRIFT_KNOTS_S,
                                            sites=np.array([tracker_site(g) for g in a.segments]), chain=chain,
                                            carried=carried)  # fmt: skip
            except ValueError as e:
                report.setdefault("warnings", []).append(f"{name}: tracker mounts not calibrated ({e}); fitting without trackers")
                a.serials, a.segments, a.trk_rot, a.trk_pos, a.trk_valid = (), (), None, None, None
            else:
                report["mounts"][name] = {serial: describe_mount(a.mounts, k) for k, serial in enumerate(a.serials)}
                if len(a.mounts.chain_segments):
                    report.setdefault("suit_misalignment", {})[name] = {
                        MVN_SEGMENTS[g]: {"rotation_deg": np.round(np.degrees(e), 3).tolist(), "std_deg": round(float(sd), 3)}
                        for g, e, sd in zip(a.mounts.chain_segments, a.mounts.chain_misalignment_rad, a.mounts.chain_std_deg)}  # fmt: skip
                h_std = float(a.mounts.heading_std_deg)
                report.setdefault("heading", {})[name] = {"offset_deg": round(float(a.mounts.heading_offset_deg), 3),
                                                          "std_deg": round(h_std, 3) if np.isfinite(h_std) else None}
                # what the actor's root is known to: the trackers' shared offset (an actor who turns no
                # segment leaves it to the sites' prior, ~14 mm for six trackers at 2 cm)
                c_std = float(a.mounts.common_offset_std_m)
                report.setdefault("common_offset", {})[name] = {"std_mm": round(c_std * 1000, 2) if np.isfinite(c_std) else None}
                if carried is not None:
                    _report_carried(report, name, a.serials, carried, a.mounts, mounts_from_take or "the calibration take", say)
                if not h_std <= HEADING_WARN_DEG and not a.mounts.carried.any():
                    report.setdefault("warnings", []).append(
                        f"{name}: heading in the tracker world known to {h_std:.1f} deg (1-sigma) only: the actor hardly "
                        "turns, so it rests on where the trackers are strapped; record the studio day's calibration take (a bow, a "
                        "twist, a turn on the spot) and sync with --mounts-from it")
                if np.isfinite(c_std) and c_std * 1000 > COMMON_OFFSET_WARN_MM and not a.mounts.carried.any():
                    report.setdefault("warnings", []).append(
                        f"{name}: the trackers' shared offset on their segments known to {round(c_std * 1000, 2):.1f} mm (1-sigma) "
                        "only, and the body's root with it: the actor turns too few segments to tell it from the suit's "
                        "drift; record the studio day's calibration take and sync with --mounts-from it")
                say(f"{name}: {K} trackers calibrated on their segments")
        out.append(a)
    return SyncResult(float(fps), times, out, report)
