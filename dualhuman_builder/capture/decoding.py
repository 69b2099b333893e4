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
"""

from __future__ import annotations

import multiprocessing as mp
import queue
import time
import traceback
from typing import Any, Mapping

#: How often the decoding process reports counters and live status (seconds).
STATUS_EVERY_S = 0.25
#: Scheduling niceness of the decoding process (lower priority than the recorder's readers).
NICENESS = 10


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
    from dualhuman_builder.capture.sources import RawPacket, make_decoder, now_ns

    try:
        decoders = [make_decoder(u) for u in urls]
        encoder = SampleEncoder(names, bindings, foxglove_hz)
        next_status = 0.0
        while True:
            try:
                msg = inbox.get(timeout=STATUS_EVERY_S)
            except queue.Empty:
                msg = None
            if msg is not None and msg[0] == "finish":
                for i, dec in enumerate(decoders):
                    items = [it for s in dec.finish() for it in encoder.encode(i, s)]
                    outbox.put(("items", i, items, dec.pop_events()))
                outbox.put(("done", [dict(d.counters) for d in decoders],
                            [d.status(now_ns()) for d in decoders], time.process_time()))  # fmt: skip
                return
            if msg is not None:
                index, packets = msg[1], msg[2]
                dec = decoders[index]
                items = []
                for t, data in packets:
                    for s in dec.feed(RawPacket(t, data)):
                        items += encoder.encode(index, s)
                outbox.put(("items", index, items, dec.pop_events()))
            if time.monotonic() >= next_status:
                now = now_ns()
                outbox.put(("status", [dict(d.counters) for d in decoders], [d.status(now) for d in decoders]))
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
        taken in as they arrive); raises RuntimeError if the process failed."""
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
