"""Capture benchmarks: live ingestion on loopback (zero loss at 1x, the highest multiple without
loss, CPU of the recorder), and replay throughput to the pipeline.

The load is the studio of the issue: two suits at 240 Hz (23 segments, types 02 + 25, both on one
MVN port), twelve trackers at 250 Hz, an Xbus MTi at 400 Hz on a pseudo-terminal and a CAN MTi at
100 Hz on python-can's virtual bus, simulated from a generated handshake padded to the take length.
The UDP and serial devices play from a child process (``dualhuman sim play``), so the recorder's
process does only the recording (the in-process CAN player is small); the CPU figure is the
recorder process's user+system time over the wall time, and the decoding process's CPU is listed
per thread. On a 2-core machine the players, the recorder and its decoding process share the two
cores, so at high multiples the simulated devices themselves compete with the recorder.

Loss is counted against what the devices sent: every suit frame and tracker sample simulated must
be recorded (kernel drops, MVN sample-counter gaps, incomplete messages all zero), and the Xbus and
CAN streams must show no packet-counter gap after their first recorded sample.

    .venv/bin/python benchmarks/bench_capture.py                      # 60 s at 1x, then multiples
    .venv/bin/python benchmarks/bench_capture.py --seconds 10 --multiples 1,10,20,40

Goals: lossless at 1x, and lossless up to 20x real time (the highest multiple tried without loss).
Replay to the pipeline is timed against the take's own length (no goal). Writes
``benchmarks/results/capture.json`` (``--out`` elsewhere); the generated scenes are cached in
``benchmarks/cache/``.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from results_file import Goal, Table, write_results  # noqa: E402

CACHE = ROOT / "benchmarks" / "cache"
#: The highest multiple of real time the studio must record without loss.
GOAL_MULTIPLE = 20.0
#: The shortest scene generated (s): shorter takes are played from a scene this long.
MIN_SCENE_S = 4.0


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def scene_file(seconds: float) -> Path:
    """A handshake padded to ``seconds`` (cached under benchmarks/cache/)."""
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    CACHE.mkdir(parents=True, exist_ok=True)
    path = CACHE / f"handshake_{seconds:g}s.npz"
    if not path.exists():
        print(f"generating a {seconds:g} s handshake scene (cached in {path}) ...", flush=True)
        make_scene(SceneParams(type="handshake", seed=3, fps=15, duration=max(seconds, MIN_SCENE_S))).save(path)
    return path


def ingest(scene: Path, multiple: float, workdir: Path) -> dict:
    """Record the studio played at ``multiple`` x real time; returns loss and CPU figures."""
    import uuid

    import can

    from dualhuman_builder.capture.log.reader import TakeReader
    from dualhuman_builder.capture.recorder import Recorder
    from dualhuman_builder.capture.sources import open_source
    from dualhuman_builder.sim.devices import CanPlayer
    from dualhuman_builder.sim.scenes import Scene
    from dualhuman_builder.sim.studio import simulate_studio

    studio = simulate_studio(Scene.load(scene).sequence, seed=3)
    counts = studio.counts()
    mvn = open_source("mvn+udp://127.0.0.1:0?rcvbuf=33554432")
    vive = open_source("vive+udp://127.0.0.1:0?rcvbuf=33554432")
    channel = f"bench-{uuid.uuid4().hex[:6]}"
    can_src = open_source(f"mti+can://virtual/{channel}?device=mti-can")
    child = subprocess.Popen([sys.executable, "-m", "cli", "sim", "play", f"sim://{scene}?devices=3", "--mvn",
                              f"127.0.0.1:{mvn.port}", "--trackers", f"127.0.0.1:{vive.port}", "--xbus", "pty",
                              "--speed", str(multiple)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True)  # fmt: skip
    pty_path = None
    lines = []
    while pty_path is None:
        line = child.stdout.readline()
        if not line:
            raise RuntimeError("sim play ended before opening its serial port:\n" + "".join(lines))
        lines.append(line)
        m = re.search(r"serial port (\S+)", line)
        if m:
            pty_path = m.group(1)
    # everything slow is prepared before the serial port is opened: an MTi streams from the moment
    # it is configured, and a pty nobody reads drops bytes
    bus = can.Bus(interface="virtual", channel=channel)
    can_player = CanPlayer(bus, speed=multiple).add_samples(studio.imus["mti-can"], clock="host")
    _ = can_player.packets
    xbus = open_source(f"xbus://{pty_path}?device=mti-xbus")
    path = workdir / f"ingest_{multiple:g}x.mcap"
    rec = Recorder(path, take=f"bench{multiple:g}", sources=[("suits", mvn), ("trackers", vive), ("prop-imu", xbus),
                                                            ("floor-imu", can_src)])  # fmt: skip
    can_player.start()
    c0, t0, main0 = cpu_s(), time.monotonic(), time.thread_time()
    done = []

    def until():
        if child.poll() is None or can_player.running:
            return False
        done.append(time.monotonic())
        return time.monotonic() - done[0] > 0.5

    if os.environ.get("BENCH_PROFILE"):
        import cProfile
        import pstats

        prof = cProfile.Profile()
        result = prof.runcall(rec.run, until=until)
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    else:
        result = rec.run(until=until)
    wall, cpu = time.monotonic() - t0, cpu_s() - c0
    threads = {"writer (main)": time.thread_time() - main0}
    threads.update(rec.thread_cpu_s)
    if rec._dproc is not None and rec._dproc.cpu_s is not None:
        threads["decoding process"] = rec._dproc.cpu_s
    rec.close()
    bus.shutdown()
    out = child.stdout.read()
    st = result.source_stats
    per_topic = {}
    for ch_topic, n in result.samples_per_topic.items():
        per_topic[ch_topic] = n
    suits = sum(n for t, n in per_topic.items() if t.startswith("suits/mvn/") and t.endswith("/SuitFrame"))
    trackers = sum(n for t, n in per_topic.items() if t.endswith("/TrackerSample"))
    want_suits = sum(v for k, v in counts.items() if k.startswith("suit/"))
    want_trackers = sum(int(studio.trackers[i].valid.size) for i in range(len(studio.trackers)))
    loss = {
        "suit frames missing": want_suits - suits,
        "tracker samples missing": want_trackers - trackers,
        "kernel drops": sum(s.get("kernel_drops", 0) for s in st.values()),
        "mvn lost": st["suits"].get("lost", 0) + st["suits"].get("incomplete", 0),
        "xbus lost": st["prop-imu"].get("lost", 0),
        "can lost": st["floor-imu"].get("lost", 0) + st["floor-imu"].get("incomplete", 0),
    }
    size = path.stat().st_size
    samples = sum(1 for _ in TakeReader(path).raw_packets()) if multiple == 1 else None
    path.unlink()
    return {"multiple": multiple, "wall_s": wall, "cpu_s": cpu, "cpu_pct": 100 * cpu / wall, "loss": loss,
            "lossless": all(v == 0 for v in loss.values()), "bytes": size, "raw_packets": samples, "threads": threads,
            "player": out.strip().splitlines()[-3:]}  # fmt: skip


def replay_throughput(scene: Path, workdir: Path, runs: int) -> dict:
    """Record the studio once (at 4x), then time replay to the pipeline against the take's own
    length (the suits' device-clock span)."""
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.capture.replay import replay_samples
    from dualhuman_builder.capture.recording import capture_take, plan_capture

    path = workdir / "replay.mcap"
    capture_take(plan_capture(sources=[f"sim://{scene}?devices=3"]), path, take="replay", sim_speed=4.0)
    frames = [c for c in read_columns(path).values() if c.sample_type == "SuitFrame"]
    span = max((c.columns["device_time_ns"][-1] - c.columns["device_time_ns"][0]) / 1e9 for c in frames)  # take time
    cols, objs = [], []
    for _ in range(runs):
        t = time.perf_counter()
        c = read_columns(path)
        cols.append(time.perf_counter() - t)
    n = sum(v.count for v in c.values())
    t = time.perf_counter()
    k = sum(1 for _ in replay_samples(path))
    objs.append(time.perf_counter() - t)
    return {"recorded_s": span, "samples": n, "columns_s": statistics.median(cols), "objects_s": objs[0],
            "columns_x": span / statistics.median(cols), "objects_x": span / objs[0], "objects": k}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="take length at 1x")
    ap.add_argument("--multiples", default="1,5,10,20", help="comma-separated multiples of real time to try")
    ap.add_argument("--fast-seconds", type=float, default=10.0, help="take length for multiples > 1 (scene time)")
    ap.add_argument("--runs", type=int, default=3, help="replay timing runs (median)")
    ap.add_argument("--skip-ingest", action="store_true")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/capture.json)")
    args = ap.parse_args()
    print(f"machine: {os.cpu_count()} CPUs, python {sys.version.split()[0]}")
    ingests = []
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        if not args.skip_ingest:
            for m in [float(x) for x in args.multiples.split(",")]:
                scene = scene_file(args.seconds if m == 1 else args.fast_seconds)
                r = ingest(scene, m, workdir)
                ingests.append(r)
                loss = ", ".join(f"{k} {v}" for k, v in r["loss"].items())
                print(f"ingest {m:g}x: {'LOSSLESS' if r['lossless'] else 'LOSS'} ({loss}); wall {r['wall_s']:.1f} s, "
                      f"recorder CPU {r['cpu_s']:.1f} s = {r['cpu_pct']:.0f} % of one core; "
                      f"{r['bytes'] / 1e6:.1f} MB written", flush=True)  # fmt: skip
                print("  CPU s by thread: " + ", ".join(f"{k} {v:.1f}" for k, v in r["threads"].items()), flush=True)
        r = replay_throughput(scene_file(args.fast_seconds), workdir, args.runs)
        print(f"replay of {r['recorded_s']:.1f} s ({r['samples']} samples): columns {r['columns_s']:.2f} s = "
              f"{r['columns_x']:.0f}x real time; sample objects {r['objects_s']:.2f} s = {r['objects_x']:.0f}x")  # fmt: skip
    lossless = [x["multiple"] for x in ingests if x["lossless"]]
    at_1x = [x["lossless"] for x in ingests if x["multiple"] == 1]
    highest = None  # the highest multiple tried up to which every multiple tried was lossless
    if ingests:
        highest = 0.0
        for x in sorted(ingests, key=lambda x: x["multiple"]):
            if not x["lossless"]:
                break
            highest = x["multiple"]
    figures = {
        "ingest": [{**x, "take_s": max(args.seconds if x["multiple"] == 1 else args.fast_seconds, MIN_SCENE_S), "mb": x["bytes"] / 1e6}
                   for x in ingests],
        "lossless_at_1x": at_1x[0] if at_1x else None,
        "highest_lossless_multiple": highest,
        "lossless_multiples": lossless,
        "replay": r,
    }  # fmt: skip
    tables = [Table("ingest on loopback (players, recorder and its decoding process share this machine's cores)",
                    ["multiple of real time", "take s", "lossless", "wall s", "recorder CPU % of one core", "MB written"],
                    [[f"{x['multiple']:g}x", f"ingest.{k}.take_s", f"ingest.{k}.lossless", f"ingest.{k}.wall_s",
                      f"ingest.{k}.cpu_pct", f"ingest.{k}.mb"] for k, x in enumerate(ingests)]),
              Table(f"replay of the take to the pipeline (median of {args.runs})", ["replay", "seconds", "x real time"],
                    [["columns (`read_columns`)", "replay.columns_s", "replay.columns_x"],
                     ["sample objects (`replay_samples`)", "replay.objects_s", "replay.objects_x"]])]  # fmt: skip
    goals = [Goal("lossless_at_1x", ">=", 1, label="lossless at 1x real time"),
             Goal("highest_lossless_multiple", ">=", GOAL_MULTIPLE, "x",
                  label="highest multiple of real time up to which every multiple tried was lossless")]  # fmt: skip
    path = write_results("capture", figures, params={k: v for k, v in vars(args).items() if k != "out"},
                         goals=goals, tables=tables, out=args.out,
                         notes="Loss counts every suit frame and tracker sample the devices sent, kernel drops, and "
                               "counter gaps of the MVN, Xbus and CAN streams.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
