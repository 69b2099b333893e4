"""Writers of recorded-file formats, for round-trip tests and benchmarks of the importers
(:mod:`dualhuman_builder.capture.importers`): MVNX (Xsens MVN's XML export) and BVH.

* :func:`write_mvnx` — a :class:`SkeletonTrack` (plus optional per-frame arrays and calibration
  poses) as MVNX, laid out as MVN exports it (element order included; the ``mvnx`` PyPI package
  reads elements by position). Conversions are the exact inverses of the reader's.
* :func:`write_bvh` — a track of global segment orientations and positions as BVH: local
  rotations relative to each segment's parent, bone offsets from one reference frame.
* :func:`mvnx_arrays_from_suit` — the per-frame arrays of a real MVNX export, computed from a
  simulated :class:`~dualhuman_builder.sim.suit.SuitStream` and its ground truth.
* :func:`upper_body_track` / :func:`upper_body_arrays` — what MVN reports in its upper-body
  configuration (no leg sensors): the legs in a fixed pose that follows the pelvis.
* :func:`write_actor_mvnx` — one actor of a scene as the MVNX file MVN would export of its suit, in
  the ``FullBody`` or an ``UpperBody`` configuration, with calibration poses.

Both writers are crash-safe (:func:`~dualhuman_builder.fileio.atomic_open`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence
from xml.sax.saxutils import escape, quoteattr

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.capture.importers.mvnx import (CALIBRATION_TYPES, FRAME_FIELD_ORDER, LEG_SEGMENTS,
                                                      MVNX_NAMESPACE, QUAT_FIELDS, VECTOR_FIELDS, quat_file_to_ours,
                                                      quat_ours_to_file, unmeasured_segments, vec_file_to_ours,
                                                      vec_ours_to_file)  # fmt: skip
from dualhuman_builder.fileio import atomic_open
from dualhuman_builder.tracks import SkeletonTrack

#: Label of the joint between each MVN segment and its parent, in MVN's naming (22 joints).
MVN_JOINT_LABELS = {
    "L5": "jL5S1", "L3": "jL4L3", "T12": "jL1T12", "T8": "jT9T8", "Neck": "jT1C7", "Head": "jC1Head",
    "RightShoulder": "jRightT4Shoulder", "RightUpperArm": "jRightShoulder", "RightForeArm": "jRightElbow",
    "RightHand": "jRightWrist", "LeftShoulder": "jLeftT4Shoulder", "LeftUpperArm": "jLeftShoulder",
    "LeftForeArm": "jLeftElbow", "LeftHand": "jLeftWrist", "RightUpperLeg": "jRightHip",
    "RightLowerLeg": "jRightKnee", "RightFoot": "jRightAnkle", "RightToe": "jRightBallFoot",
    "LeftUpperLeg": "jLeftHip", "LeftLowerLeg": "jLeftKnee", "LeftFoot": "jLeftAnkle", "LeftToe": "jLeftBallFoot",
}  # fmt: skip

#: Foot contact points, in the order of MVNX ``footContacts``.
FOOT_CONTACTS = ("LeftFoot_Heel", "LeftFoot_Toe", "RightFoot_Heel", "RightFoot_Toe")

#: The sensors of MVN's upper-body configuration: the full suit's without the six on the legs.
UPPER_BODY_SENSORS = ("Pelvis", "T8", "Head", "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
                      "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand")  # fmt: skip

#: Ergonomic joint angles (labels in MVN's style: reference_segment).
ERGONOMIC_JOINTS = ("T8_Head", "T8_LeftUpperArm", "T8_RightUpperArm", "Pelvis_T8", "Vertical_Pelvis", "Vertical_T8")


def _parents_of(track: SkeletonTrack, parents: Mapping[str, str | None] | None) -> dict[str, str | None] | None:
    """Parent of each segment of ``track`` (``None`` for roots), or ``None`` when unknown."""
    if parents is None:
        if not set(track.segment_names) <= set(MVN_PARENTS):
            return None
        parents = MVN_PARENTS
    out = {}
    for s in track.segment_names:
        p = parents.get(s)
        out[s] = p if p in track.segment_names else None
    return out


def _offsets(track: SkeletonTrack, parents: dict[str, str | None], frame: int) -> dict[str, np.ndarray]:
    """Each non-root segment's origin in its parent's frame at ``frame`` (metres)."""
    rot = Rotation.from_quat(track.orientations[frame])
    out = {}
    for s, p in parents.items():
        if p is not None:
            i, j = track.segment_index(s), track.segment_index(p)
            out[s] = rot[j].apply(track.positions[frame, i] - track.positions[frame, j], inverse=True)
    return out


def _order(names: Sequence[str], parents: dict[str, str | None]) -> list[str]:
    """Segments with every parent before its children (depth first, in track order)."""
    children: dict[str | None, list[str]] = {}
    for s in names:
        children.setdefault(parents[s], []).append(s)
    out, stack = [], list(reversed(children.get(None, [])))
    while stack:
        s = stack.pop()
        out.append(s)
        stack.extend(reversed(children.get(s, [])))
    if len(out) != len(names):
        raise ValueError(f"parents form a cycle among {sorted(set(names) - set(out))}")
    return out


# --------------------------------------------------------------------------------------------- MVNX
def identity_pose(track: SkeletonTrack, parents: Mapping[str, str | None] | None = None,
                  frame: int = 0) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """MVN's ``identity`` calibration pose of ``track``'s skeleton: every segment at identity
    orientation in the file's (Z-up) world, the bones of ``frame`` chained from the root's
    position there. Returns ``orientations (S, 4)`` and ``positions (S, 3)`` in our Y-up world."""
    S = len(track.segment_names)
    quat = np.tile(quat_file_to_ours(np.array([1.0, 0.0, 0.0, 0.0])), (S, 1))
    par = _parents_of(track, parents)
    if par is None:
        return quat, np.array(track.positions[frame])
    offsets = _offsets(track, par, frame)
    pos_z = {}
    for s in _order(track.segment_names, par):
        p = par[s]
        root = vec_ours_to_file(track.positions[frame, track.segment_index(s)])
        pos_z[s] = root if p is None else pos_z[p] + offsets[s]
    return quat, vec_file_to_ours(np.stack([pos_z[s] for s in track.segment_names]))


def _file_values(name: str, a: np.ndarray) -> np.ndarray:
    """Our per-frame array ``(n, ...)`` -> the file's values ``(n, width)``."""
    n = a.shape[0]
    if name in QUAT_FIELDS:
        a = quat_ours_to_file(a)
    elif name in VECTOR_FIELDS:
        a = vec_ours_to_file(a.reshape(n, -1, 3))
    return np.asarray(a, dtype=np.float64).reshape(n, -1)


def _timecode(t_s: float, fps: float) -> str:
    whole = int(math.floor(t_s + 1e-9))
    ff = int(round((t_s - whole) * fps)) if fps > 0 else 0
    return f"{whole // 3600:02d}:{whole // 60 % 60:02d}:{whole % 60:02d}:{ff:02d}"


def write_mvnx(path: str | Path, track: SkeletonTrack, *, arrays: Mapping[str, np.ndarray] | None = None,
               calibration: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
               parents: Mapping[str, str | None] | None = None, sensors: Sequence[str] | None = None,
               ergonomic_joints: Sequence[str] = (), foot_contacts: Sequence[str] = FOOT_CONTACTS,
               subject: Mapping[str, str] | None = None, start_epoch_ms: int = 0, float_format: str = "%.9g",
               namespace: bool = True, block: int = 1024) -> Path:  # fmt: skip
    """Write ``track`` as an MVNX file; returns ``path``.

    * ``arrays``: other per-frame elements (``velocity``, ``sensorOrientation``, ``jointAngle``,
      ...) in our conventions and the shapes :func:`~dualhuman_builder.capture.importers.mvnx.read_mvnx`
      returns (``(T, N, k)`` or ``(T, n)``); converted back to MVNX's Z-up / w x y z.
    * ``calibration``: frame type -> ``(orientations (S, 4), positions (S, 3))`` in our frame,
      written before the normal frames; default: the ``identity`` pose of :func:`identity_pose`.
    * ``parents``: segment -> parent for the joints and points (default :data:`MVN_PARENTS` when
      the track holds MVN segments); bone offsets (``pos_b`` of the joint points) from frame 0.
    * ``sensors``: sensor labels (default: the 17 MVN sensor segments for an MVN track).
    * Frame ``time`` is ``device_time_ns`` in whole ms (as MVN writes it), ``ms`` is
      ``start_epoch_ms + time``, ``tc`` the time code at ``track.fps``.
    * ``float_format``: ``%.9g`` keeps every value to float32 precision (9 significant digits);
      MVN itself writes ``%f``-like 6 decimals.
    """
    from dualhuman_builder.sim.suit import MVN_SENSOR_SEGMENTS

    arrays = dict(arrays or {})
    T, S = track.num_frames, len(track.segment_names)
    for name, a in arrays.items():
        if name in ("orientation", "position"):
            raise ValueError(f"arrays[{name!r}] comes from the track; do not pass it")
        if np.shape(a)[0] != T:
            raise ValueError(f"arrays[{name!r}] has {np.shape(a)[0]} frames, the track {T}")
    par = _parents_of(track, parents)
    if sensors is None:
        sensors = MVN_SENSOR_SEGMENTS if set(track.segment_names) == set(MVN_SEGMENTS) else ()
    if calibration is None:
        calibration = {"identity": identity_pose(track, parents)}
    ms = np.round(track.device_time_ns / 1e6).astype(np.int64)
    fields = [f for f in FRAME_FIELD_ORDER if f in arrays or f in ("orientation", "position")]
    fields += [f for f in arrays if f not in fields]
    attrs = {"label": track.actor or "subject", "torsoColor": "#ea6852", "frameRate": f"{track.fps:g}",
             "segmentCount": str(S), "recDate": "", "originalFilename": Path(path).with_suffix(".mvn").name,
             "configuration": "FullBody", "userScenario": "noLevel", "processingQuality": "HD"}  # fmt: skip
    attrs.update(subject or {})
    offsets = _offsets(track, par, 0) if par is not None and T else {}
    joints = [(MVN_JOINT_LABELS.get(s, f"j{p}{s}"), p, s) for s, p in (par or {}).items() if p is not None]

    def fmt(vals) -> str:
        return " ".join(float_format % v for v in vals)

    with atomic_open(path, "w", encoding="utf-8", newline="\n") as f:
        ns = f' xmlns="{MVNX_NAMESPACE}" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"' if namespace else ""
        f.write(f'<?xml version="1.0" encoding="UTF-8" standalone="no" ?>\n<mvnx version="4"{ns}>\n')
        f.write('<mvn version="2023.0.0" build="dualhuman-builder sim.files"/>\n<comment></comment>\n')
        f.write("<subject " + " ".join(f"{k}={quoteattr(str(v))}" for k, v in attrs.items()) + ">\n<comment></comment>\n")
        f.write("<segments>\n")
        for i, s in enumerate(track.segment_names):
            f.write(f"<segment label={quoteattr(s)} id=\"{i + 1}\">\n<points>\n")
            p = (par or {}).get(s)
            own = MVN_JOINT_LABELS.get(s, f"j{p}{s}") if p else ("pHipOrigin" if s == "Pelvis" else f"p{s}Origin")
            pts = [(own, np.zeros(3))]
            pts += [(label, offsets[c]) for label, p, c in joints if p == s]
            for label, pos in pts:
                f.write(f"<point label={quoteattr(label)}>\n<pos_b>{fmt(pos)}</pos_b>\n</point>\n")
            f.write("</points>\n</segment>\n")
        f.write("</segments>\n<sensors>\n")
        f.writelines(f"<sensor label={quoteattr(s)}/>\n" for s in sensors)
        f.write("</sensors>\n<joints>\n")
        for label, p, c in joints:
            f.write(f"<joint label={quoteattr(label)}>\n<connector1>{escape(p)}/{escape(label)}</connector1>\n"
                    f"<connector2>{escape(c)}/{escape(label)}</connector2>\n</joint>\n")  # fmt: skip
        f.write("</joints>\n<ergonomicJointAngles>\n")
        for e in ergonomic_joints:
            ref, _, seg = e.partition("_")
            f.write(f"<ergonomicJointAngle label={quoteattr(e)} parentSegment={quoteattr(ref)} "
                    f"childSegment={quoteattr(seg)}/>\n")  # fmt: skip
        f.write("</ergonomicJointAngles>\n<footContactDefinition>\n")
        f.writelines(f'<contactDefinition index="{i}" label={quoteattr(c)}/>\n' for i, c in enumerate(foot_contacts))
        f.write("</footContactDefinition>\n")
        f.write(f'<frames segmentCount="{S}" sensorCount="{len(sensors)}" jointCount="{len(joints)}">\n')
        for ftype in sorted(calibration, key=lambda t: (CALIBRATION_TYPES + (t,)).index(t)):
            q, p = calibration[ftype]
            f.write(f'<frame time="0" index="" tc="" ms="" type={quoteattr(ftype)}>\n'
                    f"<orientation>{fmt(quat_ours_to_file(q).ravel())}</orientation>\n"
                    f"<position>{fmt(vec_ours_to_file(p).ravel())}</position>\n</frame>\n")  # fmt: skip
        formats = {}
        for k0 in range(0, T, block):
            k1 = min(T, k0 + block)
            data = {"orientation": _file_values("orientation", track.orientations[k0:k1]),
                    "position": _file_values("position", track.positions[k0:k1])}  # fmt: skip
            data.update({n: _file_values(n, np.asarray(arrays[n][k0:k1])) for n in fields if n in arrays})
            rows = {n: d.tolist() for n, d in data.items()}
            for n, d in data.items():
                formats.setdefault(n, " ".join([float_format] * d.shape[1]))
            out = []
            for i in range(k1 - k0):
                k = k0 + i
                t = int(ms[k])
                out.append(f'<frame time="{t}" index="{k}" tc="{_timecode(t / 1000.0, track.fps)}" '
                           f'ms="{start_epoch_ms + t}" type="normal">')  # fmt: skip
                out.extend(f"<{n}>{formats[n] % tuple(rows[n][i])}</{n}>" for n in fields)
                out.append("</frame>")
            f.write("\n".join(out))
            f.write("\n")
        f.write('</frames>\n</subject>\n<securityCode code=""/>\n</mvnx>\n')
    return Path(path)


def mvnx_arrays_from_suit(stream) -> dict[str, np.ndarray]:
    """The per-frame arrays of a real MVNX export for a simulated suit ``stream``
    (:class:`~dualhuman_builder.sim.suit.SuitStream`), in our conventions and the reader's shapes.

    From the stream's ground truth (MVN's engine estimates these; the truth stands in for them):
    ``velocity``, ``acceleration``, ``angularVelocity``, ``angularAcceleration`` ``(T, 23, 3)``
    (world); ``sensorFreeAcceleration`` ``(T, 17, 3)`` (world acceleration of the sensor's segment),
    ``sensorOrientation (T, 17, 4)`` (segment orientation times the sensor mount),
    ``sensorMagneticField (T, 17, 3)`` (the simulated magnetometer); ``jointAngle`` and
    ``jointAngleXZY (T, 22, 3)`` degrees (child relative to parent, Euler ZXY and XZY);
    ``jointAngleErgo (T, 6, 3)`` degrees; ``footContacts (T, 4)`` (1 where the foot / toe segment origin
    is within 10 cm of the floor); ``centerOfMass (T, 9)`` (position, velocity, acceleration of the segment
    mean, world).
    """
    from dualhuman_builder.sim.suit import MVN_SENSOR_SEGMENTS

    truth = stream.truth
    T = len(stream)
    sidx = [MVN_SEGMENTS.index(s) for s in MVN_SENSOR_SEGMENTS]
    sensor_q = (Rotation.from_quat(stream.orientations[:, sidx].reshape(-1, 4))
                * Rotation.from_quat(np.tile(stream.sensor_mount, (T, 1)))).as_quat().reshape(T, -1, 4)  # fmt: skip
    quat = stream.orientations
    angles, angles_xzy = _joint_angles(quat)
    ergo_pairs = [("T8", "Head"), ("T8", "LeftUpperArm"), ("T8", "RightUpperArm"), ("Pelvis", "T8")]
    ergo = [(Rotation.from_quat(quat[:, MVN_SEGMENTS.index(a)]).inv()
             * Rotation.from_quat(quat[:, MVN_SEGMENTS.index(b)])).as_euler("ZXY", degrees=True) for a, b in ergo_pairs]  # fmt: skip
    for seg in ("Pelvis", "T8"):
        ergo.append(Rotation.from_quat(quat[:, MVN_SEGMENTS.index(seg)]).as_euler("ZXY", degrees=True))
    feet = [MVN_SEGMENTS.index(s) for s in ("LeftFoot", "LeftToe", "RightFoot", "RightToe")]
    foot = stream.positions[:, feet, 1] < 0.10
    com = np.concatenate([stream.positions.mean(1), truth.velocity.mean(1), truth.acceleration.mean(1)], axis=1)
    return {
        "velocity": np.asarray(truth.velocity), "acceleration": np.asarray(truth.acceleration),
        "angularVelocity": np.asarray(truth.angular_velocity_world),
        "angularAcceleration": np.asarray(truth.angular_acceleration_world),
        "footContacts": foot.astype(np.float64),
        "sensorFreeAcceleration": np.asarray(truth.acceleration[:, sidx]),
        "sensorMagneticField": np.asarray(stream.sensor_mag),
        "sensorOrientation": sensor_q,
        "jointAngle": angles, "jointAngleXZY": angles_xzy,
        "jointAngleErgo": np.stack(ergo, 1), "centerOfMass": com,
    }  # fmt: skip


def _joint_angles(quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``jointAngle`` and ``jointAngleXZY`` ``(T, 22, 3)`` degrees of MVN-ordered orientations ``quat (T, 23, 4)``:
    each segment relative to its parent, Euler ZXY and XZY."""
    angles, angles_xzy = [], []
    for c, name in enumerate(MVN_SEGMENTS[1:], start=1):
        p = MVN_SEGMENTS.index(MVN_PARENTS[name])
        local = Rotation.from_quat(quat[:, p]).inv() * Rotation.from_quat(quat[:, c])
        angles.append(local.as_euler("ZXY", degrees=True))
        angles_xzy.append(local.as_euler("XZY", degrees=True))
    return np.stack(angles, 1), np.stack(angles_xzy, 1)


def _pelvis_heading(quat: np.ndarray) -> Rotation:
    """``(T,)`` rotations about the vertical (+Y) by the pelvis's change of heading since the first frame
    (the twist about Y of its rotation since then); ``quat (T, 4)`` the pelvis's orientations."""
    d = (Rotation.from_quat(quat) * Rotation.from_quat(quat[0]).inv()).as_quat()
    yaw = 2.0 * np.arctan2(d[:, 1], d[:, 3])
    return Rotation.from_rotvec(np.outer(yaw, [0.0, 1.0, 0.0]))


def upper_body_track(track: SkeletonTrack) -> SkeletonTrack:
    """What MVN reports of ``track`` (the 23 MVN segments) in its upper-body configuration, where no sensor
    is on the legs: the pelvis and everything above it as in ``track``; each leg segment
    (:data:`~dualhuman_builder.capture.importers.mvnx.LEG_SEGMENTS`) held in its first frame's pose relative
    to the pelvis, carried along with the pelvis's position and heading (it turns about the vertical with
    the pelvis, never bends). A standing actor's legs then look right and any step or knee bend is lost."""
    if tuple(track.segment_names) != tuple(MVN_SEGMENTS):
        raise ValueError("upper_body_track needs the 23 MVN segments in MVN order")
    quat, pos = np.array(track.orientations, dtype=np.float64), np.array(track.positions, dtype=np.float64)
    heading = _pelvis_heading(quat[:, 0])
    for g in LEG_SEGMENTS:
        i = MVN_SEGMENTS.index(g)
        quat[:, i] = (heading * Rotation.from_quat(np.tile(quat[0, i], (len(quat), 1)))).as_quat()
        pos[:, i] = pos[:, 0] + heading.apply(pos[0, i] - pos[0, 0])
    meta = {**track.meta, "configuration": "UpperBody"}
    return SkeletonTrack(track.segment_names, quat, pos, track.device_time_ns, track.host_time_ns, actor=track.actor,
                         fps=track.fps, orientation_valid=track.orientation_valid, position_valid=track.position_valid,
                         meta=meta)  # fmt: skip


def upper_body_arrays(arrays: Mapping[str, np.ndarray], track: SkeletonTrack) -> dict[str, np.ndarray]:
    """The per-frame arrays of :func:`mvnx_arrays_from_suit` as MVN writes them in the upper-body
    configuration of ``track`` (:func:`upper_body_track`'s): sensor arrays of the upper-body sensors only
    (:data:`UPPER_BODY_SENSORS`), the legs' velocities and accelerations the pelvis's (they move with
    it), joint angles of the track's own orientations, no ``footContacts`` (no foot is measured)."""
    from dualhuman_builder.sim.suit import MVN_SENSOR_SEGMENTS

    out = {k: np.array(v) for k, v in arrays.items() if k != "footContacts"}
    keep = [MVN_SENSOR_SEGMENTS.index(s) for s in UPPER_BODY_SENSORS]
    for name in ("sensorFreeAcceleration", "sensorMagneticField", "sensorOrientation"):
        if name in out:
            out[name] = out[name][:, keep]
    legs = [MVN_SEGMENTS.index(g) for g in LEG_SEGMENTS]
    for name in ("velocity", "acceleration", "angularVelocity", "angularAcceleration"):
        if name in out:
            out[name][:, legs] = out[name][:, :1]
    if "jointAngle" in out or "jointAngleXZY" in out:
        out["jointAngle"], out["jointAngleXZY"] = _joint_angles(np.asarray(track.orientations))
    return out


def write_actor_mvnx(path: str | Path, body, *, configuration: str = "FullBody", rate_hz: float = 60.0, seed: int = 0,
                     character: int = 0, label: str | None = None, start_epoch_ms: int = 1_700_000_000_000):  # fmt: skip
    """Write the MVNX file MVN would export of one actor's suit; returns ``(path, suit, track)``: the
    :class:`~dualhuman_builder.sim.suit.SuitStream` simulated from ``body`` and the
    :class:`SkeletonTrack` written (its times from 0, as an export's).

    ``body``: the actor's ground truth, a :class:`~dualhuman_builder.tracks.BodyTrack` (e.g.
    ``scene.sequence.actors[i]``) or its MVN :class:`SkeletonTrack`; the suit is simulated at ``rate_hz``
    with ``seed`` and ``character`` (:func:`~dualhuman_builder.sim.suit.simulate_suit`).
    ``configuration``: MVN's suit configuration (the subject's ``configuration`` attribute); ``FullBody``
    writes every segment and the 17 sensors as measured, an upper-body one (``UpperBody``,
    ``UpperBodyNoHands``...) the legs in MVN's fixed pose (:func:`upper_body_track`) and the sensors and
    arrays of that configuration (:func:`upper_body_arrays`). Calibration poses: ``identity``
    (:func:`identity_pose`) and ``tpose`` (the first frame's pose, standing in for the calibration)."""
    from dualhuman_builder.sim.groundtruth import segment_kinematics
    from dualhuman_builder.sim.kinematics import KinematicSpline
    from dualhuman_builder.sim.suit import MVN_SENSOR_SEGMENTS, simulate_suit

    unmeasured = unmeasured_segments(configuration)
    if unmeasured is None:
        raise ValueError(f"unknown MVN configuration {configuration!r}")
    upper = bool(unmeasured) and set(LEG_SEGMENTS) <= set(unmeasured)
    if unmeasured and not upper:
        raise ValueError(f"write_actor_mvnx writes FullBody and UpperBody configurations, not {configuration!r}")
    skeleton = body if isinstance(body, SkeletonTrack) else segment_kinematics(body)
    suit = simulate_suit(KinematicSpline(skeleton), character=character, rate_hz=rate_hz, seed=seed)
    reported = suit.to_track()
    t = np.asarray(reported.device_time_ns) - int(reported.device_time_ns[0])
    track = SkeletonTrack(reported.segment_names, reported.orientations, reported.positions, t, t,
                          actor=label or body.actor or "subject", fps=rate_hz, meta=dict(reported.meta))  # fmt: skip
    arrays = mvnx_arrays_from_suit(suit)
    sensors, contacts = MVN_SENSOR_SEGMENTS, FOOT_CONTACTS
    if upper:
        track = upper_body_track(track)
        arrays = upper_body_arrays(arrays, track)
        sensors = tuple(s for s in UPPER_BODY_SENSORS if not (s in unmeasured))
        if len(sensors) != len(UPPER_BODY_SENSORS):  # no hand sensors: their arrays go with them
            keep = [UPPER_BODY_SENSORS.index(s) for s in sensors]
            for name in ("sensorFreeAcceleration", "sensorMagneticField", "sensorOrientation"):
                arrays[name] = arrays[name][:, keep]
        contacts = ()
    calibration = {"identity": identity_pose(track), "tpose": (track.orientations[0], track.positions[0])}
    write_mvnx(path, track, arrays=arrays, calibration=calibration, sensors=sensors, ergonomic_joints=ERGONOMIC_JOINTS,
               foot_contacts=contacts, subject={"label": track.actor, "configuration": configuration},
               start_epoch_ms=start_epoch_ms)  # fmt: skip
    return Path(path), suit, track


# --------------------------------------------------------------------------------------------- BVH
_AXES = "XYZ"


def write_bvh(path: str | Path, track: SkeletonTrack, *, parents: Mapping[str, str | None] | None = None,
              units_per_metre: float = 100.0, order: str = "ZXY", positions: str = "root",
              reference_frame: int = 0, end_sites: Mapping[str, Sequence[float]] | None = None,
              float_format: str = "%.6f") -> Path:  # fmt: skip
    """Write ``track`` (global segment orientations and positions, Y-up metres) as BVH.

    * ``parents``: segment -> parent (default :data:`MVN_PARENTS` for MVN segments); a segment's
      BVH rotation is its orientation relative to its parent's (the root's is global), as Euler
      angles in degrees, intrinsic ``order`` (``"ZXY"`` writes ``Zrotation Xrotation Yrotation``).
    * Bone ``OFFSET``: the segment's origin in its parent's frame at ``reference_frame``, in file
      units (``units_per_metre``: 100 writes centimetres). The rest pose of the file is every
      segment frame aligned with the file's axes. The root's OFFSET is 0 and its position is in
      its position channels.
    * ``positions="all"`` adds position channels to every joint (value = translation - OFFSET),
      so bones whose length changes over the track still come back exactly.
    * ``end_sites``: leaf segment -> End Site offset (file units); default half the leaf's own
      bone, continued (a stub for viewers; it carries no data).
    """
    if positions not in ("root", "all"):
        raise ValueError(f"positions must be 'root' or 'all', got {positions!r}")
    if sorted(order.upper()) != ["X", "Y", "Z"]:
        raise ValueError(f"order must be a permutation of XYZ, got {order!r}")
    order = order.upper()
    par = _parents_of(track, parents)
    if par is None:
        raise ValueError("the track's segments are not MVN segments; pass parents={segment: parent}")
    if not (track.orientation_valid.all() and track.position_valid.all()):
        raise ValueError("BVH cannot mark samples invalid; fill or cut the invalid samples first")
    T = track.num_frames
    fps = track.fps
    if not fps > 0:
        if T < 2:
            raise ValueError("track.fps is 0 and there are too few frames to derive a frame time")
        fps = 1e9 / float(np.median(np.diff(track.device_time_ns)))
    names = _order(list(track.segment_names), par)
    offsets = _offsets(track, par, reference_frame) if T else {s: np.zeros(3) for s in names}
    scale = float(units_per_metre)
    children = {s: [c for c in names if par[c] == s] for s in names}
    glob = {s: Rotation.from_quat(track.orientations[:, track.segment_index(s)]) for s in names}
    columns, lines = [], ["HIERARCHY"]
    rot_channels = " ".join(f"{a}rotation" for a in order)

    def emit(s: str, depth: int) -> None:
        pad = "\t" * depth
        p = par[s]
        lines.append(f"{pad}{'ROOT' if p is None else 'JOINT'} {s}")
        lines.append(f"{pad}{{")
        off = np.zeros(3) if p is None else offsets[s] * scale
        lines.append(f"{pad}\tOFFSET {' '.join(float_format % v for v in off)}")
        i = track.segment_index(s)
        if p is None or positions == "all":
            lines.append(f"{pad}\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}")
            if p is None:
                columns.append(track.positions[:, i] * scale)
            else:
                j = track.segment_index(p)
                local_t = glob[p].apply(track.positions[:, i] - track.positions[:, j], inverse=True) * scale
                columns.append(local_t - off)
        else:
            lines.append(f"{pad}\tCHANNELS 3 {rot_channels}")
        local = glob[s] if p is None else glob[p].inv() * glob[s]
        columns.append(local.as_euler(order, degrees=True) if T else np.zeros((0, 3)))
        for c in children[s]:
            emit(c, depth + 1)
        if not children[s]:
            site = (end_sites or {}).get(s)
            if site is None:
                site = 0.5 * offsets.get(s, np.zeros(3)) * scale
            lines.append(f"{pad}\tEnd Site")
            lines.append(f"{pad}\t{{")
            lines.append(f"{pad}\t\tOFFSET {' '.join(float_format % v for v in np.asarray(site, float))}")
            lines.append(f"{pad}\t}}")
        lines.append(f"{pad}}}")

    for root in (s for s in names if par[s] is None):
        emit(root, 0)
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / fps:.10f}"]
    motion = np.concatenate(columns, axis=1) if columns else np.zeros((T, 0))
    with atomic_open(path, "w", encoding="ascii", newline="\n") as f:
        f.write("\n".join(lines) + "\n")
        if T:
            np.savetxt(f, motion, fmt=float_format, delimiter=" ")
    return Path(path)
