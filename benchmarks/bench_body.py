"""Body-model throughput: bodies per second for forward and forward+backward, and peak memory.

This is the ceiling the fitter is measured against (``bench_fit.py`` reports its frame pairs per
second as a ratio to anny's rate); it has no goal of its own. Each configuration runs in a fresh
child process so that peak memory is its own: on CPU the peak resident set size (VmHWM, reset after
warm-up) and its increase over the resident size before the timed runs; on CUDA
``torch.cuda.max_memory_allocated``.

    .venv/bin/python benchmarks/bench_body.py                     # CPU, batches 1 16 64 256
    .venv/bin/python benchmarks/bench_body.py --device all        # CPU and CUDA when present
    .venv/bin/python benchmarks/bench_body.py --device cuda --batches 1,16,64,256,1024

Timing: 2 warm-up runs, then the median of ``--repeats`` timed runs (float32, default anny rig
and topology, random poses and shapes). Forward+backward differentiates the sum of squared
vertices with respect to pose (rotation vectors), shape and translation.

Writes ``benchmarks/results/body.json`` (``body_cuda.json`` when CUDA is among the devices;
``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

from results_file import Table, write_results

REPO = Path(__file__).resolve().parents[1]
MODES = {"forward": "forward", "forward+backward": "forward_backward"}  # mode -> key in the results


def _rss_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def worker(device: str, batch: int, mode: str, repeats: int) -> dict:
    import torch

    from dualhuman_builder.body.model import get_body_model

    torch.manual_seed(0)
    model = get_body_model(device)
    pose = 0.2 * torch.randn(batch, model.num_bones, 3, device=model.device)
    shape = torch.rand(batch, len(model.shape_names), device=model.device)
    transl = torch.randn(batch, 3, device=model.device)
    backward = mode == "forward+backward"

    def once():
        if backward:
            p, s, t = (x.clone().requires_grad_(True) for x in (pose, shape, transl))
            model(p, s, t).vertices.square().sum().backward()
        else:
            with torch.no_grad():
                model(pose, shape, transl)
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    for _ in range(2):
        once()
    rss_before = _rss_kib("VmRSS")
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    else:
        Path("/proc/self/clear_refs").write_text("5")  # reset the peak RSS (VmHWM) to the current RSS
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        once()
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    out = {"device": device, "batch": batch, "mode": mode, "median_s": med, "bodies_per_s": batch / med,
           "runs": len(times)}  # fmt: skip
    if device.startswith("cuda"):
        out["peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
        out["device_name"] = torch.cuda.get_device_name()
    else:
        out["peak_mb"] = _rss_kib("VmHWM") / 1024
        out["peak_increase_mb"] = (_rss_kib("VmHWM") - rss_before) / 1024
        out["threads"] = torch.get_num_threads()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="cpu, cuda, or all (cpu and, when present, cuda)")
    ap.add_argument("--batches", default="1,16,64,256")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", "--json", type=Path, default=None,
                    help="results file (default benchmarks/results/body.json, or body_cuda.json with CUDA)")
    ap.add_argument("--_worker", nargs=3, metavar=("DEVICE", "BATCH", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args._worker:
        print(json.dumps(worker(args._worker[0], int(args._worker[1]), args._worker[2], args.repeats)))
        return

    import torch

    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    if "cuda" in devices and not torch.cuda.is_available():
        print("CUDA not available: skipping the GPU figures")
        devices.remove("cuda")
    results = []
    env = {**os.environ, "PYTHONPATH": f"{REPO}:{os.environ.get('PYTHONPATH', '')}"}
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}")
    print(f"{'device':6s} {'batch':>5s} {'mode':17s} {'bodies/s':>10s} {'ms/batch':>9s} {'peak MB':>9s} {'+MB':>7s}")
    for device in devices:
        for batch in [int(b) for b in args.batches.split(",")]:
            for mode in ("forward", "forward+backward"):
                cmd = [sys.executable, __file__, "--repeats", str(args.repeats), "--_worker", device, str(batch), mode]
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                if proc.returncode != 0:
                    print(f"{device} batch {batch} {mode}: failed\n{proc.stderr[-2000:]}")
                    continue
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                results.append(r)
                extra = f"{r['peak_increase_mb']:7.0f}" if "peak_increase_mb" in r else ""
                print(f"{device:6s} {batch:5d} {mode:17s} {r['bodies_per_s']:10.1f} {1000 * r['median_s']:9.1f} "
                      f"{r['peak_mb']:9.0f} {extra}")  # fmt: skip
    if not results:
        raise SystemExit("no configuration ran: nothing to write")
    figures: dict = {}
    for r in results:
        figures.setdefault(r["device"], {}).setdefault(str(r["batch"]), {})[MODES[r["mode"]]] = r
    tables = []
    for device in figures:
        mem = "peak GPU MB (max_memory_allocated)" if device.startswith("cuda") else "peak RSS MB"
        tables.append(Table(f"{device}: bodies per second (median of {args.repeats})",
                            ["batch", "forward bodies/s", "forward+backward bodies/s", f"{mem}, forward",
                             f"{mem}, forward+backward"],
                            [[b, f"{device}.{b}.forward.bodies_per_s", f"{device}.{b}.forward_backward.bodies_per_s",
                              f"{device}.{b}.forward.peak_mb", f"{device}.{b}.forward_backward.peak_mb"]
                             for b in figures[device]]))  # fmt: skip
    name = "body_cuda" if "cuda" in devices else "body"
    path = write_results(name, figures, params={"devices": devices, "batches": args.batches, "repeats": args.repeats,
                                                "torch_threads": torch.get_num_threads()},
                         tables=tables, out=args.out,
                         notes="The ceiling for bench_fit's fit/anny ratio; no goal of its own.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
