"""The recorder: every source of a rig into one take file, with a live status, surviving bad input.

One reader thread per source drains its transport and hands the raw packets, and the events the
transport raised (a sender not in ``allow=``, a receive buffer smaller than asked), to the writer
thread (the caller's). The writer writes each packet's bytes, has it decoded — in a decoding process
beside this one by default (:mod:`.decoding`), or inline — and writes the samples
(:class:`~dualhuman_builder.capture.log.writer.TakeWriter`). Reading never waits for the disk or
the decoder: the readers start as the recorder is made, and between two drains a reader sleeps at
most a quarter of the time its source's buffer (a socket's granted receive buffer, a pty's 4 KiB)
takes to fill at the rate it last saw, so batching never overflows a buffer.

A take ends when its duration is reached, when :meth:`Recorder.stop` is called (Ctrl-C in the
CLI), when ``until()`` says so (a simulated studio that finished playing), when every source is
gone, or when the file can no longer be written. One part failing does not end it:

* a device lost mid-take (unplugged serial adapter, CAN bus down: :class:`SourceLost`, or its
  reader failing) ends that source — an event ``source-lost`` with the reason — and the others go
  on recording; only when every source is gone does the take stop (reason ``source-lost``);
* one source's decoding failing ends its decoding (event ``decoding-failed``); its raw packets are
  still recorded;
* the decoding process failing (or killed) ends decoding; every raw packet is still recorded to
  the end of the take, and ``dualhuman log repair`` re-decodes the samples from them;
* the disk full or the file-size limit reached stops the take; the file keeps every complete
  chunk (``dualhuman log repair`` adds the index).

In every case the packets already received are written (the queue is drained, the decoders
flushed) before the file is closed, and what failed is in :class:`TakeResult` (``error``,
``ended``, ``decode_failed``, ``fix``), in the take's ``events`` and in its final ``stats``
metadata. The kernel's drops of a UDP source (its ``kernel_drops`` counter) are reported as
``kernel-drops`` events too.
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
from dualhuman_builder.capture.sources import Source, SourceError, SourceEvent, SourceLost, now_ns
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.rig import RigActor

#: Counters that mean data went missing, and those that mean data arrived damaged.
LOSS_COUNTERS = ("lost", "kernel_drops", "incomplete", "dropped_bytes")
ERROR_COUNTERS = ("truncated", "bad_header", "bad_payload", "bad_checksum", "bad_length", "bad_magic", "bad_version",
                  "bad_pose", "unknown_id", "rejected_senders", "duplicate", "out_of_order", "oversize")
#: Bytes a source's buffer holds when the source does not say (``buffer_bytes``): a pty's line
#: discipline holds 4 KiB, the smallest buffer of the transports read here.
DEFAULT_BUFFER_BYTES = 4096
#: Share of a source's buffer a reader lets fill between two drains (room for a 4x burst).
BUFFER_SHARE = 0.25
#: A reader's first sleep between drains (s); it doubles per batch up to ``gather_s`` while the
#: buffer allows.
FIRST_NAP_S = 0.001
#: Per batch, the remembered arrival rate decays by this factor (a burst is remembered a few batches).
RATE_DECAY = 0.8
#: Most packets a reader hands to the writer at once.
MAX_HANDOVER = 8192
#: Seconds between two ``kernel-drops`` events of one source; drops in between go into the next one.
DROP_EVENT_EVERY_S = 10.0
#: Source name of the events about decoding as a whole (the decoding process failing).
ALL_SOURCES = "*"
#: Event kind of a source's decoding ending (here or in the decoding process), or of all decoding.
DECODING_FAILED = "decoding-failed"


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
    """One source in the live status; ``state``: ``recording``, ``lost`` (the device went away:
    nothing more is read) or ``raw only`` (its decoding failed: raw packets are still recorded)."""

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
    state: str = "recording"


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
    """How a take ended: ``reason`` (``duration``, ``stopped``, ``finished``, ``source-lost``: every
    source gone, ``write-failed``), ``error`` (what failed, None when nothing did: a source lost or
    decoding failed while the take went on is an error too), counts per topic and source, the
    events. ``ended``: source name -> why it was lost; ``decode_failed``: source name (``"*"``:
    the decoding process, every source) -> why its decoding ended; ``fix``: how to recover."""

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
    ended: dict[str, str] = field(default_factory=dict)
    decode_failed: dict[str, str] = field(default_factory=dict)
    fix: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def _why(e: BaseException) -> str:
    """One line saying what ``e`` was (no traceback)."""
    if isinstance(e, DualhumanError):
        return e.message
    return f"{type(e).__name__}: {e}"


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return lines[-1] if lines else "unknown failure"


class Recorder:
    """Records ``sources`` (``[(name, Source), ...]``, opened) into ``path`` as take ``take``.

    ``actors``: the rig's actors (bindings and the per-actor live status); ``rig_text``: stored as
    metadata; ``foxglove_hz``, ``flush_s``, ``chunk_size``: see :class:`TakeWriter`; ``gather_s``:
    the longest a reader lets packets accumulate before draining its source and handing them over
    (default 10 ms; shorter whenever the source's buffer would fill sooner — a source may say how
    much it holds with ``buffer_bytes`` and ``packet_overhead``, bytes each queued packet costs
    beyond its data; else :data:`DEFAULT_BUFFER_BYTES`); ``decode``: ``"process"`` (default)
    decodes in a :class:`~.decoding.DecodeProcess` beside this one, so reading and raw writing never
    wait for decoding; ``"inline"`` decodes in the writer thread (no extra process; tops out at a
    few times real time).

    The readers start here (so that nothing waits in a kernel buffer while the take is set up);
    :meth:`run` records the take once, :meth:`close` closes the sources."""

    def __init__(self, path: str | Path, *, take: str, sources: Sequence[tuple[str, Source]],
                 actors: Sequence[RigActor] = (), rig_text: str | None = None, foxglove_hz: float = 60.0,
                 flush_s: float = 1.0, chunk_size: int = 1 << 20, extra_meta: dict[str, str] | None = None,
                 gather_s: float = 0.01, decode: str = "process"):  # fmt: skip
        if not sources:
            raise SourceError("nothing to record: no sources", fix="give --rig or at least one --source")
        names = [n for n, _ in sources]
        if len(set(names)) != len(names):
            raise SourceError(f"source names repeat: {names}", fix="name each source once")
        if decode not in ("process", "inline"):
            raise ValueError(f"decode must be 'process' or 'inline', got {decode!r}")
        self.take = take
        #: Longest seconds a reader thread lets packets accumulate before draining its source.
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
        #: Sources lost mid-take (index -> why) and sources whose decoding failed (index -> why).
        self._ended: dict[int, str] = {}
        self._undecoded: dict[int, str] = {}
        #: Why the decoding process failed (None while it works), and its traceback.
        self._decode_error: str | None = None
        self._decode_detail: str | None = None
        self._drops_seen: dict[int, int] = {}
        self._drops_event_at: dict[int, float] = {}
        self.started = time.monotonic()
        self._inline = decode == "inline"
        self._dproc = None
        for i, (name, src) in enumerate(self.sources):  # reading first: spawning the decoder takes a while
            th = threading.Thread(target=self._reader, args=(i, src), name=f"read-{name}", daemon=True)
            th.start()
            self._threads.append(th)
        if not self._inline:
            from dualhuman_builder.capture.decoding import DecodeProcess

            try:
                self._dproc = DecodeProcess([s.url for _, s in self.sources], names, self.writer.bindings,
                                            foxglove_hz)  # fmt: skip
            except BaseException:
                self._stop.set()
                raise

    @property
    def path(self) -> Path:
        return self.writer.path

    def stop(self) -> None:
        """Ask the take to end (thread-safe); :meth:`run` returns after writing what it has."""
        self._stop.set()

    # ------------------------------------------------------------------ readers
    def _reader(self, index: int, src: Source) -> None:
        try:
            self._read_loop(index, src)
        except SourceLost as e:
            self._queue.put((index, None, e))
        except Exception as e:  # noqa: BLE001 - a source bug ends that source, never the take
            self._queue.put((index, None, SourceLost(f"its reader failed ({_why(e)})")))
        finally:
            self.thread_cpu_s[f"read-{self.sources[index][0]}"] = time.thread_time()

    def _read_loop(self, index: int, src: Source) -> None:
        """Drain ``src`` until the take ends; hand over ``(index, packets, events)``.

        After the first packet of a batch, sleep (so that one wake-up and one queue item carry many
        packets), then drain everything that arrived. The sleep is at most ``gather_s``, and at most
        :data:`BUFFER_SHARE` of the time the source's buffer takes to fill at the highest recent
        arrival rate, so that a small buffer or a fast stream is drained before it overflows."""
        put = self._queue.put
        stopped = self._stop.is_set
        read = src.read
        mono, sleep = time.monotonic, time.sleep
        gather = self.gather_s
        room = BUFFER_SHARE * float(getattr(src, "buffer_bytes", None) or DEFAULT_BUFFER_BYTES)
        overhead = int(getattr(src, "packet_overhead", 0) or 0)
        transport_events = getattr(src, "pop_events", None)
        # with decoding in its own process this decoder is never fed: what it holds, the transport raised
        own = None if self._inline else src.decoder
        rate = 0.0  # bytes per second the buffer fills at (highest recent)
        nap = min(gather, FIRST_NAP_S)
        while not stopped():
            packets = read(0.05)
            if packets and gather > 0:
                first = len(packets)
                t0 = mono()
                if nap > 0:
                    sleep(nap)
                while len(packets) < MAX_HANDOVER:
                    more = read(0.0)
                    if not more:
                        break
                    packets += more
                came = len(packets) - first
                seen = (sum([len(p.data) for p in packets[first:]]) + overhead * came) / max(mono() - t0, 1e-4)
                rate = max(seen, rate * RATE_DECAY)
                nap = min(gather, 2 * max(nap, FIRST_NAP_S / 2), room / rate if rate > 0 else gather)
            events = transport_events() if transport_events is not None else []
            if own is not None and own.events:
                events = events + own.pop_events()
            if packets or events:
                put((index, packets, events))

    # ------------------------------------------------------------------ the writer's side
    def _handle(self, index: int, packets, extra) -> None:
        """One item from a reader: packets and transport events, or ``packets=None`` and the
        :class:`SourceLost` that ended it."""
        if packets is None:
            self._source_lost(index, extra)
            return
        if packets:
            self._process(index, packets)
        if extra:
            self._write_events(index, extra)

    def _process(self, index: int, packets) -> None:
        w = self.writer
        add_raw = w.add_raw
        if not self._inline or index in self._undecoded:
            for p in packets:
                add_raw(index, p)
            self._packets[index] += len(packets)
            if self._dproc is not None and self._decode_error is None:
                self._dproc.submit(index, packets)  # a source failed there is only counted (undecoded_packets)
            return
        dec = self.sources[index][1].decoder
        add_sample = w.add_sample
        n_samples = 0
        done = 0
        try:
            for p in packets:
                add_raw(index, p)
                done += 1
                for s in dec.feed(p):
                    add_sample(index, s)
                    n_samples += 1
        except TakeWriteError:
            raise
        except Exception as e:  # noqa: BLE001 - one source's decoding failing must not stop the others
            self._decoding_failed(index, _why(e))
            for p in packets[done:]:
                add_raw(index, p)
        if n_samples:
            self._last_sample_ns[index] = packets[-1].host_time_ns
        self._packets[index] += len(packets)
        self._samples[index] += n_samples
        self._drain_events(index)

    def _decoded(self, msg: tuple) -> None:
        """Write what the decoding process sent back: ``("items", source, items, events)``; a
        ``decoding-failed`` event among them means that source's decoding ended there."""
        if msg[0] != "items":
            return
        _, index, items, events = msg
        for ev in events:
            if ev.kind == DECODING_FAILED and index not in self._undecoded:
                self._undecoded[index] = ev.message
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

    def _poll_decoder(self) -> None:
        """Write what the decoding process finished; a failure of the process ends decoding."""
        if self._dproc is None or self._decode_error is not None:
            return
        try:
            for msg in self._dproc.poll():
                self._decoded(msg)
        except RuntimeError:
            self._decoder_lost(self._decoder_exit(), self._dproc.error)

    def _check_decoder_alive(self) -> None:
        if self._dproc is None or self._decode_error is not None or self._dproc.proc.is_alive():
            return
        self._poll_decoder()  # what it sent before it ended
        self._decoder_lost(self._decoder_exit())

    def _decoder_exit(self, fallback: str = "the decoding process failed") -> str:
        """Why the decoding process ended: the last line of its traceback, or how it exited."""
        if self._dproc.error:
            return _last_line(self._dproc.error)
        code = self._dproc.proc.exitcode
        if code is None:
            return fallback
        how = f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
        return f"the decoding process {how}"

    def _drain_events(self, index: int) -> None:
        try:
            events = self.sources[index][1].decoder.pop_events()
        except Exception:  # noqa: BLE001 - a broken decoder's events are lost, not the take
            return
        self._write_events(index, events)

    def _write_events(self, index: int, events) -> None:
        self._write_named_events(self.sources[index][0], events)

    def _write_named_events(self, name: str, events) -> None:
        for ev in events:
            self.writer.add_event(name, ev)
            self.events.append({"source": name, "kind": ev.kind, "entity": ev.entity, "message": ev.message,
                                "host_time_ns": ev.host_time_ns})  # fmt: skip

    def _event(self, index: int | None, kind: str, message: str) -> None:
        """An event of the recorder itself about source ``index`` (None: about decoding as a whole)."""
        name = ALL_SOURCES if index is None else self.sources[index][0]
        entity = "decoding" if index is None else name
        self._write_named_events(name, [SourceEvent(now_ns(), kind, entity, message)])

    def _after(self) -> str:
        return f"after {time.monotonic() - self.started:.1f} s"

    def _source_lost(self, index: int, e: BaseException) -> None:
        if index in self._ended:
            return
        why = _why(e)
        self._ended[index] = why
        others = len(self.sources) - len(self._ended)
        self._event(index, "source-lost", f"{self.sources[index][1].url} was lost {self._after()}: {why}; "
                                          + (f"{others} other source(s) go on recording" if others else
                                             "no source is left"))  # fmt: skip

    def _decoding_failed(self, index: int, why: str) -> None:
        if index in self._undecoded:
            return
        self._undecoded[index] = why
        self._event(index, DECODING_FAILED, f"decoding source {self.sources[index][0]} stopped {self._after()} "
                                            f"({why}); its raw packets are still recorded and `dualhuman log repair` "
                                            f"re-decodes them")  # fmt: skip

    def _decoder_lost(self, why: str, detail: str | None = None) -> None:
        if self._decode_error is not None:
            return
        self._decode_error, self._decode_detail = why, detail
        self._event(None, DECODING_FAILED, f"decoding stopped {self._after()} ({why}); every raw packet is still "
                                           f"recorded and `dualhuman log repair` re-decodes the samples")  # fmt: skip

    def _check_drops(self, stats: dict[str, dict[str, int]], final: bool = False) -> None:
        """A ``kernel-drops`` event when a source's ``kernel_drops`` rose (at most one per
        :data:`DROP_EVENT_EVERY_S` and source; at the end, whatever is left)."""
        now = time.monotonic()
        for i, (name, src) in enumerate(self.sources):
            drops = int(stats.get(name, {}).get("kernel_drops", 0))
            new = drops - self._drops_seen.get(i, 0)
            if new <= 0 or (not final and now - self._drops_event_at.get(i, -1e9) < DROP_EVENT_EVERY_S):
                continue
            self._drops_seen[i], self._drops_event_at[i] = drops, now
            granted = getattr(src, "buffer_bytes", None)
            held = f" ({granted} bytes granted)" if granted else ""
            self._event(i, "kernel-drops", f"the kernel dropped {new} datagram(s) (total {drops}): the receive "
                                           f"buffer{held} was full; raise rcvbuf= in the source URL (and "
                                           f"net.core.rmem_max), or lighten this machine's load")  # fmt: skip

    # ------------------------------------------------------------------ status
    def _state(self, index: int) -> str:
        if index in self._ended:
            return "lost"
        if index in self._undecoded or self._decode_error is not None:
            return "raw only"
        return "recording"

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
            ents: dict[str, dict[str, Any]] = {}
            if self._dproc is not None:
                ents = self._dproc.status[i] if i < len(self._dproc.status) else {}
            elif src.decoder is not None and i not in self._undecoded:
                try:
                    ents = src.decoder.status(now)
                except Exception:  # noqa: BLE001 - a broken decoder shows no entities
                    ents = {}
            for e, st in ents.items():
                entity_live[f"{name}|{e}"] = st
            last = self._last_sample_ns.get(i)
            out.append(SourceStatus(name, src.kind, src.url, self._packets[i], self._samples[i], prate, srate,
                                    sum(stats.get(k, 0) for k in LOSS_COUNTERS),
                                    sum(stats.get(k, 0) for k in ERROR_COUNTERS),
                                    None if last is None else (now - last) / 1e9, stats, ents,
                                    self._state(i)))  # fmt: skip
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
        try:
            st = dict(self.sources[index][1].stats())
        except Exception:  # noqa: BLE001 - a lost device may not answer; its counters so far are in the take
            st = dict(self.sources[index][1].counters)
        if self._dproc is not None and index < len(self._dproc.counters):
            st.update(self._dproc.counters[index])
        return st

    def _stats(self) -> dict[str, dict[str, int]]:
        return {name: {k: int(v) for k, v in self._source_stats(i).items()} for i, (name, _) in enumerate(self.sources)}

    # ------------------------------------------------------------------ run
    def run(self, duration: float | None = None, *, until: Callable[[], bool] | None = None,
            on_status: Callable[[LiveStatus], None] | None = None, status_every: float = 0.25) -> TakeResult:  # fmt: skip
        """Record until the duration, :meth:`stop`, ``until()``, every source lost, or a write
        failure; returns how it ended (what failed on the way is in the result too)."""
        self.started = time.monotonic()
        reason, error, fix = "stopped", None, None
        next_status = next_record = self.started
        get = self._queue.get
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
                if len(self._ended) == len(self.sources):
                    reason = "source-lost"
                    break
                try:
                    index, packets, extra = get(timeout=0.05)
                except queue.Empty:
                    pass
                else:
                    self._handle(index, packets, extra)
                self._poll_decoder()
                self.writer.maybe_flush()
                if now >= next_record:
                    stats = self._stats()
                    self.writer.add_status(now_ns(), stats)
                    self._check_drops(stats)
                    self._check_decoder_alive()
                    next_record = now + 1.0
                if on_status is not None and now >= next_status:
                    on_status(self.status())
                    next_status = now + status_every
        except KeyboardInterrupt:
            reason = "stopped"
        except TakeWriteError as e:
            reason, error, fix = "write-failed", e.message, e.fix
        finally:
            self._stop.set()
            for th in self._threads:
                th.join(timeout=2.0)
        recorded_s = time.monotonic() - self.started  # decoding may still catch up below; not part of the take
        if error is None:
            try:
                self._drain()
                self._check_drops(self._stats(), final=True)
            except TakeWriteError as e:
                reason, error, fix = "write-failed", e.message, e.fix
        if self._dproc is not None:
            self._dproc.close()
        if on_status is not None:
            on_status(self.status())  # the final state, decoding complete
        stats = self._stats()
        if error is None:
            error, fix = self._failures(reason)
        ended = {self.sources[i][0]: why for i, why in self._ended.items()}
        decode_failed = {self.sources[i][0]: why for i, why in self._undecoded.items()}
        if self._decode_error is not None:
            decode_failed[ALL_SOURCES] = self._decode_error
        result = TakeResult(self.writer.path, self.take, reason, error, recorded_s,
                            self.writer.take_start_utc, self.writer.messages, self.writer.samples_per_topic(), stats,
                            self.events, ended, decode_failed, fix)  # fmt: skip
        summary = {"sources": stats, "reason": reason, "error": error or "", "duration_s": result.duration_s,
                   "ended_sources": ended, "decode_failed": decode_failed, "fix": fix or ""}  # fmt: skip
        if self._decode_detail:
            summary["decode_traceback"] = self._decode_detail
        try:
            self.writer.close(summary)
        except TakeWriteError as e:
            result.reason, result.error, result.fix = "write-failed", e.message, e.fix
        return result

    def _failures(self, reason: str) -> tuple[str | None, str | None]:
        """The error and fix of a take that ran to its end with parts failed on the way."""
        problems, fixes = [], []
        for i, why in self._ended.items():
            name, src = self.sources[i]
            problems.append(f"source {name!r} ({src.url}) was lost: {why}")
        if self._ended:
            fixes.append("reconnect the lost device before the next take" + (
                "" if reason == "source-lost" else "; the other sources were recorded to the end"))
        for i, why in self._undecoded.items():
            problems.append(f"decoding source {self.sources[i][0]!r} failed ({why}); its raw packets were recorded")
        if self._decode_error is not None:
            problems.append(f"decoding failed ({self._decode_error}); every raw packet was recorded, the decoded "
                            f"samples stop where decoding did")  # fmt: skip
        if self._undecoded or self._decode_error is not None:
            fixes.append(f"`dualhuman log repair {self.writer.path}` re-decodes the samples from the raw packets")
        if not problems:
            return None, None
        head = "every source was lost: " if reason == "source-lost" else ""
        return head + "; ".join(problems), "; ".join(fixes)

    def _drain(self) -> None:
        """Write what the reader threads handed over but was not written yet, then what the
        decoders still hold."""
        while True:
            try:
                index, packets, extra = self._queue.get_nowait()
            except queue.Empty:
                break
            self._handle(index, packets, extra)
        if self._dproc is not None:
            if self._decode_error is None:
                try:
                    self._dproc.finish(self._decoded)
                except RuntimeError as e:
                    self._dproc.proc.join(timeout=1.0)  # an early end: its exit code says how
                    self._decoder_lost(self._decoder_exit(_last_line(str(e))), self._dproc.error)
            return
        for i, (_, src) in enumerate(self.sources):
            if i in self._undecoded:
                continue
            try:
                for s in src.decoder.finish():
                    self.writer.add_sample(i, s)
                    self._samples[i] += 1
            except TakeWriteError:
                raise
            except Exception as e:  # noqa: BLE001 - as in _process
                self._decoding_failed(i, _why(e))
            self._drain_events(i)

    def close(self) -> None:
        """Stop the readers (if :meth:`run` did not) and close the sources (the recorder does not
        own them otherwise)."""
        self._stop.set()
        for th in self._threads:
            th.join(timeout=2.0)
        if self._dproc is not None and self._dproc.proc.is_alive():  # run() was not called
            self._dproc.proc.terminate()
            self._dproc.close()
        for _, src in self.sources:
            try:
                src.close()
            except Exception:  # noqa: BLE001 - closing must not mask the take's outcome
                pass
