"""Decoding beside the recorder, in a process of its own (docs/decisions/0006-decoding-process.md).

Decoding packets and encoding samples is most of a recorder's CPU work, and with it in the
recorder's process the reader threads and the writer share one interpreter lock: at a few times
real time the readers stop draining their sockets and the kernel drops datagrams. So by default
the recorder keeps for itself only what cannot wait — reading every transport and writing every
raw packet to the take — and a :class:`DecodeProcess` runs the sources' decoders (the same
classes, fed the same packets in the same order, so the samples are the same) and the
:class:`~dualhuman_builder.capture.log.writer.SampleEncoder`, and sends back ready-to-write
messages, the decoders' counters, events and live status.

If decoding falls behind (a take at many times real time), nothing is lost: the raw packets are
already on disk and the decoded samples follow as they are ready; the take is finished once the
decoder has caught up (:meth:`DecodeProcess.finish`).

One source never stops the others. Its decoder never raises (the guard of
:class:`~dualhuman_builder.capture.sources.Decoder`); anything else about it that fails here — its
decoder cannot be built, a sample cannot be encoded, its counters or status cannot be read — marks
that source failed (:class:`_Lanes`): a ``decoding-failed`` event names the error, its counters
show ``decoding_failed`` = 1 and, from then on, ``undecoded_packets``, and the other sources go on.
Its raw packets are still written by the recorder, so replay can decode them later.
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import time
import traceback
from collections import Counter
from typing import Any, Callable, Mapping

#: How often the decoding process reports counters and live status (seconds).
STATUS_EVERY_S = 0.25
#: Scheduling niceness of the decoding process (lower priority than the recorder's readers).
NICENESS = 10


class _Lanes:
    """The decoders of one decoding process, one per source, isolated from each other.

    ``make_decoder(url)`` builds each decoder, ``encode(index, sample)`` turns a sample into
    items. :meth:`feed`, :meth:`finish`, :meth:`counters` and :meth:`status` never raise: a
    failure of one source marks it failed (see the module docstring) and the others go on."""

    def __init__(self, urls: list[str], names: list[str], make_decoder: Callable, encode: Callable):
        from dualhuman_builder.capture.sources import SourceEvent, now_ns

        self._event, self._now = SourceEvent, now_ns
        self.names = list(names)
        self.encode = encode
        self.decoders: list[Any] = []
        self.failed: list[str | None] = [None] * len(urls)
        self.extra: list[Counter] = [Counter() for _ in urls]
        self._pending: list[list] = [[] for _ in urls]
        self._last_ns = [0] * len(urls)
        for i, url in enumerate(urls):
            try:
                self.decoders.append(make_decoder(url))
            except Exception as e:  # noqa: BLE001 - this source only
                self.decoders.append(None)
                self._fail(i, "its decoder cannot be built", e)

    def _fail(self, index: int, what: str, error: BaseException) -> None:
        name = self.names[index] if index < len(self.names) else str(index)
        message = f"{type(error).__name__}: {error}"
        self.failed[index] = message[:400]
        self.extra[index]["decoding_failed"] = 1
        t = self._last_ns[index] or self._now()
        self._pending[index].append(self._event(t, "decoding-failed", name,
                                                f"decoding source {name} stopped, {what} ({self.failed[index]}); "
                                                "its raw packets are still recorded: `dualhuman replay` decodes "
                                                "them again"))  # fmt: skip

    def feed(self, index: int, packets) -> tuple:
        """``("items", index, items, events)`` for raw packets ``[(host_time_ns, data)]`` of source ``index``."""
        from dualhuman_builder.capture.sources import RawPacket

        items: list = []
        if self.failed[index] is None:
            dec = self.decoders[index]
            try:
                for t, data in packets:
                    self._last_ns[index] = t
                    for s in dec.feed(RawPacket(t, data)):
                        items += self.encode(index, s)
            except Exception as e:  # noqa: BLE001 - what the decoder guard cannot catch (encoding)
                self._fail(index, "a sample could not be written", e)
        else:
            self.extra[index]["undecoded_packets"] += len(packets)
        return ("items", index, items, self._events(index))

    def finish(self) -> list[tuple]:
        """The held-back samples of every source, as ``("items", ...)`` messages."""
        out = []
        for i, dec in enumerate(self.decoders):
            items: list = []
            if self.failed[i] is None:
                try:
                    for s in dec.finish():
                        items += self.encode(i, s)
                except Exception as e:  # noqa: BLE001
                    self._fail(i, "a sample could not be written", e)
            out.append(("items", i, items, self._events(i)))
        return out

    def leftover(self) -> list[tuple]:
        """``("items", index, [], events)`` for the failures noted since the last messages."""
        out = [("items", i, [], pending) for i, pending in enumerate(self._pending) if pending]
        self._pending = [[] for _ in self._pending]
        return out

    def _events(self, index: int) -> list:
        dec, out = self.decoders[index], []
        if dec is not None:
            try:
                out = list(dec.pop_events())
            except Exception as e:  # noqa: BLE001
                if self.failed[index] is None:
                    self._fail(index, "its events could not be read", e)
        out += self._pending[index]
        self._pending[index] = []
        return out

    def counters(self) -> list[dict[str, int]]:
        out = []
        for i, dec in enumerate(self.decoders):
            c: dict[str, int] = {}
            if dec is not None:
                try:
                    c = dict(dec.counters)
                except Exception as e:  # noqa: BLE001
                    if self.failed[i] is None:
                        self._fail(i, "its counters could not be read", e)
            c.update(self.extra[i])
            out.append(c)
        return out

    def status(self, now: int) -> list[dict[str, Any]]:
        out = []
        for i, dec in enumerate(self.decoders):
            st: dict[str, Any] = {}
            if dec is not None and self.failed[i] is None:
                try:
                    st = dict(dec.status(now))
                except Exception as e:  # noqa: BLE001
                    self._fail(i, "its status could not be read", e)
            out.append(st)
        return out


def _work(urls: list[str], names: list[str], bindings: Mapping, foxglove_hz: float, inbox, outbox) -> None:
    import os

    # reading the devices comes first: on a busy machine the decoder yields the CPU to the
    # recorder's readers and catches up later (the raw packets are on disk meanwhile)
    try:
        os.nice(NICENESS)
    except OSError:
        pass
    parent = os.getppid()

    def watchdog() -> None:
        # the recorder died (kill -9): nobody will read what we decode, and the main thread may be
        # blocked on a message the recorder was half-way through writing — leave at once
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(0)

    import threading

    threading.Thread(target=watchdog, name="parent-watchdog", daemon=True).start()
    from dualhuman_builder.capture.log.writer import SampleEncoder
    from dualhuman_builder.capture.sources import make_decoder, now_ns

    try:
        encoder = SampleEncoder(names, bindings, foxglove_hz)
        lanes = _Lanes(urls, names, make_decoder, encoder.encode)
        next_status = 0.0
        newest = 0  # host time of the newest packet decoded (ns)

        def clock() -> int:
            # liveness is judged at the time decoding has reached: while packets wait in the inbox
            # (decoding behind), "now" would call a device silent that is only not decoded yet
            return newest if newest and not inbox.empty() else now_ns()

        while True:
            try:
                msg = inbox.get(timeout=STATUS_EVERY_S)
            except queue.Empty:
                msg = None
            if msg is not None and msg[0] == "finish":
                msgs = lanes.finish()
                status = lanes.status(newest or now_ns())  # the take's end, not when decoding got there
                counters = lanes.counters()
                msgs += lanes.leftover()
                for out in msgs:
                    outbox.put(out)
                outbox.put(("done", counters, status, time.process_time()))
                return
            if msg is not None:
                outbox.put(lanes.feed(msg[1], msg[2]))
                if msg[2]:
                    newest = max(newest, msg[2][-1][0])
            if time.monotonic() >= next_status:
                status = lanes.status(clock())
                outbox.put(("status", lanes.counters(), status))
                next_status = time.monotonic() + STATUS_EVERY_S
    except BaseException:  # noqa: BLE001 - report any failure to the recorder, which stops cleanly
        outbox.put(("error", traceback.format_exc()))


class DecodeProcess:
    """The decoders of ``urls`` (one per source, in the recorder's order) in a spawned process.

    :meth:`submit` hands over raw packets (never blocks: a feeder thread pipes them);
    :meth:`poll` returns what came back since the last call; :meth:`finish` flushes the decoders
    and waits for everything. ``counters[i]`` / ``status[i]``: the latest decoder counters and
    live status of source ``i``."""

    def __init__(self, urls: list[str], names: list[str], bindings: Mapping, foxglove_hz: float):
        ctx = mp.get_context("spawn")  # never fork a process that has threads and open devices
        self._inbox = ctx.Queue()
        self._outbox = ctx.Queue()
        self.proc = ctx.Process(target=_work, args=(list(urls), list(names), dict(bindings), foxglove_hz, self._inbox,
                                                    self._outbox), name="dualhuman-decode", daemon=True)  # fmt: skip
        self.proc.start()
        self.counters: list[dict[str, int]] = [{} for _ in urls]
        self.status: list[dict[str, Any]] = [{} for _ in urls]
        #: CPU seconds the decoding process used (known once it has finished).
        self.cpu_s: float | None = None
        self.error: str | None = None

    def submit(self, index: int, packets) -> None:
        self._inbox.put(("packets", index, [(p.host_time_ns, p.data) for p in packets]))

    def poll(self, timeout: float = 0.0) -> list[tuple]:
        """``("items", source, items, events)`` messages that came back (status and counters are
        taken in as they arrive); raises RuntimeError if the process failed — after handing back,
        in an earlier call, what it decoded before failing."""
        if self.error is not None:
            raise RuntimeError(f"the decoding process failed:\n{self.error}")
        out = []
        deadline = time.monotonic() + timeout
        while True:
            try:
                msg = self._outbox.get(timeout=max(0.0, deadline - time.monotonic())) if timeout else \
                    self._outbox.get_nowait()  # fmt: skip
            except queue.Empty:
                break
            kind = msg[0]
            if kind == "items":
                out.append(msg)
            elif kind in ("status", "done"):
                self.counters, self.status = msg[1], msg[2]
                if kind == "done":
                    self.cpu_s = msg[3]
                    out.append(msg)
                    break
            elif kind == "error":
                self.error = msg[1]
                if out:  # what came before the failure is written first; the next call raises
                    break
                raise RuntimeError(f"the decoding process failed:\n{msg[1]}")
            if timeout and out:
                break
        return out

    def finish(self, on_items, timeout: float = 600.0) -> None:
        """Flush the decoders, hand every remaining message to ``on_items`` and stop the process."""
        self._inbox.put(("finish",))
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not self.proc.is_alive() and self._outbox.empty():
                raise RuntimeError(f"the decoding process ended early (exit code {self.proc.exitcode})")
            for msg in self.poll(timeout=0.2):
                if msg[0] == "done":
                    self.close()
                    return
                on_items(msg)
        raise RuntimeError(f"the decoding process did not finish within {timeout:g} s")

    def close(self) -> None:
        self.proc.join(timeout=2.0)
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout=2.0)
        for q in (self._inbox, self._outbox):
            q.cancel_join_thread()
            q.close()
