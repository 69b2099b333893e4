"""Decoding cost per packet of every capture decoder, on the packets of a recorded take.

Records (once, cached under ``benchmarks/cache/``) a simulated handshake through the real loopback
transports — two MVN suits, twelve VIVE trackers, an Xbus MTi on a pseudo-terminal, a CAN MTi on
python-can's virtual bus — then feeds each source's raw packets to a fresh decoder
(:func:`dualhuman_builder.capture.sources.make_decoder`), ``--repeat`` times, and reports the best
time per packet and per sample, and the share of one core each source's decoding takes at the
rate its packets arrived (recorded host times). The recorder decodes every source in one process
(:mod:`dualhuman_builder.capture.decoding`); the goal is that the whole studio's decoding takes at
most half a core, so one core decodes the studio at twice real time.

    .venv/bin/python benchmarks/bench_decoders.py
    .venv/bin/python benchmarks/bench_decoders.py --repeat 10 --out /tmp/decoders.json

Writes ``benchmarks/results/decoders.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from results_file import Goal, write_results  # noqa: E402

CACHE = ROOT / "benchmarks" / "cache"
#: Goal: the studio's decoding load, in cores, at the recorded (real-time) packet rates.
MAX_LOAD_CORES = 0.5


def recorded_take(fps: float = 15.0) -> Path:
    """A simulated handshake recorded through loopback transports (cached)."""
    from dualhuman_builder.capture.recording import capture_take, plan_capture

    path = CACHE / f"decoders-handshake-{fps:g}.mcap"
    if not path.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        print(f"recording a simulated handshake into {path} (real time)...", flush=True)
        tmp = path.with_suffix(".part.mcap")
        tmp.unlink(missing_ok=True)
        res = capture_take(plan_capture(sources=[f"sim://handshake?seed=1&fps={fps:g}"]), tmp, take="BENCH")
        if res.error:
            raise SystemExit(f"recording failed: {res.error}")
        tmp.rename(path)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5, help="decode each source's packets this many times; the best counts")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/decoders.json)")
    args = ap.parse_args()

    from dualhuman_builder.capture.log.reader import TakeReader
    from dualhuman_builder.capture.sources import make_decoder, source_class

    take = recorded_take()
    reader = TakeReader(take)
    reader.load_header()
    urls = {s["name"]: s["url"] for s in reader.take_meta().get("sources", [])}
    packets = defaultdict(list)
    for name, packet in TakeReader(take).raw_packets():
        packets[name].append(packet)
    figures: dict = {"sources": {}}
    for name, url in urls.items():
        kind = source_class(url).kind
        times = [p.host_time_ns for p in packets[name]]
        rate = (len(times) - 1) / ((times[-1] - times[0]) * 1e-9) if len(times) > 1 and times[-1] > times[0] else 0.0
        best = float("inf")
        samples = 0
        for _ in range(args.repeat):
            dec = make_decoder(url)
            t0 = time.perf_counter()
            n = sum(len(dec.feed(p)) for p in packets[name])
            n += len(dec.finish())
            best = min(best, time.perf_counter() - t0)
            samples = n
        per_packet = best / max(len(packets[name]), 1) * 1e6
        load = per_packet * rate / 1e6
        figures["sources"][name] = {"kind": kind, "packets": len(packets[name]), "samples": samples,
                                    "packets_per_s": round(rate, 1), "us_per_packet": round(per_packet, 3),
                                    "us_per_sample": round(best / max(samples, 1) * 1e6, 3), "load_cores": round(load, 4)}  # fmt: skip
        print(f"{name:<10} {kind:<8} {len(packets[name]):>7} packets at {rate:7.1f}/s: {per_packet:8.2f} µs/packet, "
              f"{100 * load:5.1f} % of a core", flush=True)  # fmt: skip
    figures["load_cores"] = round(sum(s["load_cores"] for s in figures["sources"].values()), 4)
    print(f"the studio's decoding: {100 * figures['load_cores']:.1f} % of a core (goal <= {100 * MAX_LOAD_CORES:.0f} %)")
    path = write_results("decoders", figures, params={"repeat": args.repeat, "take": take.name},
                         goals=[Goal("load_cores", "<=", MAX_LOAD_CORES, "cores")], out=args.out)  # fmt: skip
    print(f"written {path}")


if __name__ == "__main__":
    main()
