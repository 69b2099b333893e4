"""The recorder: every source of a rig into one take file, with a live status, surviving bad input.

One reader thread per source calls :meth:`Source.read` and hands the raw packets to the writer
thread (the caller's), which writes each packet's bytes, decodes it with the source's decoder and
writes the samples (:class:`~dualhuman_builder.capture.log.writer.TakeWriter`). Reading never waits
for the disk: a source's kernel buffer and the queue absorb bursts while a chunk is compressed.

A take ends when its duration is reached, when :meth:`Recorder.stop` is called (Ctrl-C in the
CLI), when ``until()`` says so (a simulated studio that finished playing), or on a failure:

* a device lost mid-take (unplugged serial adapter, CAN bus down: :class:`SourceLost`) — the
  take stops, everything received before is decoded and written, the error names the device;
* the disk full or the file-size limit reached — the take stops, the file keeps every complete
  chunk (``dualhuman log repair`` adds the index), the error says so.

In every case the packets already received are written (the queue is drained, the decoders
flushed) before the file is closed.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from dualhuman_builder.capture.log.writer import TakeWriteError, TakeWriter
from dualhuman_builder.capture.sources import Source, SourceError, SourceLost, now_ns
from dualhuman_builder.rig import RigActor

#: Counters that mean data went missing, and those that mean data arrived damaged.
LOSS_COUNTERS = ("lost", "kernel_drops", "incomplete", "dropped_bytes")
ERROR_COUNTERS = ("truncated", "bad_header", "bad_payload", "bad_checksum", "bad_length", "bad_magic", "bad_version",
                  "bad_pose", "unknown_id", "rejected_senders", "duplicate", "out_of_order")


def rig_bindings(actors: Sequence[RigActor]) -> dict[str, dict[str, dict[str, str]]]:
    """Entity bindings for :class:`TakeWriter`: ``mvn/<character>`` of the actor's source, and each
    tracker serial (``vive/<serial>``, on any source) with the segment it is strapped to."""
    out: dict[str, dict[str, dict[str, str]]] = {}
    for a in actors:
        if a.source is not None and a.character is not None:
            out.setdefault(a.source, {})[f"mvn/{a.character}"] = {"actor": a.name}
        for serial, segment in a.trackers.items():
            out.setdefault("*", {})[f"vive/{serial}"] = {"actor": a.name, "segment": segment}
    return out


@dataclass
class SourceStatus:
    name: str
    kind: str
    url: str
    packets: int
    samples: int
    packet_rate: float
    sample_rate: float
    loss: int
    errors: int
    last_sample_age_s: float | None
    counters: dict[str, int]
    entities: dict[str, dict[str, Any]]


@dataclass
class ActorStatus:
    name: str
    suit: str  # "live", "stale", "absent", or "-" (no suit bound)
    trackers_live: int
    trackers_total: int


@dataclass
class LiveStatus:
    """What the live display shows: elapsed seconds, per source and per actor."""

    take: str
    elapsed_s: float
    messages: int
    sources: list[SourceStatus]
    actors: list[ActorStatus]


@dataclass
class TakeResult:
    """How a take ended: ``reason`` (``duration``, ``stopped``, ``finished``, ``source-lost``,
    ``write-failed``, ``decode-failed``), ``error`` (the message when it failed), counts per topic
    and source."""

    path: Path
    take: str
    reason: str
    error: str | None
    duration_s: float
    start_utc: str
    messages: int
    samples_per_topic: Counter
    source_stats: dict[str, dict[str, int]]
    events: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.error is None


class Recorder:
    """Records ``sources`` (``[(name, Source), ...]``, opened) into ``path`` as take ``take``.

    ``actors``: the rig's actors (bindings and the per-actor live status); ``rig_text``: stored as
    metadata; ``foxglove_hz``, ``flush_s``, ``chunk_size``: see :class:`TakeWriter`; ``gather_s``:
    how long a reader lets packets accumulate before handing them to the writer (default 10 ms;
    the source's buffers must hold that much: a UDP socket holds 8 MiB, a pty 4 KiB or more);
    ``decode``: ``"process"`` (default) decodes in a :class:`~.decoding.DecodeProcess` beside this
    one, so reading and raw writing never wait for decoding; ``"inline"`` decodes in the writer
    thread (no extra process; tops out at a few times real time)."""

    def __init__(self, path: str | Path, *, take: str, sources: Sequence[tuple[str, Source]],
                 actors: Sequence[RigActor] = (), rig_text: str | None = None, foxglove_hz: float = 60.0,
                 flush_s: float = 1.0, chunk_size: int = 1 << 20, extra_meta: dict[str, str] | None = None,
                 gather_s: float = 0.01, decode: str = "process"):  # fmt: skip
        if not sources:
            raise SourceError("nothing to record: no sources", fix="give --rig or at least one --source")
        names = [n for n, _ in sources]
        if len(set(names)) != len(names):
            raise SourceError(f"source names repeat: {names}", fix="name each source once")
        self.take = take
        #: Seconds a reader thread lets packets accumulate after the first before handing them over.
        self.gather_s = float(gather_s)
        self.sources = list(sources)
        self.actors = list(actors)
        for _, src in self.sources:
            if src.decoder is None:
                src.decoder = src.make_decoder(src.url)
        self.writer = TakeWriter(path, take=take, sources=[(n, s.url, s.kind) for n, s in self.sources],
                                 bindings=rig_bindings(self.actors), rig_text=rig_text, chunk_size=chunk_size,
                                 flush_s=flush_s, foxglove_hz=foxglove_hz, extra_meta=extra_meta)  # fmt: skip
        self._stop = threading.Event()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._threads: list[threading.Thread] = []
        #: CPU seconds each reader thread used (filled as they end): where a take's CPU goes.
        self.thread_cpu_s: dict[str, float] = {}
        self._packets = Counter()
        self._samples = Counter()
        self._last_sample_ns: dict[int, int] = {}
        self._rates: dict[int, tuple[float, int, int]] = {}
        self.events: list[dict[str, Any]] = []
        self.started = time.monotonic()
        if decode not in ("process", "inline"):
            raise ValueError(f"decode must be 'process' or 'inline', got {decode!r}")
        self._dproc = None
        if decode == "process":
            from dualhuman_builder.capture.decoding import DecodeProcess

            self._dproc = DecodeProcess([s.url for _, s in self.sources], names, self.writer.bindings, foxglove_hz)

    @property
    def path(self) -> Path:
        return self.writer.path

    def stop(self) -> None:
        """Ask the take to end (thread-safe); :meth:`run` returns after writing what it has."""
        self._stop.set()

    # ------------------------------------------------------------------ threads
    def _reader(self, index: int, src: Source) -> None:
        try:
            self._read_loop(index, src)
        finally:
            self.thread_cpu_s[f"read-{self.sources[index][0]}"] = time.thread_time()

    def _read_loop(self, index: int, src: Source) -> None:
        q = self._queue
        gather = self.gather_s
        while not self._stop.is_set():
            try:
                packets = src.read(0.05)
                if packets and gather > 0:
                    # let more arrive (the kernel, pty or bus buffers them) and hand over one batch:
                    # fewer thread wake-ups and queue items per packet, at 1x and at 20x alike
                    time.sleep(gather)
                    more = src.read(0.0)
                    while more:
                        packets += more
                        more = src.read(0.0) if len(more) >= 64 else None
            except SourceLost as e:
                q.put((index, e))
                return
            except Exception as e:  # noqa: BLE001 - a source bug must end the take cleanly, not hang it
                q.put((index, SourceLost(f"{type(e).__name__}: {e}")))
                return
            if packets:
                q.put((index, packets))

    def _process(self, index: int, packets) -> None:
        w = self.writer
        if self._dproc is not None:
            add_raw = w.add_raw
            for p in packets:
                add_raw(index, p)
            self._packets[index] += len(packets)
            self._dproc.submit(index, packets)
            return
        src = self.sources[index][1]
        dec = src.decoder
        add_raw, add_sample = w.add_raw, w.add_sample
        n_samples = 0
        for p in packets:
            add_raw(index, p)
            for s in dec.feed(p):
                add_sample(index, s)
                n_samples += 1
        if n_samples:
            self._last_sample_ns[index] = packets[-1].host_time_ns
        self._packets[index] += len(packets)
        self._samples[index] += n_samples
        self._drain_events(index)

    def _decoded(self, msg: tuple) -> None:
        """Write what the decoding process sent back: ``("items", source, items, events)``."""
        if msg[0] != "items":
            return
        _, index, items, events = msg
        add = self.writer.add_item
        n = 0
        last = None
        for it in items:
            add(it)
            if it[0] == "msg":
                n += 1
                last = it[2]
        if n:
            self._samples[index] += n
            self._last_sample_ns[index] = last
        self._write_events(index, events)

    def _drain_events(self, index: int) -> None:
        self._write_events(index, self.sources[index][1].decoder.pop_events())

    def _write_events(self, index: int, events) -> None:
        name = self.sources[index][0]
        for ev in events:
            self.writer.add_event(name, ev)
            self.events.append({"source": name, "kind": ev.kind, "entity": ev.entity, "message": ev.message,
                                "host_time_ns": ev.host_time_ns})  # fmt: skip

    # ------------------------------------------------------------------ status
    def status(self) -> LiveStatus:
        now = now_ns()
        t = time.monotonic()
        out = []
        entity_live: dict[str, dict[str, Any]] = {}
        for i, (name, src) in enumerate(self.sources):
            stats = self._source_stats(i)
            t0, p0, s0 = self._rates.get(i, (self.started, 0, 0))
            dt = max(t - t0, 1e-6)
            prate, srate = (self._packets[i] - p0) / dt, (self._samples[i] - s0) / dt
            if t - t0 >= 1.0:
                self._rates[i] = (t, self._packets[i], self._samples[i])
            if self._dproc is not None:
                ents = self._dproc.status[i] if i < len(self._dproc.status) else {}
            else:
                ents = src.decoder.status(now) if src.decoder is not None else {}
            for e, st in ents.items():
                entity_live[f"{name}|{e}"] = st
            last = self._last_sample_ns.get(i)
            out.append(SourceStatus(name, src.kind, src.url, self._packets[i], self._samples[i], prate, srate,
                                    sum(stats.get(k, 0) for k in LOSS_COUNTERS),
                                    sum(stats.get(k, 0) for k in ERROR_COUNTERS),
                                    None if last is None else (now - last) / 1e9, stats, ents))  # fmt: skip
        actors = []
        for a in self.actors:
            suit = "-"
            if a.source is not None and a.character is not None:
                st = entity_live.get(f"{a.source}|mvn/{a.character}")
                suit = "absent" if st is None else ("live" if st.get("live") else "stale")
            live = 0
            for serial in a.trackers:
                live += any(st.get("live") for k, st in entity_live.items() if k.endswith(f"|vive/{serial}"))
            actors.append(ActorStatus(a.name, suit, live, len(a.trackers)))
        return LiveStatus(self.take, t - self.started, self.writer.messages, out, actors)

    def _source_stats(self, index: int) -> dict[str, int]:
        st = dict(self.sources[index][1].stats())
        if self._dproc is not None and index < len(self._dproc.counters):
            st.update(self._dproc.counters[index])
        return st

    def _stats(self) -> dict[str, dict[str, int]]:
        return {name: {k: int(v) for k, v in self._source_stats(i).items()} for i, (name, _) in enumerate(self.sources)}

    # ------------------------------------------------------------------ run
    def run(self, duration: float | None = None, *, until: Callable[[], bool] | None = None,
            on_status: Callable[[LiveStatus], None] | None = None, status_every: float = 0.25) -> TakeResult:  # fmt: skip
        """Record until the duration, :meth:`stop`, ``until()`` or a failure; returns how it ended."""
        self.started = time.monotonic()
        for i, (name, src) in enumerate(self.sources):
            th = threading.Thread(target=self._reader, args=(i, src), name=f"read-{name}", daemon=True)
            th.start()
            self._threads.append(th)
        reason, error = "stopped", None
        next_status = next_record = self.started
        try:
            while True:
                now = time.monotonic()
                if duration is not None and now - self.started >= duration:
                    reason = "duration"
                    break
                if self._stop.is_set():
                    break
                if until is not None and until():
                    reason = "finished"
                    break
                try:
                    index, item = self._queue.get(timeout=0.05)
                except queue.Empty:
                    item = None
                if isinstance(item, SourceLost):
                    name = self.sources[index][0]
                    reason, error = "source-lost", f"source {name!r} ({self.sources[index][1].url}) was lost: {item.message}"
                    break
                if item is not None:
                    self._process(index, item)
                if self._dproc is not None:
                    for msg in self._dproc.poll():
                        self._decoded(msg)
                self.writer.maybe_flush()
                if now >= next_record:
                    self.writer.add_status(now_ns(), self._stats())
                    next_record = now + 1.0
                if on_status is not None and now >= next_status:
                    on_status(self.status())
                    next_status = now + status_every
        except KeyboardInterrupt:
            reason = "stopped"
        except TakeWriteError as e:
            reason, error = "write-failed", e.message
        except RuntimeError as e:  # the decoding process failed: raw packets are safe, decoding stops
            reason, error = "decode-failed", str(e)
        finally:
            self._stop.set()
            for th in self._threads:
                th.join(timeout=2.0)
        recorded_s = time.monotonic() - self.started  # decoding may still catch up below; not part of the take
        if error is None or reason == "source-lost":
            try:
                self._drain()
            except TakeWriteError as e:
                reason, error = "write-failed", e.message
            except RuntimeError as e:
                reason, error = "decode-failed", str(e)
        if self._dproc is not None:
            self._dproc.close()
        if on_status is not None:
            on_status(self.status())  # the final state, decoding complete
        stats = self._stats()
        result = TakeResult(self.writer.path, self.take, reason, error, recorded_s,
                            self.writer.take_start_utc, self.writer.messages, self.writer.samples_per_topic(), stats,
                            self.events)  # fmt: skip
        try:
            self.writer.close({"sources": stats, "reason": reason, "error": error or "",
                               "duration_s": result.duration_s})  # fmt: skip
        except TakeWriteError as e:
            result.reason, result.error = "write-failed", e.message
        return result

    def _drain(self) -> None:
        """Write what the reader threads handed over but was not written yet, then what the
        decoders still hold."""
        while True:
            try:
                index, item = self._queue.get_nowait()
            except queue.Empty:
                break
            if not isinstance(item, BaseException):
                self._process(index, item)
        if self._dproc is not None:
            self._dproc.finish(self._decoded)
            return
        for i, (_, src) in enumerate(self.sources):
            for s in src.decoder.finish():
                self.writer.add_sample(i, s)
                self._samples[i] += 1
            self._drain_events(i)

    def close(self) -> None:
        """Close the sources (the recorder does not own them otherwise)."""
        for _, src in self.sources:
            try:
                src.close()
            except Exception:  # noqa: BLE001 - closing must not mask the take's outcome
                pass
