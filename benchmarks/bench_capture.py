"""Capture benchmarks: live ingestion on loopback (zero loss at 1x, the highest multiple without
loss, CPU of the recorder), and replay throughput to the pipeline.

The load is the studio of the issue: two suits at 240 Hz (23 segments, types 02 + 25, both on one
MVN port), twelve trackers at 250 Hz, an Xbus MTi at 400 Hz on a pseudo-terminal and a CAN MTi at
100 Hz on python-can's virtual bus, simulated from a generated handshake padded to the take length.
The UDP and serial devices play from a child process, so the recorder's process does only the
recording (the in-process CAN player is small). The devices start playing once the recorder runs
(the child answers the Xbus configuration dialogue first and waits for a go), so what is measured
is the recorder, not how long it takes to start. The CPU figure is the recorder process's
user+system time over the wall time, and the decoding process's CPU is listed per thread. On a
2-core machine the players, the recorder and its decoding process share the two cores, so at high
multiples the simulated devices themselves compete with the recorder.

Loss is counted against what the devices sent: every suit frame and tracker sample simulated must
be recorded (kernel drops, MVN sample-counter gaps, incomplete messages all zero), and the Xbus and
CAN streams must each be recorded whole (every sample sent, no packet-counter gap). The receive buffer
the kernel granted each UDP socket is recorded beside the figures (``rcvbuf``).

    .venv/bin/python benchmarks/bench_capture.py                      # 60 s at 1x, then multiples
    .venv/bin/python benchmarks/bench_capture.py --seconds 10 --multiples 1,10,20,40
    .venv/bin/python benchmarks/bench_capture.py --baseline HEAD~1    # each multiple also on older code

``--baseline REF`` records each multiple a second time, just before, with the capture code of the
git revision ``REF`` (its ``dualhuman_builder`` run from a temporary copy, the same players and
loss counting), so that old and new are compared side by side on the same machine at the same
time; ``--rcvbuf BYTES`` sets the receive buffer asked for (what a machine whose
``net.core.rmem_max`` is low grants, e.g. 212992, shows the readers' pacing).

Goals: lossless at 1x, and lossless up to 20x real time (the highest multiple tried without loss).
Replay to the pipeline is timed against the take's own length (no goal). Writes
``benchmarks/results/capture.json`` (``--out`` elsewhere); the generated scenes are cached in
``benchmarks/cache/``.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The tree whose ``dualhuman_builder`` is measured: this checkout, or a baseline's copy
#: (``--baseline``: the child run is told by this environment variable).
CODE = Path(os.environ.get("DUALHUMAN_BENCH_CODE", ROOT))
sys.path.insert(0, str(CODE))
sys.path.insert(1, str(ROOT / "benchmarks"))

from results_file import Goal, Table, write_results  # noqa: E402

CACHE = ROOT / "benchmarks" / "cache"
#: The highest multiple of real time the studio must record without loss.
GOAL_MULTIPLE = 20.0
#: The shortest scene generated (s): shorter takes are played from a scene this long.
MIN_SCENE_S = 4.0
#: Receive buffer asked for each UDP source (bytes), unless --rcvbuf says otherwise.
RCVBUF = 32 << 20

#: The device side, run in a child process from this checkout: the Xbus MTi answers the
#: configuration dialogue on a pty at once; the suits, trackers and the MTi's samples start on "go".
PLAYER = r"""
import sys
sys.path.insert(0, sys.argv[1])
from dualhuman_builder.capture.wire.xbus import SimulatedMti
from dualhuman_builder.sim.devices import Player, PtyMaster, SerialPlayer, UdpPlayer, mvn_packets, tracker_packets
from dualhuman_builder.sim.scenes import Scene
from dualhuman_builder.sim.studio import simulate_studio

scene, mvn_port, vive_port, speed = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
studio = simulate_studio(Scene.load(scene).sequence, seed=3)
pty = PtyMaster(drop_when_full=True)
mti = SimulatedMti()
dialogue = SerialPlayer(pty, mti=mti, linger_s=600.0).start()
players = {"mvn": UdpPlayer(("127.0.0.1", mvn_port), speed=speed),
           "trackers": UdpPlayer(("127.0.0.1", vive_port), speed=speed),
           "xbus": SerialPlayer(pty, speed=speed, mti=mti, linger_s=0.2)}
players["xbus"].add_samples(studio.imus["mti-xbus"], clock="host")
for suit in studio.suits:
    players["mvn"].add(mvn_packets(suit, clock="host"))
for tr in studio.trackers:
    players["trackers"].add(tracker_packets(tr, clock="host"))
for p in players.values():
    p.packets  # merged before the go
print("serial port", pty.slave_path, flush=True)
sys.stdin.readline()
dialogue.stop()
dialogue.join()
Player.share_clock(players.values())
for p in players.values():
    p.start()
for name, p in players.items():
    r = p.join()
    print(f"{name}: sent {r.sent} packets ({r.bytes_sent} bytes) in {r.elapsed_s:.2f} s", flush=True)
if pty.dropped_bytes:
    print(f"xbus: {pty.dropped_bytes} bytes dropped: nobody read the pty fast enough", flush=True)
print("played", flush=True)
sys.stdin.readline()  # the pty stays open until the recorder is done with it (closing it is an unplugged MTi)
pty.close()
"""


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


def _granted(src) -> int | None:
    import socket

    got = getattr(src, "buffer_bytes", None)
    if got is None and hasattr(src, "sock"):
        got = src.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    return got


def ingest(scene: Path, multiple: float, workdir: Path, rcvbuf: int = RCVBUF) -> dict:
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
    mvn = open_source(f"mvn+udp://127.0.0.1:0?rcvbuf={rcvbuf}")
    vive = open_source(f"vive+udp://127.0.0.1:0?rcvbuf={rcvbuf}")
    channel = f"bench-{uuid.uuid4().hex[:6]}"
    can_src = open_source(f"mti+can://virtual/{channel}?device=mti-can")
    child = subprocess.Popen([sys.executable, "-c", PLAYER, str(ROOT), str(scene), str(mvn.port), str(vive.port),
                              str(multiple)], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)  # fmt: skip
    pty_path = None
    lines: list[str] = []
    while pty_path is None:
        line = child.stdout.readline()
        if not line:
            raise RuntimeError("the players ended before opening their serial port:\n" + "".join(lines))
        lines.append(line)
        m = re.search(r"serial port (\S+)", line)
        if m:
            pty_path = m.group(1)

    def collect() -> None:
        for line in child.stdout:
            lines.append(line)

    threading.Thread(target=collect, daemon=True).start()
    bus = can.Bus(interface="virtual", channel=channel)
    can_player = CanPlayer(bus, speed=multiple).add_samples(studio.imus["mti-can"], clock="host")
    _ = can_player.packets
    xbus = open_source(f"xbus://{pty_path}?device=mti-xbus")  # the configuration dialogue
    path = workdir / f"ingest_{multiple:g}x.mcap"
    rec = Recorder(path, take=f"bench{multiple:g}", sources=[("suits", mvn), ("trackers", vive), ("prop-imu", xbus),
                                                            ("floor-imu", can_src)])  # fmt: skip
    c0, t0, main0 = cpu_s(), time.monotonic(), time.thread_time()
    done = []

    def until():
        if not done:  # the recorder runs: the devices start
            done.append(None)
            child.stdin.write("go\n")
            child.stdin.flush()
            can_player.start()
            return False
        if "played\n" not in lines or can_player.running:
            return False
        if done[-1] is None:
            done.append(time.monotonic())
        return time.monotonic() - done[-1] > 0.5

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
    granted = {"suits": _granted(mvn), "trackers": _granted(vive)}
    rec.close()
    bus.shutdown()
    child.stdin.close()
    child.wait()
    out = "".join(lines)
    st = result.source_stats
    per_topic = dict(result.samples_per_topic)
    suits = sum(n for t, n in per_topic.items() if t.startswith("suits/mvn/") and t.endswith("/SuitFrame"))
    trackers = sum(n for t, n in per_topic.items() if t.endswith("/TrackerSample"))
    want_suits = sum(v for k, v in counts.items() if k.startswith("suit/"))
    want_trackers = sum(int(studio.trackers[i].valid.size) for i in range(len(studio.trackers)))
    xbus_sent = re.search(r"xbus: sent (\d+) packets", out)
    imu = {src: sum(n for t, n in per_topic.items() if t.startswith(f"{src}/") and t.endswith("/ImuSample"))
           for src in ("prop-imu", "floor-imu")}  # fmt: skip
    loss = {
        "suit frames missing": want_suits - suits,
        "tracker samples missing": want_trackers - trackers,
        "kernel drops": sum(s.get("kernel_drops", 0) for s in st.values()),
        "mvn lost": st["suits"].get("lost", 0) + st["suits"].get("incomplete", 0),
        "xbus samples missing": (int(xbus_sent.group(1)) if xbus_sent else -1) - imu["prop-imu"],
        "xbus lost": st["prop-imu"].get("lost", 0),
        "can samples missing": len(studio.imus["mti-can"]) - imu["floor-imu"],
        "can lost": st["floor-imu"].get("lost", 0) + st["floor-imu"].get("incomplete", 0),
    }
    size = path.stat().st_size
    samples = sum(1 for _ in TakeReader(path).raw_packets()) if multiple == 1 else None
    path.unlink()
    return {"multiple": multiple, "wall_s": wall, "cpu_s": cpu, "cpu_pct": 100 * cpu / wall, "loss": loss,
            "lossless": all(v == 0 for v in loss.values()), "bytes": size, "raw_packets": samples, "threads": threads,
            "rcvbuf": granted, "error": result.error, "player": [ln for ln in out.splitlines() if ": " in ln][-4:]}  # fmt: skip


def resolve(ref: str) -> str:
    """The commit git revision ``ref`` names (``HEAD`` moves; the results keep the commit)."""
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", f"{ref}^{{commit}}"], capture_output=True,
                          text=True, check=True).stdout.strip()  # fmt: skip


def baseline_tree(ref: str, workdir: Path) -> Path:
    """``dualhuman_builder`` of git revision ``ref``, extracted under ``workdir``."""
    data = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "dualhuman_builder"], capture_output=True,
                          check=True).stdout  # fmt: skip
    out = workdir / "baseline"
    out.mkdir()
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(out, filter="data")
    return out


def ingest_baseline(tree: Path, scene: Path, multiple: float, workdir: Path, rcvbuf: int) -> dict:
    """:func:`ingest` in a child process that imports the capture code from ``tree``."""
    out = workdir / f"baseline_{multiple:g}x.json"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--ingest-one", str(multiple), "--scene", str(scene),
           "--rcvbuf", str(rcvbuf), "--ingest-json", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, env={**os.environ, "DUALHUMAN_BENCH_CODE": str(tree)}, capture_output=True,
                          text=True)  # fmt: skip
    if proc.returncode != 0 or not out.exists():
        raise RuntimeError(f"the baseline run at {multiple:g}x failed:\n{proc.stdout[-2000:]}{proc.stderr[-3000:]}")
    return json.loads(out.read_text())


def _print_ingest(r: dict, label: str = "") -> None:
    loss = ", ".join(f"{k} {v}" for k, v in r["loss"].items())
    print(f"ingest {r['multiple']:g}x{label}: {'LOSSLESS' if r['lossless'] else 'LOSS'} ({loss}); "
          f"wall {r['wall_s']:.1f} s, recorder CPU {r['cpu_s']:.1f} s = {r['cpu_pct']:.0f} % of one core; {r['bytes'] / 1e6:.1f} MB written; "
          f"rcvbuf granted {r['rcvbuf']}", flush=True)  # fmt: skip
    print("  CPU s by thread: " + ", ".join(f"{k} {v:.1f}" for k, v in r["threads"].items()), flush=True)


def highest_lossless(runs: list[dict]) -> float | None:
    """The highest multiple tried up to which every multiple tried was lossless (0 if 1x lost)."""
    if not runs:
        return None
    highest = 0.0
    for x in sorted(runs, key=lambda x: x["multiple"]):
        if not x["lossless"]:
            break
        highest = x["multiple"]
    return highest


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
    ap.add_argument("--skip-replay", action="store_true")
    ap.add_argument("--baseline", default=None, metavar="REF", help="also record each multiple with the capture "
                                                                    "code of this git revision, side by side")
    ap.add_argument("--rcvbuf", type=int, default=RCVBUF, help="receive buffer asked for each UDP source (bytes)")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/capture.json)")
    ap.add_argument("--ingest-one", type=float, default=None, help=argparse.SUPPRESS)  # a baseline's child run
    ap.add_argument("--scene", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--ingest-json", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.ingest_one is not None:
        with tempfile.TemporaryDirectory() as tmp:
            r = ingest(args.scene, args.ingest_one, Path(tmp), args.rcvbuf)
        args.ingest_json.write_text(json.dumps(r))
        return
    print(f"machine: {os.cpu_count()} CPUs, python {sys.version.split()[0]}")
    ingests, baseline = [], []
    r = None
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        if args.baseline:
            args.baseline = resolve(args.baseline)
        tree = baseline_tree(args.baseline, workdir) if args.baseline and not args.skip_ingest else None
        if not args.skip_ingest:
            for m in [float(x) for x in args.multiples.split(",")]:
                scene = scene_file(args.seconds if m == 1 else args.fast_seconds)
                if tree is not None:
                    b = ingest_baseline(tree, scene, m, workdir, args.rcvbuf)
                    baseline.append(b)
                    _print_ingest(b, f" [baseline {args.baseline}]")
                x = ingest(scene, m, workdir, args.rcvbuf)
                ingests.append(x)
                _print_ingest(x)
        if not args.skip_replay:
            r = replay_throughput(scene_file(args.fast_seconds), workdir, args.runs)
            print(f"replay of {r['recorded_s']:.1f} s ({r['samples']} samples): columns {r['columns_s']:.2f} s = "
                  f"{r['columns_x']:.0f}x real time; sample objects {r['objects_s']:.2f} s = {r['objects_x']:.0f}x")  # fmt: skip
    at_1x = [x["lossless"] for x in ingests if x["multiple"] == 1]

    def take_s(x):
        return max(args.seconds if x["multiple"] == 1 else args.fast_seconds, MIN_SCENE_S)

    figures = {
        "ingest": [{**x, "take_s": take_s(x), "mb": x["bytes"] / 1e6} for x in ingests],
        "lossless_at_1x": at_1x[0] if at_1x else None,
        "highest_lossless_multiple": highest_lossless(ingests),
        "lossless_multiples": [x["multiple"] for x in ingests if x["lossless"]],
        "replay": r,
    }
    if baseline:
        figures["baseline"] = {"ref": args.baseline, "ingest": [{**x, "take_s": take_s(x), "mb": x["bytes"] / 1e6}
                                                                for x in baseline],
                               "highest_lossless_multiple": highest_lossless(baseline)}  # fmt: skip
    rows = []
    for k, x in enumerate(ingests):
        row = [f"{x['multiple']:g}x", f"ingest.{k}.take_s", f"ingest.{k}.lossless", f"ingest.{k}.loss.kernel drops",
               f"ingest.{k}.wall_s", f"ingest.{k}.cpu_pct", f"ingest.{k}.mb"]  # fmt: skip
        if baseline:
            row[3:3] = [f"baseline.ingest.{k}.lossless", f"baseline.ingest.{k}.loss.kernel drops"]
        rows.append(row)
    columns = ["multiple of real time", "take s", "lossless", "kernel drops", "wall s", "recorder CPU % of one core",
               "MB written"]  # fmt: skip
    if baseline:
        columns[3:3] = [f"lossless, baseline {args.baseline}", "kernel drops, baseline"]
    tables = [Table("ingest on loopback (players, recorder and its decoding process share this machine's cores)",
                    columns, rows)]
    if r is not None:
        tables.append(Table(f"replay of the take to the pipeline (median of {args.runs})",
                            ["replay", "seconds", "x real time"],
                            [["columns (`read_columns`)", "replay.columns_s", "replay.columns_x"],
                             ["sample objects (`replay_samples`)", "replay.objects_s", "replay.objects_x"]]))  # fmt: skip
    goals = [Goal("lossless_at_1x", ">=", 1, label="lossless at 1x real time"),
             Goal("highest_lossless_multiple", ">=", GOAL_MULTIPLE, "x",
                  label="highest multiple of real time up to which every multiple tried was lossless")]  # fmt: skip
    notes = ("Loss counts every suit frame, tracker sample and IMU sample the devices sent, kernel drops, and counter "
             "gaps of the MVN, Xbus and CAN streams. The devices start once the recorder runs.")  # fmt: skip
    if baseline:
        notes += (f" The baseline columns are the same runs with the capture code of {args.baseline}, each just "
                  f"before the current code's run at that multiple; its highest lossless multiple: "
                  f"{figures['baseline']['highest_lossless_multiple']:g}x.")  # fmt: skip
    path = write_results("capture", figures, params={k: v for k, v in vars(args).items()
                                                     if k not in ("out", "ingest_one", "scene", "ingest_json")},
                         goals=goals, tables=tables, out=args.out, notes=notes)  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
