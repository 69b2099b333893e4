"""BVH (Biovision hierarchy) files -> a :class:`SkeletonTrack` of global joint orientations and
positions.

Reading of the format (Meredith & Maddock, "Motion Capture File Formats Explained", 2001):

* ``HIERARCHY`` holds ``ROOT name { OFFSET x y z  CHANNELS n ch...  JOINT ... }``, nested; a leaf
  may end in ``End Site { OFFSET x y z }``. Channels are ``Xposition Yposition Zposition Xrotation
  Yrotation Zrotation`` in any order and number (keywords and channel names in any case).
* ``MOTION``, ``Frames: N``, ``Frame Time: dt`` (seconds), then N lines of one value per channel,
  joints in hierarchy order, angles in degrees.
* A joint's local transform: translation = OFFSET plus its position channels (the root's position
  is offset + channels, as Meredith & Maddock state; other joints rarely have position channels);
  rotation = the rotation channels composed in the order listed: ``Zrotation Xrotation
  Yrotation`` is ``Rz @ Rx @ Ry`` (intrinsic Z-X-Y). Globals: ``G = G_parent @ L``,
  ``p = p_parent + G_parent t``. End Sites carry no data (kept in ``meta``).

Output: one segment per ROOT/JOINT in file order; orientations x y z w (rotation of the joint's
frame to the world, which is the file's rest frame); positions in metres. Units: ``scale`` (file
units -> metres) or, by default, detected from the rest-pose size of the skeleton (largest extent
of the joints and End Sites with every channel at 0, i.e. stature or arm span): up to 3 units:
metres; up to 300: centimetres; else millimetres. The choice and its reason go to
``meta["units"]`` / ``meta["scale_note"]``. BVH is usually Y-up, as our world; ``up="z"`` rotates
a Z-up file with :data:`~dualhuman_builder.conventions.ZUP_TO_YUP`. Times: frame ``k`` at
``k / fps`` on both clocks (a BVH file has one clock: ``fps`` = 1 / Frame Time, snapped to an
integer rate when within 1e-4 of one).

Counts are never trusted for allocation: ``Frames:`` and ``CHANNELS n`` must be whole numbers (ASCII
digits) and agree with the frame lines and channel names present before any array is made, and the
track's frames x joints poses may not exceed :data:`POSES_PER_BYTE` per byte of the file (joints
without channels cost memory without bytes). ``Frame Time`` must lie within :data:`FRAME_TIME_RANGE`
and the last frame's time fit int64 nanoseconds. The hierarchy is read without recursion, however
deep.

Values that are not finite (``nan``, ``inf``) are read, as in MVNX files: a joint whose rotation
channels are not all finite has no valid orientation in that frame, nor have its descendants; a
position that is not finite (its own channels, or a parent's orientation, or overflow) is invalid.
Invalid entries are NaN under a False validity mask, counted in ``meta`` (``invalid_orientations``,
``invalid_positions``, ``nonfinite_values``) and logged as a warning.

Bad files raise :class:`~dualhuman_builder.errors.FormatError` with the line number: missing or
extra braces, unknown keywords or channels, a CHANNELS count that disagrees with the names
listed, a motion line with the wrong number of values or a non-number, fewer or more frame lines
than ``Frames:`` declares, more poses than the file's size allows.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualhuman_builder.errors import FormatError
from dualhuman_builder.tracks import SkeletonTrack

log = logging.getLogger(__name__)

#: Most track poses (frames x joints) per byte of the file, beyond :data:`MIN_POSES`: a joint's values in a
#: frame take 6 bytes or more ("0 0 0 "), a pose about 60 bytes in the track.
POSES_PER_BYTE = 1
MIN_POSES = 10_000
#: Frame Time (seconds) accepted: 1 MHz to one frame per hour.
FRAME_TIME_RANGE = (1e-6, 3600.0)
#: Most digits of ``Frames:`` and of a ``CHANNELS`` count.
_MAX_DIGITS = 12

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNELS = {c.lower(): c for c in CHANNEL_NAMES}
HOST_TIME_NOTE = "host_time_ns copies device_time_ns: a BVH file has one clock (its Frame Time)"


@dataclass(frozen=True)
class BvhJoint:
    """A ROOT or JOINT: ``parent`` index (-1 for a root), ``offset (3,)`` and ``end_site (3,)``
    (or None) in file units, ``channels`` as named in :data:`CHANNEL_NAMES`, ``line`` where it starts."""

    name: str
    parent: int
    offset: np.ndarray
    channels: tuple[str, ...]
    line: int
    end_site: np.ndarray | None = None


@dataclass(eq=False)
class BvhFile:
    """A parsed BVH file: ``joints`` in file order, ``frame_time`` s, ``motion (F, C)`` channel values."""

    path: Path
    joints: tuple[BvhJoint, ...]
    frame_time: float
    motion: np.ndarray

    @property
    def num_channels(self) -> int:
        return sum(len(j.channels) for j in self.joints)


class _Joint:  # mutable while parsing
    def __init__(self, name, parent, line, index):
        self.name, self.parent, self.line, self.index = name, parent, line, index
        self.offset = None
        self.channels: tuple[str, ...] | None = None
        self.end_site = None


def _whole(text: str) -> int | None:
    """``text`` as a whole number when it is 1 to :data:`_MAX_DIGITS` ASCII digits, else None."""
    return int(text) if text.isascii() and text.isdigit() and len(text) <= _MAX_DIGITS else None


def _err(path: Path, line: int | None, message: str, fix: str | None = None) -> FormatError:
    where = f"line {line}: " if line is not None else ""
    return FormatError(where + message, path=path, fix=fix or "fix the file or re-export it")


def parse_bvh(path: str | Path) -> BvhFile:
    """Parse a BVH file's hierarchy and motion (no kinematics); see the module docstring."""
    path = Path(path)
    if not path.is_file():
        raise FormatError("no such file", path=path, fix="check the path")
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError as e:
        raise _err(path, None, f"not a text file ({e})") from None
    toks: list[tuple[str, int]] = []
    motion_line = None
    for ln, line in enumerate(lines, 1):
        parts = line.split()
        if parts and parts[0].upper() == "MOTION":
            motion_line = ln
            break
        toks.extend((t, ln) for t in parts)
    if not toks or toks[0][0].upper() != "HIERARCHY":
        raise _err(path, toks[0][1] if toks else 1, f"expected HIERARCHY, found {toks[0][0] if toks else 'nothing'!r}",
                   fix="pass a .bvh file")  # fmt: skip
    joints = _parse_hierarchy(path, toks, motion_line or len(lines))
    if motion_line is None:
        raise _err(path, len(lines), "no MOTION section after the HIERARCHY")
    frame_time, frames, data = _parse_motion_header(path, lines, motion_line)
    C = sum(len(j.channels) for j in joints)
    motion = _parse_motion(path, lines, data, frames, C, len(joints))
    return BvhFile(path, tuple(joints), frame_time, motion)


def _parse_hierarchy(path: Path, toks: list[tuple[str, int]], end_line: int) -> list[BvhJoint]:
    joints: list[_Joint] = []
    names: set[str] = set()
    stack: list[tuple[str, _Joint]] = []  # ("joint" | "end", joint)
    i, n = 1, len(toks)

    def same_line_after(k: int) -> list[str]:
        ln = toks[k][1]
        out = []
        k += 1
        while k < n and toks[k][1] == ln and toks[k][0] != "{":
            out.append(toks[k][0])
            k += 1
        return out

    def expect_open(k: int, what: str) -> None:
        if k >= n:
            raise _err(path, end_line, f"expected '{{' after {what}, found the end of the hierarchy")
        if toks[k][0] != "{":
            raise _err(path, toks[k][1], f"expected '{{' after {what}, found {toks[k][0]!r}")

    def close(joint: _Joint, ln: int) -> None:
        if joint.offset is None:
            raise _err(path, ln, f"joint {joint.name!r} (line {joint.line}) has no OFFSET")
        if joint.channels is None:
            joint.channels = ()

    while i < n:
        tok, ln = toks[i]
        up = tok.upper()
        if up in ("ROOT", "JOINT"):
            if up == "ROOT" and stack:
                raise _err(path, ln, f"ROOT inside joint {stack[-1][1].name!r}: a '}}' is missing before it")
            if up == "JOINT" and (not stack or stack[-1][0] == "end"):
                where = "outside any ROOT" if not stack else "inside an End Site"
                raise _err(path, ln, f"JOINT {' '.join(same_line_after(i))!r} {where}")
            name_parts = same_line_after(i)
            if not name_parts:
                raise _err(path, ln, f"{up} without a name")
            name = " ".join(name_parts)
            if name in names:
                raise _err(path, ln, f"a second joint named {name!r}")
            i += 1 + len(name_parts)
            expect_open(i, f"{up} {name}")
            joint = _Joint(name, stack[-1][1].index if stack else -1, ln, len(joints))
            joints.append(joint)
            names.add(name)
            stack.append(("joint", joint))
            i += 1
        elif up == "END":
            if i + 1 >= n or toks[i + 1][0].upper() != "SITE":
                raise _err(path, ln, "expected 'End Site'")
            if not stack or stack[-1][0] == "end":
                raise _err(path, ln, "End Site outside a joint")
            i += 2
            expect_open(i, "End Site")
            stack.append(("end", stack[-1][1]))
            i += 1
        elif up == "OFFSET":
            if not stack:
                raise _err(path, ln, "OFFSET outside a joint")
            vals = toks[i + 1 : i + 4]
            try:
                offset = np.array([float(v) for v, _ in vals])
            except ValueError:
                raise _err(path, ln, f"OFFSET needs 3 numbers, got {[v for v, _ in vals]}") from None
            if offset.size != 3 or any(l != ln for _, l in vals) or not np.isfinite(offset).all():
                raise _err(path, ln, f"OFFSET needs 3 numbers on its line, got {[v for v, l in vals if l == ln]}")
            kind, joint = stack[-1]
            if kind == "end":
                joint.end_site = offset
            elif joint.offset is not None:
                raise _err(path, ln, f"a second OFFSET for joint {joint.name!r}")
            else:
                joint.offset = offset
            i += 4
        elif up == "CHANNELS":
            if not stack or stack[-1][0] == "end":
                raise _err(path, ln, "CHANNELS outside a joint" if not stack else "CHANNELS in an End Site")
            joint = stack[-1][1]
            rest = same_line_after(i)
            count = _whole(rest[0]) if rest else None
            if count is None:
                raise _err(path, ln, f"CHANNELS needs a count (a whole number), got {[r[:20] for r in rest[:1]]}")
            listed = rest[1:]
            if len(listed) != count:
                raise _err(path, ln, f"CHANNELS declares {count} channels but lists {len(listed)}: {' '.join(listed)}")
            unknown = [c for c in listed if c.lower() not in _CHANNELS]
            if unknown:
                raise _err(path, ln, f"unknown channel {unknown[0]!r}; channels are {', '.join(CHANNEL_NAMES)}")
            if joint.channels is not None:
                raise _err(path, ln, f"a second CHANNELS for joint {joint.name!r}")
            joint.channels = tuple(_CHANNELS[c.lower()] for c in listed)
            positions = [c for c in joint.channels if c.endswith("position")]
            if len(set(positions)) != len(positions):
                raise _err(path, ln, f"a position channel is repeated: {' '.join(listed)}")
            i += 1 + len(rest)
        elif tok == "}":
            if not stack:
                raise _err(path, ln, "'}' without a matching '{'")
            kind, joint = stack.pop()
            if kind == "joint":
                close(joint, ln)
            elif joint.end_site is None:
                raise _err(path, ln, f"End Site of {joint.name!r} has no OFFSET")
            i += 1
        else:
            raise _err(path, ln, f"unexpected {tok!r}; expected OFFSET, CHANNELS, JOINT, End Site or '}}'")
    if stack:
        kind, joint = stack[-1]
        what = f"joint {joint.name!r} opened at line {joint.line}" if kind == "joint" else f"End Site of {joint.name!r}"
        raise _err(path, end_line, f"{len(stack)} block(s) not closed before MOTION: {what} has no matching '}}'")
    if not joints:
        raise _err(path, end_line, "no ROOT in the HIERARCHY")
    return [BvhJoint(j.name, j.parent, j.offset, j.channels, j.line, j.end_site) for j in joints]


def _parse_motion_header(path: Path, lines: list[str], motion_line: int) -> tuple[float, int, int]:
    """``(frame_time, frames, index of the first data line)``."""
    values = {}
    k = motion_line  # 0-based index of the line after MOTION
    for key in ("frames", "frame time"):
        while k < len(lines) and not lines[k].strip():
            k += 1
        if k >= len(lines):
            raise _err(path, len(lines), f"the file ends before '{key.title()}:'")
        label, sep, value = lines[k].partition(":")
        if not sep or label.strip().lower() != key:
            raise _err(path, k + 1, f"expected '{key.title()}: ...', found {lines[k].strip()[:60]!r}")
        values[key] = (value.strip(), k + 1)
        k += 1
    (frames_text, frames_ln), (ft_text, ft_ln) = values["frames"], values["frame time"]
    frames = _whole(frames_text)
    if frames is None:
        raise _err(path, frames_ln, f"Frames must be a whole number, got {frames_text[:40]!r}")
    try:
        frame_time = float(ft_text)
    except ValueError:
        frame_time = math.nan
    if not (math.isfinite(frame_time) and frame_time > 0):
        raise _err(path, ft_ln, f"Frame Time must be a positive number of seconds, got {ft_text[:40]!r}")
    low, high = FRAME_TIME_RANGE
    if not low <= frame_time <= high:
        raise _err(path, ft_ln, f"Frame Time {frame_time:g} s is not a plausible frame interval "
                                f"({low:g} to {high:g} s)")  # fmt: skip
    if frames * frame_time * 1e9 >= 2**63:
        raise _err(path, frames_ln, f"{frames} frames of {frame_time:g} s last beyond the int64 nanosecond range")
    return frame_time, frames, k


def _parse_motion(path: Path, lines: list[str], start: int, frames: int, C: int, J: int) -> np.ndarray:
    data = [(k + 1, line) for k, line in enumerate(lines[start:], start) if line.strip()]
    if len(data) < frames:
        end = data[-1][0] if data else start
        raise _err(path, end, f"Frames: declares {frames} frames but the file holds {len(data)} frame lines "
                              f"(truncated?)", fix="re-export the file, or correct Frames:")  # fmt: skip
    if len(data) > frames:
        raise _err(path, data[frames][0], f"more frame lines than the {frames} that Frames: declares",
                   fix="correct Frames: or remove the extra lines")  # fmt: skip
    if frames == 0:
        return np.zeros((0, C))
    texts = [line for _, line in data]
    if C:
        try:
            motion = np.loadtxt(texts, dtype=np.float64, comments=None, ndmin=2)
            if motion.shape == (frames, C):
                return motion
        except ValueError:
            pass
    motion = np.empty((frames, C))
    for f, (ln, line) in enumerate(data):
        parts = line.split()
        if len(parts) != C:
            raise _err(path, ln, f"frame {f} holds {len(parts)} values, expected {C} (the CHANNELS of {J} joints)")
        for j, p in enumerate(parts):
            try:
                motion[f, j] = float(p)
            except ValueError:
                raise _err(path, ln, f"frame {f}, value {j}: {p!r} is not a number") from None
    return motion


def _detect_scale(joints: tuple[BvhJoint, ...]) -> tuple[float, str, str]:
    """``(scale to metres, units, note)`` from the rest-pose extent of the skeleton."""
    rest = np.zeros((len(joints), 3))
    points = []
    with np.errstate(over="ignore", invalid="ignore"):  # huge offsets: an infinite extent, read as mm
        for i, j in enumerate(joints):
            rest[i] = j.offset + (rest[j.parent] if j.parent >= 0 else 0.0)
            points.append(rest[i])
            if j.end_site is not None:
                points.append(rest[i] + j.end_site)
        extent = float(np.ptp(np.array(points), axis=0).max())
    if extent == 0.0:
        return 0.01, "cm", "the rest pose has no extent; assumed centimetres (pass scale= to choose)"
    scale, units = (1.0, "m") if extent <= 3.0 else (0.01, "cm") if extent <= 300.0 else (0.001, "mm")
    return scale, units, (f"rest-pose extent {extent:.4g} file units: read as {units} "
                          f"(scale {scale:g} to metres; pass scale= to override)")  # fmt: skip


def read_bvh(path: str | Path, *, scale: float | None = None, up: str = "y") -> SkeletonTrack:
    """Read a BVH file as a :class:`SkeletonTrack` (see the module docstring): ``scale`` file units
    -> metres (default: detected), ``up`` the file's up axis (``"y"`` or ``"z"``)."""
    from scipy.spatial.transform import Rotation  # here: importing the MVNX reader stays light

    if up not in ("y", "z"):
        raise ValueError(f"up must be 'y' or 'z', got {up!r}")
    bvh = parse_bvh(path)
    path = bvh.path
    if scale is None:
        scale, units, note = _detect_scale(bvh.joints)
    else:
        if not (scale > 0 and math.isfinite(scale)):
            raise ValueError(f"scale must be a positive number, got {scale}")
        units, note = "given", f"scale {scale:g} to metres given by the caller"
    F, J = bvh.motion.shape[0], len(bvh.joints)
    size = path.stat().st_size
    if F * J > MIN_POSES + POSES_PER_BYTE * size:
        bare = sum(not j.channels for j in bvh.joints)
        raise _err(path, None, f"{J} joints x {F} frames = {F * J:,} poses from a {size:,}-byte file: more than "
                               f"{POSES_PER_BYTE} per byte ({bare} joints have no channels)",
                   fix="a BVH file holds a value per channel per frame; check where the file comes from, or "
                       "re-export it")  # fmt: skip
    quat = np.zeros((F, J, 4))
    pos = np.zeros((F, J, 3))
    ovalid = np.ones((F, J), dtype=bool)
    pvalid = np.ones((F, J), dtype=bool)
    glob: list = [None] * J
    col = 0
    for j, joint in enumerate(bvh.joints):
        t = np.tile(joint.offset, (F, 1))
        axes, cols = "", []
        for c, name in enumerate(joint.channels, start=col):
            if name.endswith("position"):
                t[:, "XYZ".index(name[0])] += bvh.motion[:, c]
            else:
                axes += name[0]
                cols.append(c)
        col += len(joint.channels)
        if F == 0:
            continue
        if len(axes) > 3:
            raise _err(path, joint.line, f"joint {joint.name!r} has {len(axes)} rotation channels; at most 3")
        # Non-finite values: identity / zero in the arithmetic, the frame marked invalid for the joint (and,
        # through its orientation, for its descendants).
        angles = bvh.motion[:, cols]
        rot_ok = np.isfinite(angles).all(axis=1)
        t_ok = np.isfinite(t).all(axis=1)
        t[~t_ok] = 0.0
        try:
            local = (Rotation.from_euler(axes, np.where(rot_ok[:, None], angles, 0.0), degrees=True) if axes
                     else Rotation.identity(F))  # fmt: skip
        except ValueError as e:
            raise _err(path, joint.line, f"rotation channels {axes} of joint {joint.name!r}: {e}") from None
        if joint.parent < 0:
            glob[j], pos[:, j] = local, t
            ovalid[:, j], pvalid[:, j] = rot_ok, t_ok
        else:
            p = joint.parent
            parent = glob[p]
            glob[j], pos[:, j] = parent * local, pos[:, p] + parent.apply(t)
            ovalid[:, j] = ovalid[:, p] & rot_ok
            pvalid[:, j] = pvalid[:, p] & ovalid[:, p] & t_ok
        quat[:, j] = glob[j].as_quat()
    with np.errstate(over="ignore", invalid="ignore"):  # huge offsets or values: not finite, marked invalid
        pos *= scale
        pvalid &= np.isfinite(pos).all(-1)
    if up == "z" and F:
        s = math.sqrt(0.5)
        zy = Rotation.from_quat([-s, 0.0, 0.0, s])  # ZUP_TO_YUP: -90 degrees about X
        quat = (zy * Rotation.from_quat(quat.reshape(-1, 4))).as_quat().reshape(F, J, 4)
        pos = np.stack([pos[..., 0], pos[..., 2], -pos[..., 1]], axis=-1)
    fps = 1.0 / bvh.frame_time
    if abs(fps - round(fps)) < 1e-4 * fps:
        fps = float(round(fps))
    t_ns = np.round(np.arange(F) * (1e9 / fps)).astype(np.int64)
    names = [j.name for j in bvh.joints]
    bad_values = int(np.count_nonzero(~np.isfinite(bvh.motion)))
    bad_o, bad_p = int(np.count_nonzero(~ovalid)), int(np.count_nonzero(~pvalid))
    if bad_o or bad_p:
        log.warning("%s: %d orientations and %d positions not finite marked invalid (NaN or infinite motion "
                    "values: %d)", path, bad_o, bad_p, bad_values)  # fmt: skip
    meta = {"source": "bvh", "file": path.name, "units": units, "scale": scale, "scale_note": note, "up": up,
            "frame_time_s": bvh.frame_time, "host_time": HOST_TIME_NOTE,
            "parents": [names[j.parent] if j.parent >= 0 else None for j in bvh.joints],
            "offsets_m": [(j.offset * scale).tolist() for j in bvh.joints],
            "channels": [list(j.channels) for j in bvh.joints],
            "end_sites_m": {j.name: (j.end_site * scale).tolist() for j in bvh.joints if j.end_site is not None},
            "invalid_orientations": bad_o, "invalid_positions": bad_p, "nonfinite_values": bad_values}  # fmt: skip
    try:
        return SkeletonTrack(segment_names=names, orientations=np.where(ovalid[..., None], quat, np.nan),
                             positions=np.where(pvalid[..., None], pos, np.nan), device_time_ns=t_ns,
                             host_time_ns=t_ns, orientation_valid=ovalid, position_valid=pvalid, fps=fps,
                             meta=meta)  # fmt: skip
    except ValueError as e:
        raise _err(path, None, f"inconsistent skeleton: {e}") from None
