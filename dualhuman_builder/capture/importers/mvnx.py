"""Xsens MVNX files (MVN's XML export), read streaming.

Layout (schema of ``http://www.xsens.com/mvn/mvnx``; files without the namespace read the same)::

    mvnx(version) > mvn(version, build), comment, subject(label, frameRate, segmentCount, recDate, ...),
                    securityCode(code)
    subject > comment, segments > segment(label, id) > points > point(label) > pos_b,
              sensors > sensor(label), joints > joint(label) > connector1, connector2,
              ergonomicJointAngles > ergonomicJointAngle(label), footContactDefinition >
              contactDefinition(label), frames(segmentCount, sensorCount, jointCount) > frame*
    frame(time, index, tc, ms, type) > orientation, position, velocity, ... (space-separated floats)

Frames of type ``identity``, ``tpose`` and ``tpose-isb`` are calibration poses (kept apart, one
each); ``normal`` frames (or frames without a type) make the take.

Conversions (our conventions: Y-up world, metres, quaternions x y z w, int64 ns):

* MVNX's world is Z-up (as MVN's network stream). World vectors (``position``, ``velocity``,
  ``acceleration``, ``angularVelocity``, ``angularAcceleration``, ``sensorFreeAcceleration``,
  ``centerOfMass``) go through ``(x, y, z) -> (x, z, -y)``; world orientations (``orientation``,
  ``sensorOrientation``, file order w x y z) are left-multiplied by that rotation and reordered
  to x y z w. This is :data:`dualhuman_builder.conventions.ZUP_TO_YUP`, written out here so that
  importing a file does not import torch (which ``conventions`` does); a test checks both agree.
  Segment frames are not changed, so ``pos_b`` points stay in their segment's frame.
* ``sensorMagneticField`` (sensor frame, a.u.), ``jointAngle*`` (degrees, joint frames) and
  ``footContacts`` (flags) are kept as in the file.
* Times: the frame ``time`` attribute (ms since the start of the recording) becomes
  ``device_time_ns``. An MVNX file carries no host receive clock, so ``host_time_ns`` is a copy
  of ``device_time_ns`` (the track's ``meta['host_time']`` says so).

Streaming: the file is parsed by :func:`defusedxml.ElementTree.iterparse` (expat, with entity
declarations and external references refused whatever the expat version: MVN never writes them, and
entity expansion could fill memory); each frame is taken apart when it closes and removed from the
tree, as is every element once read, and its texts are parsed by block (NumPy's C text reader) into
arrays sized from the file size. Memory stays at the result arrays plus a few MB, whatever the
length of the file.

Counts are never trusted for allocation: ``<frames segmentCount sensorCount jointCount>`` must be
whole numbers up to :data:`MAX_ITEMS`, ``segmentCount`` must match the segments listed, and the
first normal frame must hold the values the counts imply before any array is made; the arrays then
hold the frames the file's bytes can hold at that frame's size (a few times the file size at most)
and grow as frames arrive. Elements nest at most :data:`MAX_DEPTH` deep and a frame or a
``<subject>`` section holds at most :data:`MAX_ELEMENTS` elements.

Bad files raise :class:`~dualhuman_builder.errors.FormatError` naming the file: malformed or
truncated XML with the line and column and what was read so far; entity declarations, external
references, an unknown encoding; a count that is not plausible or disagrees with the data; a frame
whose element holds the wrong number of values, or a non-number, with the frame and the element;
frames whose elements differ from the first normal frame's; times going backwards, not finite or
beyond the int64 nanosecond range. Values that are not finite are read as they are: orientations
that are not unit quaternions and positions that are not finite are marked invalid, counted in the
track's ``meta`` (``invalid_orientations``, ``invalid_positions``) and logged as a warning.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable
from xml.etree.ElementTree import ParseError
from xml.parsers.expat import ErrorString

import defusedxml.ElementTree as DET
import numpy as np
from defusedxml import DefusedXmlException, EntitiesForbidden, ExternalReferenceForbidden

from dualhuman_builder.errors import FormatError
from dualhuman_builder.tracks import SkeletonTrack

log = logging.getLogger(__name__)

MVNX_NAMESPACE = "http://www.xsens.com/mvn/mvnx"

#: Frame types that hold calibration poses rather than recorded motion.
CALIBRATION_TYPES = ("identity", "tpose", "tpose-isb")

#: Per-frame elements with one item per segment / sensor / joint / ergonomic joint: values per item.
SEGMENT_FIELDS = {"orientation": 4, "position": 3, "velocity": 3, "acceleration": 3, "angularVelocity": 3,
                  "angularAcceleration": 3}  # fmt: skip
SENSOR_FIELDS = {"sensorFreeAcceleration": 3, "sensorMagneticField": 3, "sensorOrientation": 4}
JOINT_FIELDS = {"jointAngle": 3, "jointAngleXZY": 3}
ERGO_FIELDS = {"jointAngleErgo": 3, "jointAngleErgoXZY": 3}

#: World-frame quaternions (w x y z, Z-up in the file) and world-frame 3-vectors (Z-up in the file).
QUAT_FIELDS = ("orientation", "sensorOrientation")
VECTOR_FIELDS = ("position", "velocity", "acceleration", "angularVelocity", "angularAcceleration",
                 "sensorFreeAcceleration", "centerOfMass")  # fmt: skip

#: Order of the per-frame elements in MVN's exports (the ``mvnx`` PyPI package reads them by position).
FRAME_FIELD_ORDER = ("orientation", "position", "velocity", "acceleration", "angularVelocity", "angularAcceleration",
                     "footContacts", "sensorFreeAcceleration", "sensorMagneticField", "sensorOrientation",
                     "jointAngle", "jointAngleXZY", "jointAngleErgo", "jointAngleErgoXZY", "centerOfMass")  # fmt: skip

HOST_TIME_NOTE = "host_time_ns copies device_time_ns: an MVNX file carries no host receive clock"

#: The legs: no sensor measures them in MVN's upper-body configurations.
LEG_SEGMENTS = ("RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToe", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot",
                "LeftToe")  # fmt: skip
_ABOVE_PELVIS = ("L5", "L3", "T12", "T8", "Neck", "Head", "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
                 "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand")  # fmt: skip
_HANDS = ("RightHand", "LeftHand")
#: MVN suit configurations (the subject's ``configuration`` attribute, as the Xsens MVN SDK names them) -> the
#: body segments no sensor measures there. MVN still reports all 23 segments: those it does not measure it
#: sets in a fixed pose (the legs of an upper-body recording) or carries along with a measured neighbour (a
#: hand with its forearm), so their motion is not the actor's.
CONFIGURATIONS: dict[str, tuple[str, ...]] = {
    "FullBody": (), "FullBodyNoSternum": (), "FullBodyNoHands": _HANDS, "FullBodyNoSternumNoHands": _HANDS,
    "FullBodyNoShoulders": ("RightShoulder", "LeftShoulder"),
    "UpperBody": LEG_SEGMENTS, "UpperBodyNoSternum": LEG_SEGMENTS, "UpperBodyNoHands": LEG_SEGMENTS + _HANDS,
    "UpperBodyNoSternumNoHands": LEG_SEGMENTS + _HANDS,
    "LowerBody": _ABOVE_PELVIS, "LowerBodyPlus": _ABOVE_PELVIS,
    "PelvisSternum": tuple(s for s in _ABOVE_PELVIS if s != "T8") + LEG_SEGMENTS,
    "SingleDevice": _ABOVE_PELVIS + LEG_SEGMENTS,
}  # fmt: skip


def unmeasured_segments(configuration: str) -> tuple[str, ...] | None:
    """The MVN body segments no sensor measures in suit ``configuration`` (:data:`CONFIGURATIONS`; the
    comparison ignores case, spaces and ``-``/``_``); ``()`` for a full body, ``None`` for a configuration
    this toolkit does not know (treated as a full body, and said so)."""
    key = "".join(ch for ch in str(configuration) if ch not in " -_").lower()
    for name, segments in CONFIGURATIONS.items():
        if name.lower() == key:
            return segments
    return None

_S = math.sqrt(0.5)
#: Most items of one kind (segments, sensors, joints, ergonomic joints) a frame may hold: a full MVN suit has
#: 23 segments, 17 sensors, 22 joints; props and gloves add tens.
MAX_ITEMS = 1000
#: Deepest element nesting read (MVN nests 7 deep: mvnx > subject > segments > segment > points > point > pos_b).
MAX_DEPTH = 32
#: Most elements inside one frame or one ``<subject>`` section (``<segments>``, ``<joints>``, ...), which are
#: held until they close.
MAX_ELEMENTS = 100_000
#: Frame times (ms) whose nanoseconds fit int64 (about 292 years either side of 0).
MAX_TIME_MS = 9.2e12
#: Most frames per second taken from ``frameRate``; a larger, non-finite or non-positive one is ignored.
MAX_FPS = 100_000.0

#: ``<subject>`` children read whole when they close.
_SECTIONS = ("segments", "sensors", "joints", "ergonomicJointAngles", "footContactDefinition")
_BLOCK = 512  # frames parsed per NumPy call
_CHUNK = 1 << 16  # bytes fed to the XML parser at a time (its events, and their elements, are queued per chunk)
_PROGRESS_EVERY = 1 << 18  # bytes between progress calls
_NAMES_CACHED = 4096  # tag names remembered (the file chooses how many there are)


# --------------------------------------------------------------------------------------------- conversions
def quat_file_to_ours(wxyz: np.ndarray) -> np.ndarray:
    """MVNX world quaternions ``(..., 4)`` w x y z, Z-up -> ours x y z w, Y-up (left-multiplied by
    the -90 degree rotation about X of :data:`~dualhuman_builder.conventions.ZUP_TO_YUP`)."""
    q = np.asarray(wxyz, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([_S * (x - w), _S * (y + z), _S * (z - y), _S * (w + x)], axis=-1)


def quat_ours_to_file(xyzw: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quat_file_to_ours`: ours x y z w, Y-up -> MVNX w x y z, Z-up."""
    q = np.asarray(xyzw, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([_S * (w - x), _S * (x + w), _S * (y - z), _S * (z + y)], axis=-1)


def vec_file_to_ours(v: np.ndarray) -> np.ndarray:
    """MVNX world vectors ``(..., 3)`` Z-up -> ours Y-up: ``(x, y, z) -> (x, z, -y)``."""
    v = np.asarray(v, dtype=np.float64)
    return np.stack([v[..., 0], v[..., 2], -v[..., 1]], axis=-1)


def vec_ours_to_file(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`vec_file_to_ours`: ``(x, y, z) -> (x, -z, y)``."""
    v = np.asarray(v, dtype=np.float64)
    return np.stack([v[..., 0], -v[..., 2], v[..., 1]], axis=-1)


def _to_ours(name: str, a: np.ndarray) -> np.ndarray:
    """Convert field ``name``'s values ``(n, width)`` (width a multiple of 4 for quaternions, of 3
    for vectors) to our frame, same shape."""
    if name in QUAT_FIELDS:
        return quat_file_to_ours(a.reshape(a.shape[0], -1, 4)).reshape(a.shape)
    if name in VECTOR_FIELDS:
        return vec_file_to_ours(a.reshape(a.shape[0], -1, 3)).reshape(a.shape)
    return a


# --------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class MvnxSegment:
    """A segment of the subject: ``label``, MVN ``id`` and its ``points`` (label -> ``pos_b (3,)``,
    metres, in the segment's own frame)."""

    label: str
    id: int
    points: dict[str, np.ndarray] = field(compare=False)


@dataclass(frozen=True)
class MvnxJoint:
    """A joint: ``label`` and its two connectors, ``"Segment/point"``."""

    label: str
    connector1: str
    connector2: str


@dataclass(frozen=True)
class CalibrationPose:
    """A calibration frame (``type`` identity / tpose / tpose-isb): ``orientations (S, 4)`` x y z w
    and ``positions (S, 3)`` metres, our Y-up world, segments in the file's order."""

    type: str
    orientations: np.ndarray = field(compare=False)
    positions: np.ndarray = field(compare=False)


@dataclass(eq=False)
class MvnxFile:
    """What :func:`read_mvnx` read.

    ``track``: the normal frames as a :class:`SkeletonTrack` (segments in the file's order);
    ``arrays``: the other per-frame elements present, ``(T, N, k)`` for those with one item per
    segment / sensor / joint / ergonomic joint (see :data:`SEGMENT_FIELDS` etc.), ``(T, n)`` for the
    rest (``footContacts``, ``centerOfMass``, unknown ones), converted as the module docstring says;
    ``frame_index (T,)`` the frames' ``index`` and ``epoch_ms (T,)`` their ``ms`` attribute (wall
    clock of the recording, ms since 1970; -1 where absent); ``calibration`` by frame type (every
    frame whose type is not ``normal``; a repeated type keeps its first frame).
    """

    path: Path
    version: str
    mvn_version: str
    mvn_build: str
    comment: str
    subject: dict[str, str]
    segments: tuple[MvnxSegment, ...]
    sensors: tuple[str, ...]
    joints: tuple[MvnxJoint, ...]
    ergonomic_joints: tuple[str, ...]
    foot_contacts: tuple[str, ...]
    calibration: dict[str, CalibrationPose]
    track: SkeletonTrack
    frame_index: np.ndarray
    epoch_ms: np.ndarray
    arrays: dict[str, np.ndarray]

    @property
    def num_frames(self) -> int:
        return self.track.num_frames

    @property
    def fps(self) -> float:
        return self.track.fps

    @property
    def label(self) -> str:
        return self.subject.get("label", "")

    @property
    def configuration(self) -> str:
        """The suit configuration MVN recorded with (``FullBody``, ``UpperBody``...; see
        :data:`CONFIGURATIONS`), ``""`` when the file does not say."""
        return self.subject.get("configuration", "")

    @property
    def segment_names(self) -> tuple[str, ...]:
        return self.track.segment_names


# --------------------------------------------------------------------------------------------- reader
class _Reader:
    """Event handler of one read; holds everything read so far."""

    def __init__(self, path: Path, total_bytes: int):
        self.path = path
        self.total_bytes = total_bytes
        self.names: dict[str, str] = {}
        self.stack: list[str] = []  # names of the open elements
        self.elems: list = []  # the open elements
        self.held = 0  # elements held in the open frame or <subject> section...
        self.held_from = 0  # ...which closes when the stack is shorter than this
        self.sections_read: set[str] = set()
        self.root_checked = False
        self.version = self.mvn_version = self.mvn_build = self.comment = ""
        self.subject: dict[str, str] = {}
        self.segments: list[MvnxSegment] = []
        self.sensors: list[str] = []
        self.joints: list[MvnxJoint] = []
        self.ergo: list[str] = []
        self.contacts: list[str] = []
        self.frames_attrib: dict[str, str] = {}
        self.calibration: dict[str, CalibrationPose] = {}
        self.fields: tuple[str, ...] | None = None
        self.widths: list[int] = []
        self.item_shapes: list[tuple[int, ...]] = []
        self.pending: list[list[str | None]] = []
        self.pending_attrs: list[tuple[str | None, str | None, str | None]] = []
        self.out: dict[str, np.ndarray] = {}
        self.times = np.empty(0)
        self.index = np.empty(0, dtype=np.int64)
        self.epoch = np.empty(0, dtype=np.int64)
        self.count: dict[str, int] | None = None
        self.explain: list[str] = []
        self.n = 0  # normal frames stored
        self.capacity = 0

    # ------------------------------------------------------------------ helpers
    def name(self, tag: str) -> str:
        n = self.names.get(tag)
        if n is None:
            n = tag.rpartition("}")[2]
            if len(self.names) < _NAMES_CACHED:
                self.names[tag] = n
        return n

    def summary(self) -> str:
        frames = self.n + len(self.pending_attrs)
        calib = ", ".join(self.calibration) or "none"
        return f"{len(self.segments)} segments, calibration poses: {calib}, {frames} complete normal frames"

    def error(self, message: str, fix: str | None = None) -> FormatError:
        return FormatError(message, path=self.path, fix=fix or "re-export the file from MVN Analyze/Animate")

    def frame_name(self, k: int, index: str | None, time: str | None) -> str:
        return f"frame {k} (index={index!r}, time={time!r} ms)"

    # ------------------------------------------------------------------ events
    def handle(self, events) -> None:
        """Take each ``(event, element)``; an element is removed from the tree once it is read, except
        the children of an open frame or ``<subject>`` section, read when that closes."""
        stack, elems = self.stack, self.elems
        for event, elem in events:
            name = self.names.get(elem.tag) or self.name(elem.tag)
            if event == "start":
                if not self.root_checked:
                    self.check_root(name, elem)
                if len(stack) >= MAX_DEPTH:
                    raise self.error(f"elements nested more than {MAX_DEPTH} deep (<{name}> inside "
                                     f"{' > '.join(stack[:6])} > ...); MVNX nests 7 deep")  # fmt: skip
                if self.holds_children():
                    if not self.held:
                        self.held_from = len(stack)
                    self.held += 1
                    if self.held > MAX_ELEMENTS:
                        raise self.error(f"more than {MAX_ELEMENTS:,} elements inside {' > '.join(stack)}")
                stack.append(name)
                elems.append(elem)
                if name == "frames":
                    self.frames_attrib = dict(elem.attrib)
                    self.start_frames()
                elif name == "subject" and len(stack) == 2:
                    self.subject = dict(elem.attrib)
                continue
            stack.pop()
            elems.pop()
            if name == "frame":
                self.frame(elem)
            elif len(stack) == 2 and stack[1] == "subject":
                self.subject_child(name, elem)
            elif len(stack) == 1:
                if name == "mvn":
                    self.mvn_version = elem.get("version", "")
                    self.mvn_build = elem.get("build", "")
                elif name == "comment":
                    self.comment = (elem.text or "").strip()
            if elems and not self.holds_children():
                del elems[-1][:]  # read: off the tree
            if len(stack) < self.held_from:
                self.held = self.held_from = 0

    def holds_children(self) -> bool:
        """Whether the innermost open element keeps its children until it closes: a frame, or an
        element of a ``<subject>`` section (see :data:`_SECTIONS`)."""
        stack = self.stack
        return bool(stack) and (stack[-1] == "frame" or (len(stack) >= 3 and stack[1] == "subject"
                                                         and stack[2] in _SECTIONS))  # fmt: skip

    def check_root(self, name: str, elem) -> None:
        self.root_checked = True
        if name != "mvnx":
            raise self.error(f"not an MVNX file: the root element is <{name}>, not <mvnx>",
                             fix="pass an .mvnx file exported by Xsens MVN")  # fmt: skip
        ns = elem.tag[1:].partition("}")[0] if elem.tag.startswith("{") else ""
        if ns and ns != MVNX_NAMESPACE:
            log.warning("%s: unexpected namespace %s (expected %s); reading on", self.path, ns, MVNX_NAMESPACE)
        self.version = elem.get("version", "")

    def subject_child(self, name: str, elem) -> None:
        if name in _SECTIONS and self.count is not None:
            raise self.error(f"<{name}> after <frames>: the frames were read with the definitions before them")
        if name in _SECTIONS and name in self.sections_read:
            raise self.error(f"a second <{name}> in <subject>")
        self.sections_read.add(name)
        if name == "segments":
            for seg in elem:
                if self.name(seg.tag) != "segment":
                    continue
                points = {}
                for pts in seg:
                    if self.name(pts.tag) != "points":
                        continue
                    for pt in pts:
                        pos = next((c for c in pt if self.name(c.tag) == "pos_b"), None)
                        label = pt.get("label", "")
                        vals = self.small_floats(pos.text if pos is not None else None,
                                                 f"pos_b of point {label!r} of segment {seg.get('label')!r}")  # fmt: skip
                        if vals.size != 3:
                            raise self.error(f"pos_b of point {label!r} of segment {seg.get('label')!r} holds "
                                             f"{vals.size} values, expected 3")  # fmt: skip
                        points[label] = vals
                try:
                    sid = int(seg.get("id", len(self.segments) + 1))
                except ValueError:
                    raise self.error(f"segment {seg.get('label')!r} has a non-integer id {seg.get('id')!r}") from None
                self.segments.append(MvnxSegment(seg.get("label", f"segment{sid}"), sid, points))
        elif name == "sensors":
            self.sensors = [s.get("label", "") for s in elem if self.name(s.tag) == "sensor"]
        elif name == "joints":
            for j in elem:
                if self.name(j.tag) != "joint":
                    continue
                conn = {self.name(c.tag): (c.text or "").strip() for c in j}
                self.joints.append(MvnxJoint(j.get("label", ""), conn.get("connector1", ""), conn.get("connector2", "")))
        elif name == "ergonomicJointAngles":
            self.ergo = [e.get("label", "") for e in elem]
        elif name == "footContactDefinition":
            self.contacts = [c.get("label", "") for c in elem]

    def small_floats(self, text: str | None, what: str) -> np.ndarray:
        try:
            return np.array((text or "").split(), dtype=np.float64)
        except ValueError:
            raise self.error(f"{what} holds a value that is not a number: {(text or '')[:80]!r}") from None

    def counts(self) -> dict[str, int]:
        """Items per frame of each kind, from <frames> (falling back on the lists in <subject>): whole
        numbers up to :data:`MAX_ITEMS`; the first normal frame checks them against its values."""
        out = {}
        for key, listed in (("segmentCount", self.segments), ("sensorCount", self.sensors),
                            ("jointCount", self.joints)):  # fmt: skip
            value = self.frames_attrib.get(key)
            if value in (None, ""):
                out[key] = len(listed)
                continue
            text = value.strip()
            if not (text.isascii() and text.isdigit() and len(text) <= 9):
                raise self.error(f"<frames {key}={value[:40]!r}> is not a whole number of items")
            out[key] = int(text)
        out["ergoCount"] = len(self.ergo)
        for key, n in out.items():
            if n > MAX_ITEMS:
                raise self.error(f"<frames> claims {n:,} items per frame ({key}); more than any MVN setup has "
                                 f"(at most {MAX_ITEMS})")  # fmt: skip
        return out

    def start_frames(self) -> None:
        c = self.counts()
        if not self.segments:
            raise self.error("no <segments> before <frames>: the file names no segments")
        if c["segmentCount"] != len(self.segments):
            raise self.error(f"<frames segmentCount={c['segmentCount']}> but <segments> lists {len(self.segments)}")
        self.count = c

    # ------------------------------------------------------------------ frames
    def frame(self, elem) -> None:
        a = elem.attrib
        ftype = a.get("type", "normal") or "normal"
        if self.count is None:
            raise self.error("a <frame> outside <frames>")
        if ftype != "normal":
            self.calibration_frame(ftype, elem)
            return
        k = self.n + len(self.pending_attrs)
        names, texts = [], []
        for c in elem:
            names.append(self.names.get(c.tag) or self.name(c.tag))
            texts.append(c.text)
        names = tuple(names)
        if self.fields is None:
            self.init_fields(names, texts, a)
        elif names != self.fields:
            raise self.error(f"{self.frame_name(k, a.get('index'), a.get('time'))} holds elements {list(names)}; "
                             f"the first normal frame holds {list(self.fields)}")  # fmt: skip
        for buf, text in zip(self.pending, texts):
            buf.append(text)
        self.pending_attrs.append((a.get("time"), a.get("index"), a.get("ms")))
        if len(self.pending_attrs) >= _BLOCK:
            self.flush()

    def calibration_frame(self, ftype: str, elem) -> None:
        if ftype in self.calibration:
            log.warning("%s: a second calibration frame of type %r ignored", self.path, ftype)
            return
        S = len(self.segments)
        got = {}
        for c in elem:
            name = self.name(c.tag)
            if name in ("orientation", "position"):
                vals = self.small_floats(c.text, f"<{name}> of the {ftype!r} calibration frame")
                want = SEGMENT_FIELDS[name] * S
                if vals.size != want:
                    raise self.error(f"<{name}> of the {ftype!r} calibration frame holds {vals.size} values, "
                                     f"expected {want} ({SEGMENT_FIELDS[name]} per segment x {S} segments)")  # fmt: skip
                got[name] = vals.reshape(S, -1)
        if "orientation" not in got:
            raise self.error(f"the {ftype!r} calibration frame has no <orientation>")
        pos = got.get("position", np.full((S, 3), np.nan))
        self.calibration[ftype] = CalibrationPose(ftype, quat_file_to_ours(got["orientation"]), vec_file_to_ours(pos))

    def init_fields(self, names: tuple[str, ...], texts: list, attrs) -> None:
        if len(set(names)) != len(names):
            raise self.error(f"frame 0 (index={attrs.get('index')!r}) repeats an element: {list(names)}")
        for need in ("orientation", "position"):
            if need not in names:
                raise self.error(f"the normal frames have no <{need}> element (they hold {list(names)})")
        per_kind = ((SEGMENT_FIELDS, "segmentCount", "segment"), (SENSOR_FIELDS, "sensorCount", "sensor"),
                    (JOINT_FIELDS, "jointCount", "joint"), (ERGO_FIELDS, "ergoCount", "ergonomic joint"))  # fmt: skip
        self.fields = names
        self.widths, self.item_shapes, self.explain = [], [], []
        est_bytes = 40 + sum(len(a) + len(v) + 4 for a, v in attrs.items())
        for name, text in zip(names, texts):
            for table, key, what in per_kind:
                if name in table:
                    count = self.count[key]
                    if count == 0 and table is ERGO_FIELDS:  # no definition: take the width as it is
                        continue
                    self.widths.append(table[name] * count)
                    self.item_shapes.append((count, table[name]))
                    self.explain.append(f"{table[name]} per {what} x {count} {what}s")
                    held = len((text or "").split())
                    if held != self.widths[-1]:  # checked before any array is sized from the count
                        raise self.error(f"{self.frame_name(0, attrs.get('index'), attrs.get('time'))}: <{name}> "
                                         f"holds {held} values, expected {self.widths[-1]} ({self.explain[-1]})",
                                         fix=f"the count of {what}s ({key}) disagrees with the frames' values; "
                                             "re-export the file from MVN Analyze/Animate")  # fmt: skip
                    break
            else:
                width = len((text or "").split())
                self.widths.append(width)
                self.item_shapes.append((width,))
                self.explain.append("as many as in the first normal frame")
            est_bytes += len(text or "") + 2 * len(name) + 6
        self.pending = [[] for _ in names]
        # Preallocate for the frames the file's bytes can hold at this frame's size (trimmed at the end). Every
        # width is that of values present in the file, each taking 2 bytes or more of text and 8 in memory: at
        # most about 4x the file size.
        self.grow(int(self.total_bytes / max(est_bytes, 1) * 1.02) + 16)

    def grow(self, capacity: int) -> None:
        if not self.out:
            self.out = {n: np.empty((capacity, *shape)) for n, shape in zip(self.fields, self.item_shapes)}
            self.times = np.empty(capacity)
            self.index = np.empty(capacity, dtype=np.int64)
            self.epoch = np.empty(capacity, dtype=np.int64)
        else:  # in place (realloc), no second copy held
            for a in (*self.out.values(), self.times, self.index, self.epoch):
                a.resize((capacity, *a.shape[1:]), refcheck=False)
        self.capacity = capacity

    def parse_block(self, j: int, texts: list, k0: int) -> np.ndarray:
        """Texts of field ``j`` for frames ``k0...`` -> ``(n, width)`` float64."""
        width, n = self.widths[j], len(texts)
        if width:
            try:  # fast path: MVN writes single spaces
                vals = np.loadtxt(texts, dtype=np.float64, delimiter=" ", comments=None, ndmin=2)
                if vals.shape == (n, width):
                    return vals
            except (ValueError, TypeError):
                pass
        vals = np.empty((n, width))
        for i, text in enumerate(texts):
            parts = (text or "").split()
            attrs = self.pending_attrs[i]
            where = f"{self.frame_name(k0 + i, attrs[1], attrs[0])}: <{self.fields[j]}>"
            if len(parts) != width:
                raise self.error(f"{where} holds {len(parts)} values, expected {width} ({self.explain[j]})")
            try:
                vals[i] = np.array(parts, dtype=np.float64)
            except ValueError:
                bad = next(p for p in parts if not _is_float(p))
                raise self.error(f"{where} value {parts.index(bad)} is not a number: {bad!r}") from None
        return vals

    def flush(self) -> None:
        n = len(self.pending_attrs)
        if n == 0:
            return
        k0 = self.n
        if k0 + n > self.capacity:
            self.grow(max(k0 + n, int(self.capacity * 1.5)))
        for j, name in enumerate(self.fields):
            vals = _to_ours(name, self.parse_block(j, self.pending[j], k0))
            self.out[name][k0 : k0 + n] = vals.reshape(n, *self.item_shapes[j])
            self.pending[j].clear()
        for i, (t, idx, ms) in enumerate(self.pending_attrs):
            k = k0 + i
            try:
                time = float(t)
            except (TypeError, ValueError):
                raise self.error(f"{self.frame_name(k, idx, t)} has no numeric time attribute") from None
            if not abs(time) <= MAX_TIME_MS:
                raise self.error(f"{self.frame_name(k, idx, t)} has a time that is not finite or beyond "
                                 f"{MAX_TIME_MS:g} ms (292 years)")  # fmt: skip
            self.times[k] = time
            self.index[k] = _int_or(idx, -1)
            self.epoch[k] = _int_or(ms, -1)
        self.pending_attrs.clear()
        self.n = k0 + n

    # ------------------------------------------------------------------ result
    def finish(self) -> MvnxFile:
        if not self.root_checked:
            raise self.error("empty file: no <mvnx> element")
        self.flush()
        if self.fields is None:
            raise self.error(f"no normal frames (read {self.summary()})")
        T = self.n
        for a in (*self.out.values(), self.times, self.index, self.epoch):
            a.resize((T, *a.shape[1:]), refcheck=False)
        times = self.times
        back = np.flatnonzero(np.diff(times) < 0)
        if back.size:
            k = int(back[0]) + 1
            raise self.error(f"time goes backwards at frame {k} (index {self.index[k]}): "
                             f"{times[k]:g} ms after {times[k - 1]:g} ms")  # fmt: skip
        t_ns = np.round(times * 1e6).astype(np.int64)
        fps = _float_or(self.subject.get("frameRate"), 0.0)
        if not 0 < fps <= MAX_FPS:  # absent or not a rate: from the frame times
            step = float(np.median(np.diff(t_ns))) if T > 1 else 0.0
            fps = 1e9 / step if step > 0 else 0.0
        quat = self.out.pop("orientation")
        pos = self.out.pop("position")
        with np.errstate(over="ignore", invalid="ignore"):  # huge or non-finite values: marked invalid below
            norms = np.sqrt(np.einsum("tsk,tsk->ts", quat, quat))
        ovalid = np.isfinite(norms) & (np.abs(norms - 1.0) <= 1e-3)
        pvalid = np.isfinite(pos).all(-1)
        bad_o, bad_p = int((~ovalid).sum()), int((~pvalid).sum())
        if bad_o or bad_p:
            log.warning("%s: %d orientations not unit quaternions and %d positions not finite marked invalid",
                        self.path, bad_o, bad_p)  # fmt: skip
        meta = {"source": "mvnx", "file": self.path.name, "subject": self.subject.get("label", ""),
                "host_time": HOST_TIME_NOTE, "invalid_orientations": bad_o, "invalid_positions": bad_p}  # fmt: skip
        try:
            track = SkeletonTrack(segment_names=[s.label for s in self.segments], orientations=quat, positions=pos,
                                  device_time_ns=t_ns, host_time_ns=t_ns, orientation_valid=ovalid,
                                  position_valid=pvalid, fps=fps, meta=meta)  # fmt: skip
        except ValueError as e:
            raise self.error(f"inconsistent skeleton: {e}") from None
        for a in (*self.out.values(), self.index, self.epoch):
            a.setflags(write=False)
        return MvnxFile(path=self.path, version=self.version, mvn_version=self.mvn_version, mvn_build=self.mvn_build,
                        comment=self.comment, subject=self.subject, segments=tuple(self.segments),
                        sensors=tuple(self.sensors), joints=tuple(self.joints), ergonomic_joints=tuple(self.ergo),
                        foot_contacts=tuple(self.contacts), calibration=self.calibration, track=track,
                        frame_index=self.index, epoch_ms=self.epoch, arrays=self.out)  # fmt: skip


def _is_float(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def _int_or(text: str | None, default: int) -> int:
    """``text`` as an int64 (a float is truncated), or ``default`` when it is absent, not a number or out
    of int64's range."""
    if not text:
        return default
    try:
        value = int(text)
    except ValueError:
        try:
            value = int(float(text))
        except (ValueError, OverflowError):
            return default
    return value if -(2**63) <= value < 2**63 else default


def _float_or(text: str | None, default: float) -> float:
    try:
        return float(text) if text else default
    except ValueError:
        return default


def read_mvnx(path: str | Path, progress: Callable[[int, int, int], None] | None = None) -> MvnxFile:
    """Read an MVNX file streaming (see the module docstring for conversions, limits and errors).

    ``progress(frames, bytes_read, total_bytes)`` is called after each 256 KiB read.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError("no such file", path=path, fix="check the path")
    total = path.stat().st_size
    reader = _Reader(path, total)
    with open(path, "rb") as f:
        source = _Source(f, reader, total, progress)
        reader.handle(_events(source, reader))
    return reader.finish()


class _Source:
    """The file as the parser reads it, :data:`_CHUNK` bytes at a time. ``progress`` is called on a read
    every :data:`_PROGRESS_EVERY` bytes and at the end (every event of the bytes before has then been
    handled), what it raises kept as ``failure``; ``eof`` once the file is all read."""

    def __init__(self, f, reader: _Reader, total: int, progress: Callable[[int, int, int], None] | None):
        self.f, self.reader, self.total, self.progress = f, reader, total, progress
        self.done = self.reported = 0
        self.eof = False
        self.failure: BaseException | None = None

    def read(self, size: int = -1) -> bytes:
        chunk = self.f.read(_CHUNK)
        if self.progress is not None and self.done and (not chunk or self.done - self.reported >= _PROGRESS_EVERY):
            self.reported = self.done
            try:
                self.progress(self.reader.n + len(self.reader.pending_attrs), self.done, self.total)
            except BaseException as e:
                self.failure = e
                raise
        self.done += len(chunk)
        self.eof = not chunk
        return chunk


#: What the XML parser raises on a file it refuses (``ValueError``, ``LookupError``: an encoding that
#: expat cannot read through Python's codecs).
_REFUSALS = (ParseError, DefusedXmlException, LookupError, ValueError)


def _events(source: _Source, reader: _Reader):
    """``(event, element)`` of the file, start and end; what the XML parser refuses becomes a
    :class:`FormatError` (:func:`_refused`)."""
    events = DET.iterparse(source, events=("start", "end"), forbid_dtd=False, forbid_entities=True,
                           forbid_external=True)  # fmt: skip
    while True:
        try:
            item = next(events, None)
        except _REFUSALS as e:
            if e is source.failure:
                raise
            raise _refused(e, source, reader) from None
        if item is None:
            return
        yield item


def _refused(e: Exception, source: _Source, reader: _Reader) -> FormatError:
    """The :class:`FormatError` for what the XML parser raised: where it stopped and what was read."""
    path = reader.path
    fix = "re-export the file from MVN; do not import XML of unknown origin"
    if isinstance(e, ParseError):
        line, col = e.position
        inside = " > ".join(reader.stack) or "no element"
        what = "the file ends before its XML is complete" if source.eof else "malformed XML"
        return FormatError(
            f"{what}: line {line}, column {col} ({ErrorString(e.code)}) inside {inside}; "
            f"read so far: {reader.summary()}",
            path=path,
            fix="the file is truncated or not well-formed XML; re-export it from MVN",
        )
    if isinstance(e, EntitiesForbidden):
        what = f"{e.name!r}, external: {e.sysid!r}" if e.sysid else repr(e.name)
        return FormatError(f"the file declares an XML entity ({what}); refused: MVN never writes entities, and "
                           "expanding them can fill memory", path=path, fix=fix)  # fmt: skip
    if isinstance(e, ExternalReferenceForbidden):
        return FormatError(f"the file refers to an external resource ({e.sysid!r}); refused: an MVNX file is "
                           "self-contained", path=path, fix=fix)  # fmt: skip
    if isinstance(e, DefusedXmlException):
        return FormatError(f"refused XML construct: {e}", path=path, fix=fix)
    return FormatError(f"cannot read the file's text encoding: {e}", path=path,
                       fix="re-export the file from MVN (UTF-8)")  # fmt: skip
