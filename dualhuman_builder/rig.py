"""Rig files: which devices a studio uses and who wears what (``rigs/*.toml``).

A rig names its sources by URL (one handler per scheme, like pyserial's ``serial_for_url``), binds
each actor to a source and, for MVN, a character ID, and says which MVN segment each of the
actor's trackers is strapped to. It also names the segment mapping used to retarget onto the body
model (looked up beside the rig file, then in the toolkit's ``rigs/``; default
``rigs/mvn_anny.toml``). Example: ``rigs/studio.toml``.

::

    [rig]
    name = "studio"
    mapping = "mvn_anny.toml"        # optional

    [[sources]]
    name = "suits"
    url = "mvn+udp://0.0.0.0:9763?allow=192.168.10.11"

    [[actors]]
    name = "alice"
    source = "suits"
    character = 0
    [actors.trackers]                # tracker serial = MVN segment
    "LHR-A1" = "Pelvis"

Loading checks what would make the rig unusable (:class:`~dualhuman_builder.errors.RigError`);
:meth:`Rig.warnings` what would let strangers in: a UDP source listening on every interface
without ``allow=`` (any machine that reaches the port can send samples), a ``vive+udp`` source
without ``serials=`` (any serial is kept, and invented ones compete for the tracker table), and an
actor's tracker that no ``serials=`` lists (its poses would be dropped).
"""

from __future__ import annotations

import hashlib
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

from dualhuman_builder.body.mapping import DEFAULT_MAPPING_PATH, MVN_SEGMENTS, SegmentMapping, load_segment_mapping
from dualhuman_builder.errors import RigError
from dualhuman_builder.resources import RIGS_DIR

#: Where the capture protocol straps a VIVE tracker on each MVN segment: the tracker's origin in
#: the segment's frame (x forward, y left, z up at the T-pose; metres), on the body surface — belt
#: at the back of the pelvis, top of the head, back of each wrist (towards the forearm), instep in
#: front of each ankle. The sync stage uses them as the prior of the mount translations (which
#: makes an actor's heading solvable from the tracker constellation while the actor stands still);
#: the simulated trackers are strapped there (plus a centimetre or so).
TRACKER_SITES: dict[str, tuple[float, float, float]] = {
    "Pelvis": (-0.11, 0.0, 0.02), "Head": (-0.04, 0.0, 0.16),
    "LeftHand": (0.0, -0.03, 0.035), "RightHand": (0.0, 0.03, 0.035),
    "LeftFoot": (0.06, 0.0, 0.03), "RightFoot": (0.06, 0.0, 0.03),
}  # fmt: skip

#: Site on a segment without an entry in :data:`TRACKER_SITES`: 5 cm off the origin, up.
GENERIC_TRACKER_SITE = (0.0, 0.0, 0.05)


def tracker_site(segment: str) -> tuple[float, float, float]:
    """The capture protocol's tracker site on MVN ``segment`` (metres, segment frame)."""
    return TRACKER_SITES.get(segment, GENERIC_TRACKER_SITE)


#: URL schemes of capture sources (handlers live in :mod:`dualhuman_builder.capture`).
SOURCE_SCHEMES = ("mvn+udp", "xbus", "mti+can", "vive+udp", "vive+usb", "sim")
#: Schemes that listen on a UDP port, and the bind addresses that mean every interface.
UDP_SCHEMES = ("mvn+udp", "vive+udp")
ALL_INTERFACES = ("0.0.0.0", "::")


@dataclass(frozen=True)
class RigSource:
    name: str
    url: str

    @property
    def scheme(self) -> str:
        return urlsplit(self.url).scheme

    @property
    def query(self) -> dict[str, str]:
        """The URL's query parameters (the last of a repeated one; capture refuses repeats)."""
        return dict(parse_qsl(urlsplit(self.url).query, keep_blank_values=True))


@dataclass(frozen=True)
class RigActor:
    name: str
    source: str
    character: int | None
    trackers: dict[str, str] = field(default_factory=dict)  # serial -> MVN segment


@dataclass(frozen=True)
class Rig:
    name: str
    path: Path
    text: str
    sources: tuple[RigSource, ...]
    actors: tuple[RigActor, ...]
    mapping: SegmentMapping

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode("utf-8")).hexdigest()

    def source(self, name: str) -> RigSource:
        for s in self.sources:
            if s.name == name:
                return s
        raise KeyError(name)

    def warnings(self) -> list[str]:
        """What would let a stranger's packets in, one sentence with its fix each (module
        docstring); [] for a rig that names its senders and trackers."""
        out = []
        worn = {serial: a.name for a in self.actors for serial in a.trackers}
        listed: set[str] = set()
        vive = [s for s in self.sources if s.scheme == "vive+udp"]
        for s in self.sources:
            if s.scheme not in UDP_SCHEMES:
                continue
            query = s.query
            try:
                host = urlsplit(s.url).hostname or ""
            except ValueError:
                host = ""
            if host in ALL_INTERFACES and not query.get("allow", "").strip():
                out.append(f"source {s.name!r} listens on every interface ({s.url}) without allow=: any machine "
                           "that reaches the port can send it samples; add allow=SENDER_IP (the machine that "
                           "streams to it), or bind the studio network's own address")  # fmt: skip
            if s.scheme == "vive+udp":
                serials = [x.strip() for x in query.get("serials", "").split(",") if x.strip()]
                listed.update(serials)
                if not serials:
                    hint = ",".join(sorted(worn)) if worn else "LHR-AAAA,LHR-BBBB"
                    out.append(f"source {s.name!r} keeps every tracker serial it hears ({s.url}): any sender can "
                               f"add trackers; add serials={hint}")  # fmt: skip
        if vive and all(s.query.get("serials", "").strip() for s in vive):
            for serial, actor in worn.items():
                if serial not in listed:
                    out.append(f"tracker {serial!r} worn by {actor!r} is in no serials= of the rig's vive+udp "
                               "sources: its poses would be dropped; add it to serials=")  # fmt: skip
        return out


def _mapping_path(name, rig_path: Path) -> Path:
    """A rig's segment mapping: beside the rig file, else among the toolkit's ``rigs/``."""
    if name is None:
        return DEFAULT_MAPPING_PATH
    for folder in (rig_path.parent, RIGS_DIR):
        if (folder / str(name)).is_file():
            return folder / str(name)
    raise RigError(f"segment mapping {name!r} not found beside the rig nor in {RIGS_DIR}", path=rig_path,
                   fix="fix the [rig] mapping entry, or omit it to use rigs/mvn_anny.toml")  # fmt: skip


def load_rig(path: str | Path) -> Rig:
    """Read and check a rig file; every error names the file, the entry and the fix."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RigError("rig file not found", path=path, fix="see rigs/studio.toml for an example") from None
    except UnicodeDecodeError as e:
        raise RigError(f"rig file is not UTF-8 text ({e})", path=path) from None
    return parse_rig(text, path)


def parse_rig(text: str, path: Path) -> Rig:
    def err(message: str, fix: str = "see rigs/studio.toml for the format") -> RigError:
        return RigError(message, path=path, fix=fix)

    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise err(f"not valid TOML: {e}") from e
    head = doc.get("rig")
    if not isinstance(head, dict) or not isinstance(head.get("name"), str) or not head["name"]:
        raise err("needs a [rig] table with a non-empty name")
    sources: list[RigSource] = []
    for i, s in enumerate(doc.get("sources", [])):
        if not isinstance(s, dict) or not isinstance(s.get("name"), str) or not isinstance(s.get("url"), str):
            raise err(f"[[sources]] #{i + 1} needs a name and a url")
        src = RigSource(s["name"], s["url"])
        if src.scheme not in SOURCE_SCHEMES:
            raise err(f"source {src.name!r}: unknown URL scheme {src.scheme!r} in {src.url!r}",
                      fix=f"use one of {', '.join(s + '://' for s in SOURCE_SCHEMES)}")  # fmt: skip
        if any(o.name == src.name for o in sources):
            raise err(f"source name {src.name!r} is used twice")
        sources.append(src)
    mapping = load_segment_mapping(_mapping_path(head.get("mapping"), path))

    actors: list[RigActor] = []
    serials: dict[str, str] = {}
    for i, a in enumerate(doc.get("actors", [])):
        if not isinstance(a, dict) or not isinstance(a.get("name"), str) or not a["name"]:
            raise err(f"[[actors]] #{i + 1} needs a name")
        name = a["name"]
        if any(o.name == name for o in actors):
            raise err(f"actor {name!r} is listed twice")
        source = a.get("source")
        if source is not None and not any(s.name == source for s in sources):
            raise err(f"actor {name!r} uses source {source!r}, which the rig does not define",
                      fix=f"define it under [[sources]] or use one of {[s.name for s in sources]}")  # fmt: skip
        character = a.get("character")
        if character is not None and (not isinstance(character, int) or not 0 <= character <= 255):
            raise err(f"actor {name!r}: character must be an MVN character ID 0-255, got {character!r}")
        trackers = a.get("trackers", {})
        if not isinstance(trackers, dict):
            raise err(f"actor {name!r}: trackers must be a table of serial = MVN segment")
        for serial, segment in trackers.items():
            if segment not in MVN_SEGMENTS:
                raise err(f"actor {name!r}: tracker {serial!r} is on unknown MVN segment {segment!r}",
                          fix=f"use one of the 23 MVN segments: {', '.join(MVN_SEGMENTS)}")  # fmt: skip
            if serial in serials:
                raise err(f"tracker {serial!r} is worn by both {serials[serial]!r} and {name!r}")
            serials[serial] = name
        actors.append(RigActor(name, source, character, dict(trackers)))
    chars = [(a.source, a.character) for a in actors if a.character is not None]
    if len(chars) != len(set(chars)):
        raise err("two actors share one MVN character ID on the same source; each needs its own")
    return Rig(head["name"], path, text, tuple(sources), tuple(actors), mapping)
