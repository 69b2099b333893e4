"""Write a take: one MCAP file with the raw bytes of every packet, the decoded samples, Foxglove
transforms of the body poses, events, periodic status, and the rig and software as metadata.

Layout of a take file (all times int64 ns on the host's monotonic clock unless said otherwise):

===============================  ==========================================================================
topic                            messages
===============================  ==========================================================================
``raw/<source>``                 one per :class:`~dualhuman_builder.capture.sources.RawPacket`, its bytes
                                 as they arrived; ``log_time`` = host receive time; no schema; message
                                 encoding ``dualhuman.raw``; channel metadata ``url``, ``kind``
``<source>/<entity>/<Type>``     decoded samples (``entity``: ``mvn/<character>``, ``vive/<serial>``,
                                 ``imu/<device>``), ROS 1 encoded with their schema
                                 (:mod:`.schemas`); channel metadata ``actor`` and ``segment`` when the
                                 rig binds the entity to an actor
``tf/<actor>``                   ``foxglove.FrameTransforms`` (JSON) of the segment poses, at most
                                 ``foxglove_hz`` per character: open the take in Foxglove's 3D panel
``events``                       ``dualhuman.SourceEvent`` (JSON): stale characters, resyncs, errors
``status``                       ``dualhuman.Status`` (JSON) once a second: every source's counters
===============================  ==========================================================================

Metadata records: ``take`` (name, sources, actor bindings, wall-clock and monotonic start so the
host clock maps to UTC), ``rig`` (the rig file's text), ``software`` (toolkit and library
versions), and at the end ``stats`` (final counters).

The file is written with the ``mcap`` library's public ``mcap.writer.Writer`` (``mcap>=1.5``, for
``Writer.flush``), which keeps up with the studio's message rate many times over
(``benchmarks/probes/probe_mcap_writer.py`` measures it; ``docs/decisions/0026-mcap-public-writer.md``).

Crash safety: messages collect in a chunk (LZ4) that is written when it reaches ``chunk_size``
bytes or ``flush_s`` seconds, whichever comes first, and the file is ``fsync``-ed then. A
``kill -9`` or power loss loses at most the chunk in progress; the file stays readable up to it
and ``dualhuman log repair`` rebuilds the index (:mod:`.reader`).
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections import Counter
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from mcap.writer import CompressionType, Writer

from dualhuman_builder.capture.log import schemas
from dualhuman_builder.capture.sources import RawPacket, SourceEvent
from dualhuman_builder.errors import DualhumanError

PROFILE = "dualhuman"
RAW_ENCODING = "dualhuman.raw"
TAKE_FORMAT_VERSION = "1"

#: ``foxglove.FrameTransforms`` as JSON Schema (Foxglove's published schema, fields we fill).
FRAME_TRANSFORMS_SCHEMA = {
    "title": "foxglove.FrameTransforms",
    "type": "object",
    "properties": {"transforms": {"type": "array", "items": {
        "title": "foxglove.FrameTransform", "type": "object",
        "properties": {
            "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
            "parent_frame_id": {"type": "string"},
            "child_frame_id": {"type": "string"},
            "translation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}},
            "rotation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}},
        }}}},
}  # fmt: skip
EVENT_SCHEMA = {"title": "dualhuman.SourceEvent", "type": "object", "properties": {
    "source": {"type": "string"}, "kind": {"type": "string"}, "entity": {"type": "string"},
    "message": {"type": "string"}, "host_time_ns": {"type": "integer"}}}  # fmt: skip
STATUS_SCHEMA = {"title": "dualhuman.Status", "type": "object", "properties": {
    "host_time_ns": {"type": "integer"}, "sources": {"type": "object"}}}  # fmt: skip

#: Our world is Y-up; Foxglove's is Z-up: a ``studio`` frame under ``world`` turns one into the other
#: (+90 degrees about X, the quaternion of ZUP_TO_YUP^T).
_STUDIO_ROTATION = {"x": float(np.sqrt(0.5)), "y": 0.0, "z": 0.0, "w": float(np.sqrt(0.5))}


class TakeWriteError(DualhumanError):
    """The take file cannot be written (disk full, file-size limit, I/O error)."""


def entity_of(sample) -> str:
    """``mvn/<character>``, ``vive/<serial>`` or ``imu/<device>``: who produced ``sample``."""
    c = getattr(sample, "character", None)
    if c is not None:
        return f"mvn/{c}"
    s = getattr(sample, "serial", None)
    if s is not None:
        return f"vive/{s}"
    d = getattr(sample, "device", None)
    if d is not None:
        return f"imu/{d}"
    return "device"


def software_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    from dualhuman_builder import __version__

    out = {"dualhuman-builder": __version__, "python": platform.python_version(), "host": platform.node(),
           "platform": platform.platform()}
    for pkg in ("mcap", "python-can", "pyserial", "pyusb", "numpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            pass
    return out


def binding(bindings: Mapping, source: str, entity: str) -> dict[str, str]:
    """What ``bindings`` (``{source or "*": {entity: {...}}}``) says of ``entity`` of ``source``."""
    return bindings.get(source, {}).get(entity) or bindings.get("*", {}).get(entity) or {}


class SampleEncoder:
    """Decoded samples -> the items a :class:`TakeWriter` writes: the CPU-heavy half of writing,
    so that it can run in a decoding process beside the recorder.

    :meth:`encode` returns a list of items: ``("decl", key, source, type name, entity, schema
    name, definition)`` the first time a (source, sample type, entity) is seen, ``("msg", key,
    log time, payload)`` per sample (ROS 1 bytes, :mod:`.schemas`), and ``("tf", actor, log time,
    payload)`` — ``foxglove.FrameTransforms`` JSON of a suit frame, at most ``foxglove_hz`` per
    character (0: none)."""

    def __init__(self, source_names: list[str], bindings: Mapping, foxglove_hz: float = 60.0):
        self.source_names = list(source_names)
        self.bindings = bindings
        self.period_ns = int(1e9 / foxglove_hz) if foxglove_hz and foxglove_hz > 0 else 0
        self._keys: dict[tuple, tuple[int, Any]] = {}
        self._tf_last: dict[tuple[int, int], int] = {}

    def encode(self, source: int, sample) -> list[tuple]:
        cls = type(sample)
        entity = entity_of(sample)
        k = (source, cls, entity)
        entry = self._keys.get(k)
        out = []
        if entry is None:
            layout = schemas.layout_for(sample)
            entry = self._keys[k] = (len(self._keys) + 1, schemas.make_shaped_encoder(layout, sample))
            out.append(("decl", entry[0], source, cls.__name__, entity, layout.schema_name, layout.definition))
        t = sample.host_time_ns
        out.append(("msg", entry[0], t, entry[1](sample)))
        if self.period_ns and cls.__name__ == "SuitFrame":
            tf = self._transforms(source, sample)
            if tf is not None:
                out.append(tf)
        return out

    def _transforms(self, source: int, frame):
        key = (source, frame.character)
        t = frame.host_time_ns
        if t - self._tf_last.get(key, -(1 << 62)) < self.period_ns:
            return None
        self._tf_last[key] = t
        name = self.source_names[source]
        actor = binding(self.bindings, name, f"mvn/{frame.character}").get("actor") or f"{name}-{frame.character}"
        stamp = {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000}
        transforms = [{"timestamp": stamp, "parent_frame_id": "world", "child_frame_id": "studio",
                       "translation": {"x": 0.0, "y": 0.0, "z": 0.0}, "rotation": _STUDIO_ROTATION}]  # fmt: skip
        pos = np.asarray(frame.positions, dtype=float).tolist()
        quat = np.asarray(frame.orientations, dtype=float).tolist()
        for seg, p, q in zip(frame.segment_names, pos, quat):
            transforms.append({"timestamp": stamp, "parent_frame_id": "studio", "child_frame_id": f"{actor}/{seg}",
                               "translation": {"x": p[0], "y": p[1], "z": p[2]},
                               "rotation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]}})  # fmt: skip
        return ("tf", actor, t, json.dumps({"transforms": transforms}).encode())


class TakeWriter:
    """Writes one take file (see the module docstring). Not thread-safe: one writer thread.

    ``sources``: ``[(name, url, kind), ...]`` in the order the recorder indexes them;
    ``bindings``: ``{source name or "*": {entity: {"actor": name, "segment": MVN segment}}}``
    from the rig (:func:`dualhuman_builder.capture.recorder.rig_bindings`); ``foxglove_hz``: transforms per second and
    character (0: none).
    """

    def __init__(self, path: str | Path, *, take: str, sources: list[tuple[str, str, str]],
                 bindings: Mapping[str, Mapping[str, Mapping[str, str]]] | None = None, rig_text: str | None = None,
                 chunk_size: int = 1 << 20, flush_s: float = 1.0, foxglove_hz: float = 60.0,
                 extra_meta: Mapping[str, str] | None = None):  # fmt: skip
        self.path = Path(path)
        if self.path.exists():
            raise TakeWriteError("a take file already exists here; takes are never overwritten", path=self.path,
                                 fix="choose another take name or --out path")  # fmt: skip
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "xb")
        self.sources = list(sources)
        self.bindings = {k: dict(v) for k, v in (bindings or {}).items()}
        self.flush_s = float(flush_s)
        self.closed = False
        self.failed: BaseException | None = None
        self.messages = 0
        self._w = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.LZ4)
        self._guard(self._w.start, PROFILE, "dualhuman_builder")
        self._raw_channels = [
            self._w.register_channel(f"raw/{name}", RAW_ENCODING, 0, {"url": url, "kind": kind, "source": name})
            for name, url, kind in self.sources
        ]
        self._schemas: dict[str, int] = {}
        self._keys: dict[int, int] = {}
        self._json_channels: dict[str, int] = {}
        #: Turns samples into messages; a recorder may run its twin in a decoding process instead.
        self.encoder = SampleEncoder([n for n, _, _ in self.sources], self.bindings, foxglove_hz)
        self.start_monotonic_ns = time.monotonic_ns()
        self.start_wall_ns = time.time_ns()
        meta = {"name": take, "format_version": TAKE_FORMAT_VERSION,
                "start_wall_clock_ns": str(self.start_wall_ns), "start_monotonic_ns": str(self.start_monotonic_ns),
                "start_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.start_wall_ns / 1e9)),
                "sources": json.dumps([{"name": n, "url": u, "kind": k} for n, u, k in self.sources]),
                "bindings": json.dumps(self.bindings), **(extra_meta or {})}  # fmt: skip
        self.take_start_utc = meta["start_utc"]
        #: Decoded samples written per channel id (topics in :attr:`topics`).
        self.sample_counts: Counter = Counter()
        self.topics: dict[int, str] = {}
        self._guard(self._w.add_metadata, "take", meta)
        self._guard(self._w.add_metadata, "software", software_versions())
        if rig_text is not None:
            self._guard(self._w.add_metadata, "rig", {"toml": rig_text})
        self._last_flush = time.monotonic()
        self.flush()

    def binding(self, source: str, entity: str) -> dict[str, str]:
        """``{"actor": ..., "segment": ...}`` the rig gives ``entity`` of ``source`` (``"*"``: any
        source, as tracker serials are bound), or ``{}``."""
        return binding(self.bindings, source, entity)

    # ------------------------------------------------------------------ errors
    def _guard(self, fn, *args):
        if self.failed is not None:
            raise TakeWriteError(f"the take file can no longer be written ({self.failed})", path=self.path)
        try:
            return fn(*args)
        except OSError as e:
            raise self._fail(e) from e

    def _fail(self, e: OSError) -> TakeWriteError:
        """Remember that writing failed; the error to raise (it names the cause and the fix)."""
        self.failed = e
        what = {28: "the disk is full", 27: "the file-size limit was reached", 122: "the disk quota is exceeded"}
        reason = what.get(e.errno, e.strerror or str(e))
        return TakeWriteError(f"writing the take stopped: {reason}", path=self.path,
                              fix="free space (or raise the limit), then `dualhuman log repair` the file: "
                                  "everything up to the last complete chunk is kept")  # fmt: skip

    # ------------------------------------------------------------------ messages
    def add_raw(self, source: int, packet: RawPacket) -> None:
        t = packet.host_time_ns
        if self.failed is not None:
            self._guard(None)
        try:
            self._w.add_message(self._raw_channels[source], t, packet.data, t)
        except OSError as e:
            raise self._fail(e) from e
        self.messages += 1

    def add_sample(self, source: int, sample) -> None:
        """One decoded sample of source number ``source`` (its channel and schema made on first use)."""
        for item in self.encoder.encode(source, sample):
            self.add_item(item)

    def add_item(self, item: tuple) -> None:
        """One item from a :class:`SampleEncoder` (here or in a decoding process)."""
        kind = item[0]
        if kind == "msg":
            _, key, t, payload = item
            cid = self._keys[key]
            self.sample_counts[cid] += 1
            if self.failed is not None:
                self._guard(None)
            try:
                self._w.add_message(cid, t, payload, t)
            except OSError as e:
                raise self._fail(e) from e
            self.messages += 1
        elif kind == "tf":
            _, actor, t, payload = item
            cid = self._json_channel(f"tf/{actor}", FRAME_TRANSFORMS_SCHEMA)
            self._guard(self._w.add_message, cid, t, payload, t)
            self.messages += 1
        else:
            _, key, source, type_name, entity, schema_name, definition = item
            self._keys[key] = self._declare(source, type_name, entity, schema_name, definition)

    def _declare(self, source: int, type_name: str, entity: str, schema_name: str, definition: str) -> int:
        sid = self._schemas.get(schema_name + definition)
        if sid is None:
            sid = self._guard(self._w.register_schema, schema_name, schemas.SCHEMA_ENCODING, definition.encode())
            self._schemas[schema_name + definition] = sid
        name, url, kind = self.sources[source]
        meta = {"source": name, "entity": entity, "kind": kind}
        meta.update(self.binding(name, entity))
        topic = f"{name}/{entity}/{type_name}"
        cid = self._guard(self._w.register_channel, topic, schemas.MESSAGE_ENCODING, sid, meta)
        self.topics[cid] = topic
        return cid

    def samples_per_topic(self) -> Counter:
        """Decoded samples written so far, by topic."""
        return Counter({self.topics[c]: n for c, n in self.sample_counts.items()})

    def _json_channel(self, topic: str, schema: dict) -> int:
        cid = self._json_channels.get(topic)
        if cid is None:
            name = schema["title"]
            sid = self._schemas.get(name)
            if sid is None:
                sid = self._schemas[name] = self._guard(self._w.register_schema, name, "jsonschema",
                                                        json.dumps(schema).encode())  # fmt: skip
            cid = self._json_channels[topic] = self._guard(self._w.register_channel, topic, "json", sid, {})
        return cid

    def add_event(self, source: str, event: SourceEvent) -> None:
        body = {"source": source, "kind": event.kind, "entity": event.entity, "message": event.message,
                "host_time_ns": event.host_time_ns}
        t = event.host_time_ns
        self._guard(self._w.add_message, self._json_channel("events", EVENT_SCHEMA), t, json.dumps(body).encode(), t)
        self.messages += 1

    def add_status(self, host_time_ns: int, stats: Mapping[str, Any]) -> None:
        body = json.dumps({"host_time_ns": host_time_ns, "sources": stats}, default=int).encode()
        cid = self._json_channel("status", STATUS_SCHEMA)
        self._guard(self._w.add_message, cid, host_time_ns, body, host_time_ns)
        self.messages += 1

    # ------------------------------------------------------------------ durability
    def maybe_flush(self) -> bool:
        """Write the chunk in progress and fsync when ``flush_s`` has passed; True if it did."""
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Write the chunk in progress and fsync the file."""
        self._guard(self._w.flush)
        self._guard(os.fsync, self._file.fileno())
        self._last_flush = time.monotonic()

    def close(self, stats: Mapping[str, Any] | None = None) -> None:
        """Write the final counters and the index (summary and footer), fsync, close. If the file
        can no longer be written, close it as it is: readable up to its last complete chunk."""
        if self.closed:
            return
        self.closed = True
        try:
            if self.failed is None:
                if stats is not None:
                    self._guard(self._w.add_metadata, "stats", {k: json.dumps(v, default=int) for k, v in stats.items()})
                self._guard(self._w.finish)
                self._guard(os.fsync, self._file.fileno())
        finally:
            try:
                self._file.close()
            except OSError:
                pass
