"""`dualhuman run` on many short simulated takes: takes per hour with the local executor and with Ray
on a local Ray cluster (a head and its worker processes, started by the benchmark) on the same
takes, CPU utilisation over each run, peak memory per worker, and Ray's overhead against the local
executor in the same run. The local executor runs once more after Ray (the first run also warms the machine's file
caches); the overhead is against the faster local run, and each run records the stage runs it left done
(``stages_done``), so the runs' work can be compared.

The takes (``--takes`` of ``--type``, seeds 0..N-1, ``--fps``) are made once with ``dualhuman sim
take`` into a base workspace (timed apart); each executor runs ``dualhuman run --until UNTIL`` on
a fresh copy of it. CPU utilisation is the share of all CPUs' time not idle over the run
(/proc/stat); peak memory per worker is the largest VmHWM of the local workers
(``dualhuman_builder.batch.worker``) or Ray's task workers (``ray::``), sampled every 0.5 s.

    python benchmarks/bench_run.py --takes 24
    python benchmarks/bench_run.py --takes 2 --out /tmp/run.json     # a quick check
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import Goal, Table, write_results

#: The benchmark's Ray cluster is local to this machine and its run: no token authentication.
RAY_ENV = {**os.environ, "RAY_AUTH_MODE": "disabled"}


def cpu_times() -> tuple[int, int]:
    """(busy, total) jiffies of all CPUs (/proc/stat)."""
    with open("/proc/stat") as f:
        parts = [int(x) for x in f.readline().split()[1:]]
    idle = parts[3] + parts[4]
    return sum(parts) - idle, sum(parts)


class Sampler:
    """Peak VmHWM (bytes) of the processes whose command line contains ``marker``, every 0.5 s."""

    def __init__(self, marker: str):
        self.marker, self.peaks, self.stop = marker, {}, threading.Event()
        self.thread = threading.Thread(target=self.loop, daemon=True)

    def loop(self) -> None:
        while not self.stop.wait(0.5):
            for proc in Path("/proc").iterdir():
                if not proc.name.isdigit():
                    continue
                try:
                    cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                    if self.marker not in cmd:
                        continue
                    for line in (proc / "status").read_text().splitlines():
                        if line.startswith("VmHWM:"):
                            self.peaks[proc.name] = max(self.peaks.get(proc.name, 0), int(line.split()[1]) * 1024)
                except OSError:
                    continue

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def timed_run(ws: Path, args, executor: str, address: str | None, marker: str) -> dict:
    cmd = [sys.executable, "-c", "from dualhuman_builder.cli import main, run; main()", "run", str(ws),
           "--fps", str(args.fps), "--executor", executor]  # fmt: skip
    if args.until:
        cmd += ["--until", args.until]
    if address:
        cmd += ["--address", address]
    b0, t0 = cpu_times()
    w0 = time.perf_counter()
    with Sampler(marker) as sampler:
        r = subprocess.run(cmd, capture_output=True, text=True, env=RAY_ENV, check=False)
    seconds = time.perf_counter() - w0
    b1, t1 = cpu_times()
    if r.returncode != 0:
        raise SystemExit(f"{executor} run failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    peak = max(sampler.peaks.values(), default=0)
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(ws, readonly=True) as w:  # the work each run did, to compare: stage runs done
        done = sum(1 for t in w.takes() for s in ("sync", "fuse", "fit", "contacts", "render", "sheet")
                   if (rec := w.stage_record(s, t)) is not None and rec.get("status") == "done")  # fmt: skip
    return {"seconds": round(seconds, 2), "takes_per_hour": round(args.takes * 3600 / seconds, 1), "stages_done": done,
            "cpu_utilisation": round((b1 - b0) / max(1, t1 - t0), 3), "workers_seen": len(sampler.peaks),
            "peak_worker_memory_mib": round(peak / 2**20, 1)}  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--takes", type=int, default=24)
    ap.add_argument("--type", default="high_five")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--until", default="fit", help="last stage of the run ('' for every stage)")
    ap.add_argument("--speed", type=float, default=8.0, help="capture speed of the simulated devices")
    ap.add_argument("--no-ray", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="bench-run-"))
    try:
        base = tmp / "base"
        t0 = time.perf_counter()
        for i in range(args.takes):
            subprocess.run([sys.executable, "-m", "dualhuman_builder", "sim", "take", str(base), "--take", f"T{i:03d}",
                            "--type", args.type, "--seed", str(i), "--fps", str(args.fps), "--speed", str(args.speed)],
                           check=True, capture_output=True)  # fmt: skip
        make_s = time.perf_counter() - t0
        figures = {"make_takes": {"seconds": round(make_s, 1), "takes_per_hour": round(args.takes * 3600 / make_s, 1)}}
        shutil.copytree(base, tmp / "local")
        figures["local"] = timed_run(tmp / "local", args, "local", None, "dualhuman_builder.batch.worker")
        if not args.no_ray:
            shutil.copytree(base, tmp / "ray")
            port = free_port()
            ray_bin = str(Path(sys.executable).with_name("ray"))
            subprocess.run([ray_bin, "start", "--head", "--port", str(port), "--include-dashboard=false"],
                           check=True, capture_output=True, env=RAY_ENV)  # fmt: skip
            try:
                figures["ray"] = timed_run(tmp / "ray", args, "ray", f"127.0.0.1:{port}", "ray::")
            finally:
                subprocess.run([ray_bin, "stop", "--force"], capture_output=True, env=RAY_ENV, check=False)
            # the local executor once more, after Ray: the first run also warms the machine's file caches
            shutil.copytree(base, tmp / "local-again")
            figures["local_again"] = timed_run(tmp / "local-again", args, "local", None, "dualhuman_builder.batch.worker")
            local_s = min(figures["local"]["seconds"], figures["local_again"]["seconds"])
            figures["ray_overhead"] = round(figures["ray"]["seconds"] / local_s - 1, 3)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    goals = [Goal("local.cpu_utilisation", ">=", 0.85, "", "CPU utilisation, local executor")]
    if "ray_overhead" in figures:
        goals.append(Goal("ray_overhead", "<=", 0.10, "", "Ray's time over the local executor's, minus 1"))
    rows = [["make the takes (sim take)", "make_takes.seconds", "make_takes.takes_per_hour", "", ""],
            ["run, local executor", "local.seconds", "local.takes_per_hour", "local.cpu_utilisation",
             "local.peak_worker_memory_mib"]]  # fmt: skip
    if "ray" in figures:
        rows.append(["run, Ray (local head)", "ray.seconds", "ray.takes_per_hour", "ray.cpu_utilisation",
                     "ray.peak_worker_memory_mib"])  # fmt: skip
        rows.append(["run, local executor again", "local_again.seconds", "local_again.takes_per_hour",
                     "local_again.cpu_utilisation", "local_again.peak_worker_memory_mib"])  # fmt: skip
    tables = [Table(f"{args.takes} takes ({args.type}, {args.fps:g} fps), until {args.until or 'sheet'}",
                    ["", "s", "takes/h", "CPU utilisation", "peak MiB per worker"], rows)]  # fmt: skip
    path = write_results("run", figures, params=vars(args), goals=goals, tables=tables, out=args.out)
    print(figures)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
