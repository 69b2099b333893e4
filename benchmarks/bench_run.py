"""`dualhuman synth` + `dualhuman run` on many short synthetic takes: takes per hour through the full
path and through the ground-truth path, the local executor and Ray on a local Ray cluster (a head
and its worker processes, started by the benchmark) on the same takes, CPU utilisation over each
run, peak memory per worker, Ray's overhead against the local executor in the same run, and what
the quality gates flag on the set.

The takes (``--takes`` short takes over ``--types``, no long takes, ``--preset`` device errors,
``--fps``) are made once with ``dualhuman synth`` (the full path: each studio day's calibration
take, then scene, devices and capture; timed apart) into a base workspace; each executor runs
``dualhuman run --until UNTIL`` on a fresh copy of it, for the takes synth made, in the order
local, Ray, local, Ray (the first run also warms the machine's file caches, and runs of a minute
vary by tens of percent); Ray's overhead compares the faster run of each executor. Each run records
the stage runs it left done (``stages_done``), so the runs' work can be compared. A take whose scene meets no quality contract in its draws is
counted (``failed_takes``) and left out of the runs, as ``synth`` goes on without it; takes per
hour count the takes delivered (``takes``). The full path's takes per hour count making the takes
and the faster local run. The ground-truth path (``dualhuman synth --path ground-truth``, scene
straight to a verified export, ``--gt-jobs`` worker processes) runs on the same plan arguments with
one pair per take. CPU utilisation of the local executor is the CPU
time of the run's own processes (the driver and its workers) over the wall time of all cores, so
other load on the machine can only lower it; ``system_busy`` is the share of all CPUs' time not idle
over the run (/proc/stat), for every executor; peak memory per worker is the largest VmHWM of the local workers
(``dualhuman_builder.batch.worker``) or Ray's task workers (``ray::``), sampled every 0.5 s; ``cpu_s``
splits the run's CPU seconds between those workers, Ray's own processes (raylet, GCS, agents) and,
for Ray, the driver, to show where Ray's overhead goes.

    python benchmarks/bench_run.py --takes 24
    python benchmarks/bench_run.py --takes 2 --out /tmp/run.json     # a quick check
    python benchmarks/bench_run.py --takes 24 --keep /tmp/run-takes   # and keep the made takes
"""

from __future__ import annotations

import argparse
import os
import resource
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


#: Command-line parts of Ray's own processes (raylet, GCS, its agents and monitors), not its task workers.
RAY_DAEMON_MARKS = ("raylet", "gcs_server", "/ray/", "ray.", "dashboard", "log_monitor", "monitor.py")


def _cpu_s(proc: Path) -> float:
    """User + system CPU seconds of a process so far (/proc/PID/stat)."""
    fields = (proc / "stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Sampler:
    """Every 0.5 s: the peak VmHWM (bytes) of the processes whose command line contains ``marker``
    (the workers), and the CPU seconds each process spent since the sampler started, summed by kind:
    ``workers``, ``ray_daemons`` (:data:`RAY_DAEMON_MARKS`). A process's CPU after its last sample is
    not seen (at most 0.5 s of it)."""

    def __init__(self, marker: str):
        self.marker, self.peaks, self.stop = marker, {}, threading.Event()
        self.base: dict[str, float] = {}
        self.cpu: dict[str, tuple[str, float]] = {}  # pid -> (kind, CPU seconds since start)
        self.thread = threading.Thread(target=self.loop, daemon=True)

    def kind(self, cmd: str) -> str | None:
        if self.marker in cmd:
            return "workers"
        return "ray_daemons" if any(m in cmd for m in RAY_DAEMON_MARKS) else None

    def scan(self, first: bool = False) -> None:
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit() or proc.name == str(os.getpid()):
                continue
            try:
                cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                kind = self.kind(cmd)
                if kind is None:
                    continue
                used = _cpu_s(proc)
                if first:
                    self.base[proc.name] = used
                    continue
                self.cpu[proc.name] = (kind, used - self.base.get(proc.name, 0.0))
                if kind == "workers":
                    for line in (proc / "status").read_text().splitlines():
                        if line.startswith("VmHWM:"):
                            self.peaks[proc.name] = max(self.peaks.get(proc.name, 0), int(line.split()[1]) * 1024)
            except (OSError, ValueError, IndexError):
                continue

    def cpu_by_kind(self) -> dict[str, float]:
        out: dict[str, float] = {"workers": 0.0, "ray_daemons": 0.0}
        for kind, used in self.cpu.values():
            out[kind] += used
        return {k: round(v, 1) for k, v in out.items()}

    def loop(self) -> None:
        while not self.stop.wait(0.5):
            self.scan()

    def __enter__(self):
        self.scan(first=True)
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()
        self.scan()


def failed_lines(stdout: str) -> list[str]:
    """The takes ``dualhuman synth`` reported ``FAILED`` (no scene met the quality contract), in order."""
    import re

    names = (re.search(r"\b([SC]\d{3,})\b", ln.split(": FAILED: ")[0]) for ln in stdout.splitlines() if ": FAILED: " in ln)
    return [m.group(1) for m in names if m]


def timed_run(ws: Path, args, executor: str, address: str | None, marker: str, takes: list[str]) -> dict:
    """``dualhuman run`` of ``takes`` (the ones synth made: a take whose scene failed is not run again,
    its calibration take comes with it), timed, with CPU and memory figures."""
    cmd = [sys.executable, "-c", "from dualhuman_builder.cli import main, run; main()", "run", str(ws),
           "--fps", str(args.fps), "--executor", executor]  # fmt: skip
    for t in takes:
        cmd += ["--take", t]
    if args.until:
        cmd += ["--until", args.until]
    if address:
        cmd += ["--address", address]
    b0, t0 = cpu_times()
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.perf_counter()
    with Sampler(marker) as sampler:
        r = subprocess.run(cmd, capture_output=True, text=True, env=RAY_ENV, check=False)
    seconds = time.perf_counter() - w0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    b1, t1 = cpu_times()
    own_cpu_s = (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)
    if r.returncode != 0:
        raise SystemExit(f"{executor} run failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    peak = max(sampler.peaks.values(), default=0)
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(ws, readonly=True) as w:  # the work each run did, to compare: stage runs done
        done = sum(1 for t in w.takes() for s in ("sync", "fuse", "fit", "contacts", "render", "sheet")
                   if (rec := w.stage_record(s, t)) is not None and rec.get("status") == "done")  # fmt: skip
    return {"seconds": round(seconds, 2), "takes": len(takes), "takes_per_hour": round(len(takes) * 3600 / seconds, 1),
            "stages_done": done,
            "system_busy": round((b1 - b0) / max(1, t1 - t0), 3),
            # the run's own processes (the driver and the local workers it waits for; Ray's workers belong
            # to the raylet, so for Ray this counts the driver only): other load on the machine lowers it
            "cpu_utilisation": round(own_cpu_s / (seconds * (os.cpu_count() or 1)), 3) if executor == "local" else None,
            "workers_seen": len(sampler.peaks),
            # CPU seconds of the workers and of Ray's own processes over the run, and the driver's
            "cpu_s": {**sampler.cpu_by_kind(), "driver": round(own_cpu_s, 1) if executor != "local" else None},
            "peak_worker_memory_mib": round(peak / 2**20, 1)}  # fmt: skip


def gate_counts(ws: Path, cli: list[str]) -> dict:
    """What the quality gates flagged on the run's takes: takes checked and flagged, flags per gate."""
    import json

    r = subprocess.run([*cli, "gates", str(ws), "--json"], capture_output=True, text=True, check=False)
    report = json.loads(r.stdout)
    takes = report if isinstance(report, dict) else {}
    per_gate: dict[str, int] = {}
    flagged = 0
    for entry in takes.values():
        flags = entry.get("flags", []) if isinstance(entry, dict) else []
        flagged += bool(flags)
        for f in flags:
            per_gate[f["gate"]] = per_gate.get(f["gate"], 0) + 1
    return {"takes_checked": len(takes), "takes_flagged": flagged, "flags_per_gate": dict(sorted(per_gate.items()))}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_tables(figures: dict, params: dict) -> list[Table]:
    """The results file's tables, from its ``figures`` and ``params``: throughput and memory per run,
    where each run's CPU seconds went, and the takes lost (no scene met its contract)."""
    runs = [("run, local executor", "local"), ("run, Ray (local head)", "ray"),
            ("run, local executor again", "local_again"), ("run, Ray again", "ray_again")]  # fmt: skip
    runs = [(label, key) for label, key in runs if key in figures]
    rows = [["make the takes (synth, full path)", "make_takes.seconds", "make_takes.takes_per_hour", "", ""]]
    rows += [[label, f"{k}.seconds", f"{k}.takes_per_hour", f"{k}.cpu_utilisation", f"{k}.peak_worker_memory_mib"]
             for label, k in runs]  # fmt: skip
    rows.append(["full path: synth + run (local)", "full_path.seconds", "full_path.takes_per_hour", "", ""])
    rows.append(["ground-truth path: synth to a verified export", "ground_truth_path.seconds",
                 "ground_truth_path.takes_per_hour", "", ""])  # fmt: skip
    p = params
    return [Table(f"{p['takes']} short takes ({p['types']}, {p['preset']}, {p['fps']:g} fps), run until "
                  f"{p['until'] or 'sheet'}", ["", "s", "takes/h", "CPU utilisation", "peak MiB per worker"], rows),
            Table("Where each run's CPU seconds went", ["", "workers", "Ray's own processes", "Ray's driver"],
                  [[label, f"{k}.cpu_s.workers", f"{k}.cpu_s.ray_daemons", f"{k}.cpu_s.driver"] for label, k in runs]),
            Table("Takes lost (no scene met its quality contract in its draws)", ["", "takes lost", "which"],
                  [["full path", "make_takes.failed_takes", "make_takes.failed"],
                   ["ground-truth path", "ground_truth_path.failed_takes", "ground_truth_path.failed"]])]  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--takes", type=int, default=24)
    ap.add_argument("--types", default="handshake,high_five,push,pat_on_back,hug,dance_turn")
    ap.add_argument("--seed", type=int, default=1, help="seed of the synthetic plan")
    ap.add_argument("--preset", default="mixed", help="device errors of the takes: ideal, realistic or mixed")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--until", default="contacts", help="last stage of the run ('' for every stage; render at its "
                    "defaults costs 8 views x every frame at 512 px, see results/render.json)")
    ap.add_argument("--speed", type=float, default=1.0, help="capture speed of the simulated devices (above 1 the host clock the "
                    "recorder stamps runs slower than the devices', which the sync cannot align: every take is flagged)")
    ap.add_argument("--no-ray", action="store_true")
    ap.add_argument("--gt-jobs", type=int, default=None, help="worker processes of the ground-truth path (default: "
                    "synth's, one per CPU)")
    ap.add_argument("--keep", type=Path, default=None, help="keep a copy of the made takes (the full path's base "
                    "workspace) in KEEP/base")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.gt_jobs is None:
        from dualhuman_builder.batch.executors import default_workers

        args.gt_jobs = default_workers()

    tmp = Path(tempfile.mkdtemp(prefix="bench-run-"))
    cli = [sys.executable, "-m", "dualhuman_builder"]
    plan_args = ["--takes", str(args.takes), "--seed", str(args.seed), "--types", args.types, "--fps", str(args.fps),
                 "--long-share", "0"]  # fmt: skip
    try:
        base = tmp / "base"
        t0 = time.perf_counter()
        made = subprocess.run([*cli, "synth", str(base), *plan_args, "--preset", args.preset, "--speed", str(args.speed)],
                              capture_output=True, text=True, check=False)  # fmt: skip
        make_s = time.perf_counter() - t0
        failed = failed_lines(made.stdout)  # a take whose scene met no contract: counted, the rest go on
        if made.returncode not in (0, 1) or (made.returncode == 1 and not failed):
            raise SystemExit(f"synth failed ({made.returncode}):\n{made.stdout[-3000:]}\n{made.stderr[-3000:]}")
        from dualhuman_builder.sim.synth import load_plan

        takes = [t["take"] for t in load_plan(base)["takes"] if t["take"] not in failed and t["mounts_from"] not in failed]
        figures = {"make_takes": {"seconds": round(make_s, 1), "takes": len(takes),
                                  "takes_per_hour": round(len(takes) * 3600 / make_s, 1),
                                  "calibration_takes": made.stdout.count("calibration take C"),
                                  "failed_takes": len(failed), "failed": failed}}  # fmt: skip
        if args.keep:
            shutil.copytree(base, args.keep / "base", dirs_exist_ok=True)
        shutil.copytree(base, tmp / "local")
        figures["local"] = timed_run(tmp / "local", args, "local", None, "dualhuman_builder.batch.worker", takes)
        figures["gates"] = gate_counts(tmp / "local", cli)
        if not args.no_ray:
            ray_bin = str(Path(sys.executable).with_name("ray"))

            def ray_run(name: str) -> dict:
                shutil.copytree(base, tmp / name)
                port = free_port()
                subprocess.run([ray_bin, "start", "--head", "--port", str(port), "--include-dashboard=false"],
                               check=True, capture_output=True, env=RAY_ENV)  # fmt: skip
                try:
                    return timed_run(tmp / name, args, "ray", f"127.0.0.1:{port}", "ray::", takes)
                finally:
                    subprocess.run([ray_bin, "stop", "--force"], capture_output=True, env=RAY_ENV, check=False)

            # local, Ray, local, Ray: each executor runs once more after the other (the first run also
            # warms the machine's file caches), and the overhead compares the faster run of each
            figures["ray"] = ray_run("ray")
            shutil.copytree(base, tmp / "local-again")
            figures["local_again"] = timed_run(tmp / "local-again", args, "local", None, "dualhuman_builder.batch.worker",
                                              takes)  # fmt: skip
            figures["ray_again"] = ray_run("ray-again")
            local_s = min(figures["local"]["seconds"], figures["local_again"]["seconds"])
            ray_s = min(figures["ray"]["seconds"], figures["ray_again"]["seconds"])
            figures["ray_overhead"] = round(ray_s / local_s - 1, 3)
        else:
            local_s = figures["local"]["seconds"]
        full_s = make_s + local_s
        figures["full_path"] = {"seconds": round(full_s, 1), "takes": len(takes),
                                "takes_per_hour": round(len(takes) * 3600 / full_s, 1)}  # fmt: skip
        t0 = time.perf_counter()
        gt = subprocess.run([*cli, "synth", str(tmp / "gt"), *plan_args, "--path", "ground-truth", "--takes-per-day", "1",
                             "--export", str(tmp / "gt" / "export"), "--jobs", str(args.gt_jobs)], capture_output=True, text=True,
                            check=False)  # fmt: skip
        gt_s = time.perf_counter() - t0
        gt_failed = failed_lines(gt.stdout)
        if gt.returncode not in (0, 1) or (gt.returncode == 1 and not gt_failed):
            raise SystemExit(f"ground-truth synth failed ({gt.returncode}):\n{gt.stdout[-3000:]}\n{gt.stderr[-3000:]}")
        gt_takes = args.takes - len(gt_failed)
        figures["ground_truth_path"] = {"seconds": round(gt_s, 1), "takes": gt_takes, "jobs": args.gt_jobs,
                                        "takes_per_hour": round(gt_takes * 3600 / gt_s, 1),
                                        "failed_takes": len(gt_failed), "failed": gt_failed}  # fmt: skip
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    goals = [Goal("local.cpu_utilisation", ">=", 0.85, "", "CPU utilisation, local executor")]
    if "ray_overhead" in figures:
        goals.append(Goal("ray_overhead", "<=", 0.10, "", "Ray's time over the local executor's, minus 1"))
    tables = run_tables(figures, vars(args))
    path = write_results("run", figures, params=vars(args), goals=goals, tables=tables, out=args.out)
    print(figures)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
