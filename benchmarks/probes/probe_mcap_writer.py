"""Probe: can the ``mcap`` library's public ``Writer.add_message`` carry the recorder's load?

The message stream of a real take (every message of a take recorded from the simulated studio,
with its channels, schemas, sizes and order) is written through

* ``public``: ``mcap.writer.Writer`` as published (``add_message``, ``flush``, ``finish``), and
* ``fastpath``: a ``Writer`` whose private chunk builder is replaced by one that appends each
  message record with a single ``struct.pack`` and builds the message indexes per chunk with
  numpy (the alternative to the public API, kept here so that it can be measured),

alternately (the order swaps every repeat), into LZ4 chunks of 1 MiB flushed every second of take
time, as :class:`~dualhuman_builder.capture.log.writer.TakeWriter` writes them. Both files are read
back with the library's indexed reader and must hold the take's messages, identical.

The rate the writer must sustain is the studio of ``benchmarks/bench_capture.py`` counted the way
``TakeWriter`` writes it: per second of real time,

==============================  =======  ===============================================  =========
device                          rate     messages per device sample                        msgs/s
==============================  =======  ===============================================  =========
2 suits (MVN, one UDP port)     240 Hz   2 raw datagrams (type 02 + 25), SuitFrame,        4 x 480
                                         SuitTimeCode; + ``tf/<actor>`` at most 60 Hz      + 120
12 trackers (UDP bridge)        250 Hz   1 raw datagram, TrackerSample                     2 x 3000
Xbus MTi (serial)               400 Hz   ImuSample; raw: one per read (at most 1/sample)   <= 800
CAN MTi (python-can)            100 Hz   8 raw CAN frames, ImuSample                       900
status                          1 Hz                                                       1
==============================  =======  ===============================================  =========

9,741 messages/s at 1x (an upper bound: a 1x ``bench_capture`` take holds ~9,460/s, the Xbus reads
batching several samples and the transforms falling below 60 Hz); ``bench_capture`` tries 1, 5,
10 and 20x.

    .venv/bin/python benchmarks/probes/probe_mcap_writer.py                 # records a 1x sim take (~20 s) first
    .venv/bin/python benchmarks/probes/probe_mcap_writer.py --take T.mcap --repeats 9
    .venv/bin/python benchmarks/probes/probe_mcap_writer.py --ingest 1,20   # also bench_capture's ingest, per variant

``--ingest`` records ``bench_capture``'s studio on loopback at the given multiples with each
variant in turn (alternating, ``--ingest-repeats`` times): whether the take is lossless and the
CPU seconds of the writer thread and of the decoding process.

Figures: ``benchmarks/results/probe_mcap_writer.json`` (median wall-clock and CPU time of the
repeats, messages/s, us/message, headroom = messages/s over the required rate).
"""

from __future__ import annotations

import argparse
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from results_file import Goal, Table, write_results

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

SIM_URL = "sim://handshake?seed=3&fps=30"
MULTIPLES = (1, 5, 10, 20)  # bench_capture's defaults
#: The decision bound: the public API is used when it writes at least this many times the 1x rate.
HEADROOM_BOUND = 5.0


def studio_rate() -> dict[str, int]:
    """Messages per second of real time that TakeWriter writes for bench_capture's studio."""
    suits = 2 * 240 * (2 + 2) + 2 * 60  # raw 02 + 25, SuitFrame + SuitTimeCode; transforms
    trackers = 12 * 250 * (1 + 1)
    xbus = 400 * (1 + 1)  # decoded + at most one raw read per sample
    can = 100 * (8 + 1)  # eight CAN frames + decoded
    status = 1
    return {"suits": suits, "trackers": trackers, "xbus_mti": xbus, "can_mti": can, "status": status,
            "total": suits + trackers + xbus + can + status}  # fmt: skip


# ---------------------------------------------------------------------------- the fast path
def fastpath_writer_class():
    """``mcap.writer.Writer`` with its private chunk builder swapped for a one-pack-per-message
    builder (indexes and statistics computed per chunk with numpy)."""
    import numpy as np
    from mcap.data_stream import RecordBuilder
    from mcap.writer import Writer

    head = struct.Struct("<BQHIQQ")  # opcode 0x05, record length, channel, sequence, log time, publish time
    index_head = struct.Struct("<BQHI")  # opcode 0x07, record length, channel, byte length of the pairs

    class Index:
        def __init__(self, cid, times, offsets):
            self.channel_id = cid
            self.records = np.stack([times, offsets], axis=1).astype("<u8")

        def write(self, stream):
            body = self.records.tobytes()
            stream.write(index_head.pack(0x07, 6 + len(body), self.channel_id, len(body)) + body)

    class Chunks:
        def __init__(self, stats):
            self._stats = stats
            self.reset()

        count = property(lambda self: len(self._buf))
        num_messages = property(lambda self: len(self._ch))
        message_start_time = property(lambda self: min(self._t) if self._t else 0)
        message_end_time = property(lambda self: max(self._t) if self._t else 0)

        @property
        def message_indices(self):
            if self._indices is None:
                self._indices = {}
                if self._ch:
                    ch = np.asarray(self._ch, dtype=np.int64)
                    t, off = np.asarray(self._t, dtype=np.uint64), np.asarray(self._off, dtype=np.uint64)
                    order = np.argsort(ch, kind="stable")
                    ids, starts = np.unique(ch[order], return_index=True)
                    for cid, a, b in zip(ids.tolist(), starts.tolist(), [*starts[1:].tolist(), len(order)]):
                        self._indices[cid] = Index(cid, t[order[a:b]], off[order[a:b]])
            return self._indices

        def end(self):
            st = self._stats
            if self._ch:
                for cid, index in self.message_indices.items():
                    st.channel_message_counts[cid] += len(index.records)
                lo, hi = self.message_start_time, self.message_end_time
                if st.message_count == 0:
                    st.message_start_time, st.message_end_time = lo, hi
                else:
                    st.message_start_time, st.message_end_time = min(st.message_start_time, lo), max(st.message_end_time, hi)
                st.message_count += len(self._ch)
            data = bytes(self._buf)
            self._buf = bytearray()
            return data

        def _record(self, record):
            rb = RecordBuilder()
            record.write(rb)
            self._buf += rb.end()

        add_channel = add_schema = _record

        def add(self, channel_id, log_time, data, publish_time, sequence=0):
            buf = self._buf
            self._off.append(len(buf))
            buf += head.pack(0x05, 22 + len(data), channel_id, sequence, log_time, publish_time)
            buf += data
            self._ch.append(channel_id)
            self._t.append(log_time)

        def reset(self):
            self._buf = bytearray()
            self._ch, self._t, self._off = [], [], []
            self._indices = None

    class FastPathWriter(Writer):
        def __init__(self, output, **kwargs):
            super().__init__(output, **kwargs)
            self._chunks = Chunks(self._Writer__statistics)
            self._Writer__chunk_builder = self._chunks
            self._limit = kwargs.get("chunk_size", 1024 * 1024)
            self._finalize = self._Writer__finalize_chunk

        def add_message(self, channel_id, log_time, data, publish_time, sequence=0):
            chunks = self._chunks
            chunks.add(channel_id, log_time, data, publish_time, sequence)
            if len(chunks._buf) > self._limit:
                self._finalize()

    return FastPathWriter


# ---------------------------------------------------------------------------- the stream
def record_take(path: Path) -> None:
    from dualhuman_builder.capture.recording import capture_take, plan_capture

    print(f"recording {SIM_URL} at 1x into {path} ...", flush=True)
    r = capture_take(plan_capture(sources=[SIM_URL]), path, take="probe", sim_speed=1.0)
    if r.error:
        raise SystemExit(f"recording the take failed: {r.error}")


def load_stream(path: Path):
    """The take's schemas, channels (in id order) and messages (file order)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        r = make_reader(f)
        s = r.get_summary()
        msgs = [(m.channel_id, m.log_time, bytes(m.data), m.publish_time, m.sequence)
                for _, _, m in r.iter_messages(log_time_order=False)]  # fmt: skip
    schemas = [s.schemas[k] for k in sorted(s.schemas)]
    channels = [s.channels[k] for k in sorted(s.channels)]
    if [x.id for x in schemas] != list(range(1, len(schemas) + 1)) or [c.id for c in channels] != list(range(1, len(channels) + 1)):
        raise SystemExit("the take's schema and channel ids are not 1..n; this probe re-registers them in order")
    return schemas, channels, msgs


def write_stream(cls, path: Path, schemas, channels, msgs, flush_ns: int) -> tuple[float, float]:
    """Write the stream with ``cls``; (wall s, thread CPU s) from ``start`` to ``finish``."""
    from mcap.writer import CompressionType

    with open(path, "xb") as f:
        t0, c0 = time.perf_counter(), time.thread_time()
        w = cls(f, chunk_size=1 << 20, compression=CompressionType.LZ4)
        w.start("dualhuman", "dualhuman_builder")
        for s in schemas:
            w.register_schema(s.name, s.encoding, s.data)
        for c in channels:
            w.register_channel(c.topic, c.message_encoding, c.schema_id, c.metadata)
        add = w.add_message
        last = msgs[0][1] if msgs else 0
        for cid, lt, data, pt, seq in msgs:
            add(cid, lt, data, pt, seq)
            if lt - last >= flush_ns:  # TakeWriter.maybe_flush, on take time
                w.flush()
                last = lt
        w.finish()
        return time.perf_counter() - t0, time.thread_time() - c0


def read_back(path: Path):
    """Messages and statistics as the library's indexed reader sees them."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        r = make_reader(f)
        s = r.get_summary()
        msgs = [(ch.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data))
                for _, ch, m in r.iter_messages(log_time_order=False)]  # fmt: skip
        by_topic = {t: sum(1 for _ in r.iter_messages(topics=[t])) for t in ("raw/trackers", "status")}
    st = s.statistics
    stats = (st.message_count, dict(st.channel_message_counts), st.message_start_time, st.message_end_time,
             st.channel_count, st.schema_count)  # fmt: skip
    indexed = all(ci.message_index_offsets for ci in s.chunk_indexes)
    return msgs, stats, len(s.chunk_indexes), indexed, by_topic


def ingest_ab(variants: dict, multiples: list[float], repeats: int) -> list[dict]:
    """``bench_capture.ingest`` with each writer variant in turn (TakeWriter's ``Writer`` swapped)."""
    import bench_capture

    import dualhuman_builder.capture.log.writer as writer_module

    runs = []
    order = list(variants)
    original = writer_module.Writer
    try:
        for rep in range(repeats):
            for name in order if rep % 2 == 0 else order[::-1]:
                writer_module.Writer = variants[name]
                for m in multiples:
                    scene = bench_capture.scene_file(8.0 if m == 1 else 10.0)
                    with tempfile.TemporaryDirectory() as d:
                        try:
                            r = bench_capture.ingest(scene, m, Path(d))
                        except Exception as e:  # noqa: BLE001 - a loopback device that failed to open: next run
                            runs.append({"variant": name, "multiple": m, "error": f"{type(e).__name__}: {e}"})
                            print(f"ingest {name:8s} {m:g}x: did not start ({e})", flush=True)
                            continue
                    run = {"variant": name, "multiple": m, "lossless": r["lossless"],
                           "loss": {k: v for k, v in r["loss"].items() if v}, "wall_s": r["wall_s"],
                           "writer_cpu_s": r["threads"]["writer (main)"],
                           "decoding_cpu_s": r["threads"].get("decoding process")}  # fmt: skip
                    runs.append(run)
                    print(f"ingest {name:8s} {m:g}x: {'lossless' if run['lossless'] else 'LOSS ' + str(run['loss'])}; "
                          f"writer thread {run['writer_cpu_s']:.2f} s CPU, decoding {run['decoding_cpu_s'] or 0:.2f} s "
                          f"in {run['wall_s']:.1f} s", flush=True)  # fmt: skip
    finally:
        writer_module.Writer = original
    return runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--take", type=Path, help="a take file to take the messages from (default: record a 1x sim take)")
    ap.add_argument("--repeats", type=int, default=7, help="timed writes per variant (medians reported)")
    ap.add_argument("--flush-s", type=float, default=1.0, help="flush a chunk every this many seconds of take time")
    ap.add_argument("--ingest", default="", help="comma-separated multiples to record bench_capture's studio at, "
                                                 "per variant (e.g. 1,20; default none)")
    ap.add_argument("--ingest-repeats", type=int, default=4, help="ingest runs per variant and multiple")
    args = ap.parse_args()
    from mcap.writer import Writer

    variants = {"public": Writer, "fastpath": fastpath_writer_class()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        take = args.take
        if take is None:
            take = tmp / "source.mcap"
            record_take(take)
        schemas, channels, msgs = load_stream(take)
        n = len(msgs)
        span_s = (max(m[1] for m in msgs) - min(m[1] for m in msgs)) / 1e9
        nbytes = sum(len(m[2]) for m in msgs)
        flush_ns = int(args.flush_s * 1e9)
        print(f"{n} messages, {len(channels)} channels, {nbytes / n:.0f} B/message, {span_s:.1f} s of take time", flush=True)

        # read-back check (and warm-up): both files hold the take's messages, identical
        source = read_back(take)[0]
        back = {}
        for name, cls in variants.items():
            p = tmp / f"check_{name}.mcap"
            write_stream(cls, p, schemas, channels, msgs, flush_ns)
            back[name] = read_back(p)
        a, b = back["public"], back["fastpath"]
        identical = a[0] == b[0] == source and a[1] == b[1] and a[4] == b[4] and a[3] and b[3]
        print(f"read back: {len(a[0])} and {len(b[0])} messages, {a[2]} and {b[2]} chunks, identical: {identical}")

        wall = {k: [] for k in variants}
        cpu = {k: [] for k in variants}
        order = list(variants)
        for rep in range(args.repeats):
            for name in order if rep % 2 == 0 else order[::-1]:
                p = tmp / f"{name}_{rep}.mcap"
                w, c = write_stream(variants[name], p, schemas, channels, msgs, flush_ns)
                p.unlink()
                wall[name].append(w)
                cpu[name].append(c)
            print(f"repeat {rep + 1}: " + ", ".join(f"{k} {n / wall[k][-1]:,.0f} msg/s" for k in order), flush=True)

    need = studio_rate()
    figures: dict = {"required_msgs_per_s": {**need, **{f"{m}x": need["total"] * m for m in MULTIPLES}},
                     "stream": {"messages": n, "channels": len(channels), "bytes_per_message": nbytes / n,
                                "take_seconds": span_s, "msgs_per_take_second": n / span_s if span_s else None},
                     "readback": {"identical": bool(identical), "messages": len(a[0]), "chunks": [a[2], b[2]]}}  # fmt: skip
    for name in order:
        med_w, med_c = statistics.median(wall[name]), statistics.median(cpu[name])
        rate = n / med_w
        figures[name] = {"msgs_per_s": rate, "us_per_msg": 1e6 * med_w / n, "cpu_us_per_msg": 1e6 * med_c / n,
                         "wall_s": wall[name], "cpu_s": cpu[name],
                         "headroom": {f"{m}x": rate / (need["total"] * m) for m in MULTIPLES}}  # fmt: skip
    figures["fastpath_speedup"] = figures["public"]["us_per_msg"] / figures["fastpath"]["us_per_msg"]
    if args.ingest:
        runs = ingest_ab(variants, [float(x) for x in args.ingest.split(",")], args.ingest_repeats)
        summary = {}
        for name in order:
            for m in sorted({r["multiple"] for r in runs}):
                rs = [r for r in runs if r["variant"] == name and r["multiple"] == m and "error" not in r]
                if not rs:
                    continue
                summary[f"{name}_{m:g}x"] = {"lossless_runs": sum(r["lossless"] for r in rs), "runs": len(rs),
                                             "writer_cpu_s": statistics.median(r["writer_cpu_s"] for r in rs),
                                             "writer_cpu_share": statistics.median(r["writer_cpu_s"] / r["wall_s"] for r in rs)}  # fmt: skip
        figures["ingest"] = {"summary": summary, "runs": runs}
    for name in order:
        f = figures[name]
        print(f"{name:9s} {f['msgs_per_s']:>10,.0f} msg/s  {f['us_per_msg']:.2f} us/msg (CPU {f['cpu_us_per_msg']:.2f})  "
              + "  ".join(f"{k} {v:.1f}x" for k, v in f["headroom"].items()))  # fmt: skip
    print(f"required: {need['total']:,} msg/s at 1x, {need['total'] * 20:,} at 20x")
    path = write_results("probe_mcap_writer", figures,
                         params={"take": str(args.take) if args.take else SIM_URL + " recorded at 1x",
                                 "repeats": args.repeats, "flush_s": args.flush_s, "chunk_size": 1 << 20,
                                 "compression": "lz4", "ingest": args.ingest, "ingest_repeats": args.ingest_repeats},
                         goals=[Goal("public.headroom.1x", ">=", HEADROOM_BOUND, "x",
                                     label="public Writer: messages/s written over the studio's rate at 1x"),
                                Goal("readback.identical", ">=", 1,
                                     label="both files read back by the library's indexed reader, identical")],
                         tables=[Table("MCAP writer on a real take's message stream (median of the repeats)",
                                       ["writer", "messages/s", "us/message", "CPU us/message", "headroom 1x",
                                        "headroom 20x"],
                                       [[name, f"{name}.msgs_per_s", f"{name}.us_per_msg", f"{name}.cpu_us_per_msg",
                                         f"{name}.headroom.1x", f"{name}.headroom.20x"] for name in order])],
                         notes="headroom = messages/s written / messages/s the studio produces; the public API is "
                               "used when its 1x headroom is at least 5 (the writer shares the cores with decoding "
                               "and the readers)")  # fmt: skip
    print(f"results: {path}")


if __name__ == "__main__":
    main()
