"""Repair a take: everything readable, the samples its raw bytes hold that were never written, a full index.

A take cut off by a crash or a full disk, or with damaged chunks, is rewritten record by record
(:class:`~dualhuman_builder.capture.log.reader.TakeReader`), with these rules:

* **Channels from wherever they survive.** Schemas and channels come from the summary section of a
  complete take as well as from the data, so a damaged chunk that held the channel records loses
  only its own messages. A message whose channel record is lost everywhere is kept: on ``raw/<source>``
  when its channel id is one of the raw channels (the recorder registers them first, ids 1.. in the
  order of the take's ``sources``), else on ``lost/<id>``; a channel whose schema is lost keeps its
  messages on ``lost/<topic>``.
* **What was lost is counted**: the bytes of the cut-off tail and of every damaged record, and the
  messages per topic that each damaged chunk held (its message index records, written after it).
* **Samples re-decoded.** The decoded samples of a take lag its raw bytes (a decoding process that
  was behind when the recorder was killed or the disk filled, a damaged chunk of samples). The raw
  packets of every source are run through a fresh decoder
  (:func:`~dualhuman_builder.capture.sources.make_decoder` on the source's URL, as
  :func:`~dualhuman_builder.capture.replay.redecode` does); a re-decoded sample that the take does
  not hold (same source, type, entity and host time) is written beside the recorded ones, in
  host-time order on its channel. Foxglove transforms are not rebuilt.
* **The original is never touched** until the repaired file is complete and synced: it is written
  to a temporary file beside it (or to ``out``) and removed if anything fails; a full disk gives a
  :class:`~dualhuman_builder.capture.log.writer.TakeWriteError` with the fix.
"""

from __future__ import annotations

import json
import os
import tempfile
from array import array
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import Attachment, Channel, Metadata, Schema

from dualhuman_builder.capture.log import schemas
from dualhuman_builder.capture.log.reader import TakeReader
from dualhuman_builder.capture.log.writer import PROFILE, RAW_ENCODING, TakeWriteError, binding, entity_of
from dualhuman_builder.capture.sources import RawPacket
from dualhuman_builder.errors import FormatError

_DISK = {28: "the disk is full", 27: "the file-size limit was reached", 122: "the disk quota is exceeded"}


@dataclass
class RepairReport:
    """What :func:`repair_take` did. ``path``: the repaired take; ``original``: where the original
    was kept (None with ``out``); ``messages``: messages copied from the original; ``lost_bytes``:
    bytes that could not be read; ``lost_messages``: per topic, messages that damaged chunks held
    (where their indexes say); ``redecoded``: per topic, samples re-decoded from the raw bytes and
    written; ``recovered``: how channels were recovered; ``problems``: the damage found;
    ``notes``: sources that could not be re-decoded and why."""

    path: Path
    original: Path | None
    messages: int
    lost_bytes: int
    problems: list[str]
    lost_messages: Counter = field(default_factory=Counter)
    redecoded: Counter = field(default_factory=Counter)
    recovered: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _sample_type(r: TakeReader, ch: Channel) -> str | None:
    """The sample class name a decoded-sample channel holds (None for other channels)."""
    if ch.message_encoding != schemas.MESSAGE_ENCODING:
        return None
    sc = r.schemas.get(ch.schema_id)
    if sc is not None and sc.name.startswith(schemas.SCHEMA_PREFIX):
        return sc.name[len(schemas.SCHEMA_PREFIX):]
    return None


def _free_name(path: Path, suffix: str) -> Path:
    """``<stem><suffix>.mcap`` beside ``path``, or ``<stem><suffix>-2.mcap``... when taken."""
    k = 1
    while True:
        cand = path.with_name(f"{path.stem}{suffix}{'' if k == 1 else f'-{k}'}.mcap")
        if not cand.exists():
            return cand
        k += 1


class _Redecoder:
    """Fresh decoders for the raw channels, and the bookkeeping that tells which re-decoded
    samples the take lacks and when each can be written (after every recorded sample of its
    channel that is not later)."""

    def __init__(self, r: TakeReader, recorded: dict[tuple, array]):
        from dualhuman_builder.capture.sources import make_decoder

        meta = {}
        try:
            meta = r.take_meta()
        except FormatError as e:
            self.notes = [f"take metadata unreadable ({e.message}): bindings of re-decoded samples unknown"]
        else:
            self.notes = []
        self.bindings = meta.get("bindings") if isinstance(meta.get("bindings"), dict) else {}
        self.names: list[str] = []
        self.kinds: dict[str, str] = {}
        self.decoders: dict[str, object] = {}
        urls: dict[str, str] = {}
        for s in meta.get("sources") or []:
            if isinstance(s, dict) and isinstance(s.get("name"), str):
                urls.setdefault(s["name"], str(s.get("url", "")))
                self.kinds.setdefault(s["name"], str(s.get("kind", "")))
        for ch in r.channels.values():
            if ch.topic.startswith("raw/"):
                name = ch.metadata.get("source", ch.topic[4:])
                urls.setdefault(name, ch.metadata.get("url", ""))
                self.kinds.setdefault(name, ch.metadata.get("kind", ""))
        self.urls = urls
        for name, url in urls.items():
            self.names.append(name)
            try:
                self.decoders[name] = make_decoder(url)
            except Exception as e:  # noqa: BLE001 - a source that cannot be re-decoded is said, not fatal
                self.notes.append(f"cannot re-decode source {name!r} ({url}): {type(e).__name__}: {e}")
        self.recorded = {k: np.sort(np.frombuffer(v, dtype=np.int64)) for k, v in recorded.items()}
        self.used = {k: np.zeros(len(v), dtype=bool) for k, v in self.recorded.items()}
        self.written: Counter = Counter()
        self.pending: dict[tuple, deque] = {}
        #: (source, type, entity) -> (encoder, output channel id, topic) of the re-decoded samples
        self.outputs: dict[tuple, tuple] = {}
        self.unwritable: Counter = Counter()

    def missing(self, name: str, sample) -> bool:
        """Whether the take lacks ``sample`` of source ``name`` (each recorded sample matches one)."""
        key = (name, type(sample).__name__, entity_of(sample))
        times = self.recorded.get(key)
        t = sample.host_time_ns
        if times is not None:
            used = self.used[key]
            i = int(np.searchsorted(times, t, "left"))
            while i < len(times) and times[i] == t:
                if not used[i]:
                    used[i] = True
                    return False
                i += 1
        return True

    def feed(self, name: str, packet: RawPacket | None) -> list:
        """Samples decoded from ``packet`` of source ``name`` (None: the decoder's last ones)."""
        dec = self.decoders.get(name)
        if dec is None:
            return []
        try:
            return list(dec.feed(packet) if packet is not None else dec.finish())
        except Exception as e:  # noqa: BLE001 - a decoder that fails stops re-decoding its source only
            self.notes.append(f"re-decoding source {name!r} stopped: {type(e).__name__}: {e}")
            self.decoders[name] = None
            return []

    def ready(self, key: tuple, t: int) -> bool:
        """Whether every recorded sample of ``key`` at or before ``t`` has been written."""
        times = self.recorded.get(key)
        return times is None or int(np.searchsorted(times, t, "right")) <= self.written[key]


def repair_take(path: str | Path, out: str | Path | None = None) -> RepairReport:
    """Rewrite ``path`` with everything readable, the samples its raw bytes hold that were never
    written, and a full index (see the module docstring). With ``out``, write there and leave
    ``path`` alone; else the repaired file takes ``path``'s place and the original is kept as
    ``<stem>.damaged.mcap`` (``.damaged-2.mcap``... when that is taken). Raises FormatError if the
    file is already complete and intact with every sample written, TakeWriteError (nothing left
    behind, the original untouched) if the repaired file cannot be written."""
    path = Path(path)
    r = TakeReader(path)
    if out is not None and Path(out).exists():
        raise FormatError("the repair target exists already", path=out, fix="remove it or give another --out")

    # pass 1: every schema and channel, and the host times of the recorded samples per (source, type, entity)
    in_data: set[int] = set()
    recorded: dict[tuple, array] = {}
    keys: dict[int, tuple | None] = {}
    for item in r._items():
        if item[0] == "rec":
            if isinstance(item[1], Channel):
                in_data.add(item[1].id)
            continue
        cid = item[1]
        key = keys.get(cid, ())
        if key == ():
            ch = r.channels.get(cid)
            typ = _sample_type(r, ch) if ch is not None else None
            md = ch.metadata if ch is not None else {}
            key = keys[cid] = None if typ is None else (md.get("source", ""), typ, md.get("entity", ""))
        if key is not None and item[3] < 1 << 63:
            recorded.setdefault(key, array("q")).append(item[3])
    redec = _Redecoder(r, recorded)

    target: Path | None = None
    try:
        if out is None:
            fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".repairing.mcap", dir=path.parent)
            target = Path(name)
            f = os.fdopen(fd, "wb")
        else:
            f = open(out, "xb")
            target = Path(out)
        with f:
            rep = _write(r, redec, in_data, keys, f)
            f.flush()
            os.fsync(f.fileno())
        if r.scan.complete and not r.problems and not rep.redecoded and not rep.recovered:
            raise FormatError("the take is complete and intact, every sample written; nothing to repair", path=path)
        rep.path = target
        if out is None:
            rep.original = _free_name(path, ".damaged")
            os.replace(path, rep.original)
            try:
                os.replace(target, path)
            except OSError:
                os.replace(rep.original, path)
                raise
            rep.path = path
    except OSError as e:
        if target is not None:
            _remove(target)
        where = Path(out).parent if out is not None else path.parent
        if e.errno in _DISK:
            fix = (f"free space on {where} (the repaired take is about {r.scan.size:,} bytes) or write it elsewhere "
                   f"with --out; {path} is unchanged")  # fmt: skip
        else:
            fix = f"check that {where} exists and is writable, or write elsewhere with --out; {path} is unchanged"
        raise TakeWriteError(f"repairing the take stopped: {_DISK.get(e.errno, e.strerror or str(e))}",
                             path=out if out is not None else path, fix=fix) from e  # fmt: skip
    except BaseException:
        if target is not None:
            _remove(target)
        raise
    return rep


def _remove(p: Path) -> None:
    try:
        p.unlink()
    except OSError:
        pass


def _write(r: TakeReader, redec: _Redecoder, in_data: set[int], keys: dict[int, tuple | None], f) -> RepairReport:
    """Pass 2: the repaired take into the open file ``f``."""
    from mcap.writer import CompressionType, Writer

    w = Writer(f, compression=CompressionType.LZ4)
    w.start(PROFILE, "dualhuman_builder")
    rep = RepairReport(Path(), None, 0, 0, [])
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    new_schemas: dict[tuple[str, str], int] = {}
    sources = redec.names

    def put_schema(sc: Schema) -> int:
        key = (sc.name, bytes(sc.data).decode("utf-8", "replace"))
        if key not in new_schemas:
            new_schemas[key] = w.register_schema(sc.name, sc.encoding, bytes(sc.data))
        return new_schemas[key]

    def put_channel(ch: Channel) -> int:
        if ch.id in channel_ids:
            return channel_ids[ch.id]
        topic, sid = ch.topic, 0
        if ch.schema_id:
            sc = r.schemas.get(ch.schema_id)
            if sc is None:
                topic = f"lost/{ch.topic}"
                rep.recovered.append(f"{ch.topic}: its schema is lost; its messages kept on {topic}")
            else:
                sid = schema_ids.setdefault(ch.schema_id, put_schema(sc))
        channel_ids[ch.id] = w.register_channel(topic, ch.message_encoding, sid, dict(ch.metadata))
        return channel_ids[ch.id]

    inferred: dict[int, Channel] = {}

    def lost_channel(cid: int) -> int:
        """An output channel for messages on channel ``cid``, whose record is lost everywhere."""
        ch = None
        if 1 <= cid <= len(sources):  # the recorder registers one raw channel per source first, in order
            name = sources[cid - 1]
            if not any(c.topic == f"raw/{name}" for c in r.channels.values()):
                meta = {"url": redec.urls.get(name, ""), "kind": redec.kinds.get(name, ""), "source": name}
                ch = Channel(id=cid, topic=f"raw/{name}", message_encoding=RAW_ENCODING, schema_id=0, metadata=meta)
                inferred[cid] = ch
                rep.recovered.append(f"channel {cid}: its record is lost; taken as raw/{name} "
                                     f"(source {cid} of the take)")  # fmt: skip
        if ch is None:
            ch = Channel(id=cid, topic=f"lost/{cid}", message_encoding="", schema_id=0,
                         metadata={"lost_channel": str(cid)})  # fmt: skip
            rep.recovered.append(f"channel {cid}: its record is lost; its messages kept on lost/{cid}")
        channel_ids[cid] = w.register_channel(ch.topic, ch.message_encoding, 0, dict(ch.metadata))
        return channel_ids[cid]

    recovered = sorted(set(r.channels) - in_data)
    if recovered:
        topics = ", ".join(r.channels[c].topic for c in recovered[:6]) + (", ..." if len(recovered) > 6 else "")
        rep.recovered.append(f"{len(recovered)} channel records taken from the summary section ({topics})")
    for ch in sorted(r.channels.values(), key=lambda c: c.id):
        put_channel(ch)

    # re-decoded samples go on the recorded channel of their (source, type, entity) when its schema is theirs
    out_of_key: dict[tuple, tuple[int, int]] = {}  # (source, type, entity) -> (its channel id, output id)
    for cid, key in keys.items():
        ch = r.channels.get(cid)
        if key is not None and ch is not None and cid in channel_ids:
            out_of_key.setdefault(key, (cid, channel_ids[cid]))

    def flush(key: tuple, final: bool = False) -> None:
        q = redec.pending.get(key)
        while q and (final or redec.ready(key, q[0][0])):
            t, payload, ocid, topic = q.popleft()
            w.add_message(ocid, t, payload, t)
            rep.redecoded[topic] += 1

    def add_redecoded(name: str, samples: list) -> None:
        for s in samples:
            key = (name, type(s).__name__, entity_of(s))
            t = getattr(s, "host_time_ns", None)
            if not isinstance(t, int) or not 0 <= t < 1 << 63:
                redec.unwritable[key] += 1
                continue
            if not redec.missing(name, s):
                continue
            try:
                if key not in redec.outputs:
                    layout = schemas.layout_for(s)
                    redec.outputs[key] = (schemas.make_encoder(layout), *_declare(key, layout))
                encode, ocid, topic = redec.outputs[key]
                payload = encode(s)
            except OSError:
                raise
            except Exception:  # noqa: BLE001 - a sample the take format cannot hold (a value out of range): counted
                redec.unwritable[key] += 1
                continue
            redec.pending.setdefault(key, deque()).append((t, payload, ocid, topic))
            flush(key)

    def _declare(key: tuple, layout: schemas.Layout) -> tuple[int, str]:
        got = out_of_key.get(key)
        if got is not None:
            sc = r.schemas.get(r.channels[got[0]].schema_id)
            if sc is not None and sc.name == layout.schema_name and bytes(sc.data) == layout.definition.encode():
                return got[1], r.channels[got[0]].topic
        name, type_name, entity = key
        sid = put_schema(Schema(id=0, name=layout.schema_name, encoding=schemas.SCHEMA_ENCODING,
                                data=layout.definition.encode()))  # fmt: skip
        meta = {"source": name, "entity": entity, "kind": redec.kinds.get(name, "")}
        meta.update(binding(redec.bindings, name, entity))
        topic = f"{name}/{entity}/{type_name}"
        return w.register_channel(topic, schemas.MESSAGE_ENCODING, sid, meta), topic

    for item in r._items():
        if item[0] == "msg":
            _, cid, seq, lt, pt, data = item
            ocid = channel_ids.get(cid)
            if ocid is None:
                ocid = lost_channel(cid)
            w.add_message(ocid, lt, bytes(data), pt, seq)
            rep.messages += 1
            key = keys.get(cid)
            if key is not None:
                redec.written[key] += 1
                flush(key)
            ch = r.channels.get(cid) or inferred.get(cid)
            if ch is not None and ch.topic.startswith("raw/") and ch.message_encoding == RAW_ENCODING:
                name = ch.metadata.get("source", ch.topic[4:])
                if name in redec.decoders:
                    add_redecoded(name, redec.feed(name, RawPacket(lt, bytes(data))))
            continue
        rec = item[1]
        if isinstance(rec, (Schema, Channel)):
            if isinstance(rec, Channel) and rec.id not in channel_ids:
                put_channel(rec)
        elif isinstance(rec, Metadata):
            w.add_metadata(rec.name, dict(rec.metadata))
        elif isinstance(rec, Attachment):
            w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
    for name in list(redec.decoders):
        add_redecoded(name, redec.feed(name, None))
    for key in list(redec.pending):
        flush(key, final=True)
    rep.lost_bytes = r.lost_bytes
    rep.lost_messages = r.lost_per_topic()
    rep.problems = list(r.problems)
    rep.notes = list(redec.notes)
    for (name, type_name, entity), n in sorted(redec.unwritable.items()):
        rep.notes.append(f"{n} re-decoded {type_name} samples of {name} {entity} have values a take cannot hold "
                         "(a host time or counter out of range); not written")  # fmt: skip
    if rep.redecoded:
        rep.notes.append(f"{sum(rep.redecoded.values())} samples re-decoded from the raw bytes and written "
                         "(the take did not hold them)")  # fmt: skip
    w.add_metadata("repair", {"original_size": str(r.scan.size), "lost_bytes": str(rep.lost_bytes),
                              "lost_messages": json.dumps(dict(rep.lost_messages)),
                              "redecoded": json.dumps(dict(rep.redecoded)), "recovered": json.dumps(rep.recovered),
                              "problems": json.dumps(rep.problems)})  # fmt: skip
    w.finish()
    return rep
