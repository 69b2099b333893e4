"""MVNX reading: our streaming ``read_mvnx`` against the PyPI ``mvnx`` package (0.2, ``MVNX(path)``,
which builds the whole ElementTree and parses every element it knows): seconds and peak memory.

Writes a 10-minute, 23-segment, 60 Hz MVNX file (``--mvnx-file``, default a temporary folder) with the
per-frame elements of a real export (orientation, position, velocity, acceleration,
angularVelocity, angularAcceleration, footContacts, sensorFreeAcceleration, sensorMagneticField,
sensorOrientation, jointAngle, jointAngleXZY, jointAngleErgo, centerOfMass — in MVN's order, which
the ``mvnx`` package relies on) and three calibration frames, values with 6 decimals as MVN writes
them. The motion is a 20 s simulated suit stream (``sim.suit``) repeated with running times.

Each reader runs ``--repeats`` times, alternating, each in a fresh subprocess; prints the median
seconds of the read (imports excluded), the child's peak RSS (``os.wait4`` rusage, ru_maxrss)
and its RSS after imports, and the ratios. Then one more child reads the file with both and
checks they agree.

    .venv/bin/python benchmarks/bench_mvnx.py [--minutes 10] [--repeats 3] [--mvnx-file FILE.mvnx]

Needs ``mvnx`` for the comparison (``.venv/bin/pip install -e '.[bench]'`` or ``pip install mvnx``);
without it, only ours runs. Writes ``benchmarks/results/mvnx.json`` (``--out`` elsewhere): both
readers' figures and the ratios ``mvnx`` / ours measured in the same run. No goals: the figures
back the choice of our importer over the package.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from results_file import Table, write_results

FPS = 60.0

CHILD = {
    "ours": """
import json, resource, sys, time
import numpy as np
from dualhuman_builder.capture.importers.mvnx import read_mvnx
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
mf = read_mvnx(sys.argv[1])
s = time.perf_counter() - t
print(json.dumps({"seconds": s, "base_kb": base, "frames": mf.num_frames, "numpy": np.__version__}))
""",
    "mvnx": """
import json, resource, sys, time
from mvnx import MVNX
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
m = MVNX(sys.argv[1])
s = time.perf_counter() - t
print(json.dumps({"seconds": s, "base_kb": base, "frames": int(m.orientation.shape[0])}))
""",
}

CHECK = """
import json, sys
import numpy as np
from mvnx import MVNX
from dualhuman_builder.capture.importers.mvnx import quat_ours_to_file, vec_ours_to_file
from dualhuman_builder.capture.importers.mvnx import read_mvnx
ours = read_mvnx(sys.argv[1])
T = ours.num_frames
theirs = MVNX(sys.argv[1])
diff = {
    "orientation": quat_ours_to_file(ours.track.orientations).reshape(T, -1) - theirs.orientation,
    "position": vec_ours_to_file(ours.track.positions).reshape(T, -1) - theirs.position,
    "jointAngle": ours.arrays["jointAngle"].reshape(T, -1) - theirs.jointAngle,
    "centerOfMass": vec_ours_to_file(ours.arrays["centerOfMass"].reshape(T, -1, 3)).reshape(T, -1) - theirs.centerOfMass,
}
print(json.dumps({k: float(np.abs(v).max()) for k, v in diff.items()}))
"""


def generate(path: Path, minutes: float) -> None:
    import numpy as np
    from scipy.spatial.transform import Rotation as R

    from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
    from dualhuman_builder.sim.files import ERGONOMIC_JOINTS, identity_pose, mvnx_arrays_from_suit, write_mvnx
    from dualhuman_builder.body.mapping import SEGMENT_TPOSE_FRAME
    from dualhuman_builder.sim.suit import simulate_suit
    from dualhuman_builder.tracks import SkeletonTrack

    # A rigid skeleton (bone vectors in a body at identity: +X left, +Y up, +Z forward) walking
    # in a circle, every joint swinging.
    bones = {"L5": (0, .1, 0), "L3": (0, .1, 0), "T12": (0, .1, 0), "T8": (0, .1, 0), "Neck": (0, .15, 0),
             "Head": (0, .1, 0), "RightShoulder": (-.03, .1, 0), "RightUpperArm": (-.15, 0, 0),
             "RightForeArm": (-.28, 0, 0), "RightHand": (-.2, 0, 0), "LeftShoulder": (.03, .1, 0),
             "LeftUpperArm": (.15, 0, 0), "LeftForeArm": (.28, 0, 0), "LeftHand": (.2, 0, 0),
             "RightUpperLeg": (-.09, -.02, 0), "RightLowerLeg": (0, -.42, 0), "RightFoot": (0, -.42, 0),
             "RightToe": (0, -.07, .14), "LeftUpperLeg": (.09, -.02, 0), "LeftLowerLeg": (0, -.42, 0),
             "LeftFoot": (0, -.42, 0), "LeftToe": (0, -.07, .14)}  # fmt: skip
    t = np.arange(int(20 * FPS) + 1) / FPS
    A = {"Pelvis": R.from_rotvec(np.outer(0.3 * t, [0, 1, 0]))}
    P = {"Pelvis": np.stack([np.sin(0.3 * t), 0.95 + 0.02 * np.sin(4 * t), np.cos(0.3 * t)], 1) * [2, 1, 2]}
    for k, s in enumerate(MVN_SEGMENTS[1:]):
        p = MVN_PARENTS[s]
        axis = [0, 0, 1] if "Arm" in s else [1, 0, 0]
        A[s] = A[p] * R.from_rotvec(np.outer(0.4 * np.sin(2 * np.pi * 0.9 * t + k), axis))
        P[s] = P[p] + A[p].apply(bones[s])
    B = R.from_matrix(SEGMENT_TPOSE_FRAME)
    ns = np.round(t * 1e9).astype(np.int64)
    gt = SkeletonTrack(MVN_SEGMENTS, np.stack([(A[s] * B).as_quat() for s in MVN_SEGMENTS], 1),
                       np.stack([P[s] for s in MVN_SEGMENTS], 1), ns, ns, actor="bench", fps=FPS)  # fmt: skip
    suit = simulate_suit(gt, rate_hz=FPS, seed=0)
    base, arrays = suit.to_track(), mvnx_arrays_from_suit(suit)
    frames = int(round(minutes * 60 * FPS))
    reps = -(-frames // base.num_frames)

    def tile(a):
        return np.concatenate([a] * reps)[:frames]

    t_ns = np.round(np.arange(frames) * 1e9 / FPS).astype(np.int64)
    track = SkeletonTrack(base.segment_names, tile(base.orientations), tile(base.positions), t_ns, t_ns,
                          actor="bench", fps=FPS)  # fmt: skip
    calibration = {"identity": identity_pose(base), "tpose": (base.orientations[0], base.positions[0]),
                   "tpose-isb": (base.orientations[1], base.positions[1])}  # fmt: skip
    write_mvnx(path, track, arrays={k: tile(v) for k, v in arrays.items()}, calibration=calibration,
               ergonomic_joints=ERGONOMIC_JOINTS, start_epoch_ms=1_700_000_000_000, float_format="%.6f")  # fmt: skip


def run_child(code: str, path: Path) -> dict:
    """Run ``code`` in a fresh interpreter; its JSON line plus its own peak RSS (os.wait4)."""
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=Path(__file__).resolve().parents[1])  # fmt: skip
    out, err = proc.stdout.read(), proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"child failed ({proc.returncode}):\n{err.decode()[-2000:]}")
    result = json.loads(out.decode().strip().splitlines()[-1])
    result["peak_kb"] = usage.ru_maxrss  # KiB on Linux
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--mvnx-file", type=Path, default=None,
                    help="MVNX file to write (reused if it exists); default: a temp dir")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/mvnx.json)")
    ap.add_argument("--no-check", action="store_true", help="Skip reading with both to compare their values.")
    ap.add_argument("--generate-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.out is not None and args.out.suffix.lower() == ".mvnx":
        ap.error("--out is the results file (.json); the MVNX file to write is --mvnx-file")
    if args.generate_only:  # in a child, so that this process stays small: a child's ru_maxrss
        generate(args.mvnx_file, args.minutes)  # starts at its parent's RSS when it was forked
        return

    tmp = None
    if args.mvnx_file is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_mvnx_")
        path = Path(tmp.name) / "bench.mvnx"
    else:
        path = args.mvnx_file
    if not path.exists():
        t0 = time.perf_counter()
        subprocess.run([sys.executable, __file__, "--generate-only", "--mvnx-file", str(path), "--minutes", str(args.minutes)],
                       check=True, cwd=Path(__file__).resolve().parents[1])  # fmt: skip
        print(f"wrote {path} in {time.perf_counter() - t0:.1f} s")
    size_mb = path.stat().st_size / 1e6
    with open(path, "rb") as f:  # warm the page cache for every reader alike
        while f.read(1 << 24):
            pass
    have_mvnx = importlib.util.find_spec("mvnx") is not None
    if not have_mvnx:
        print("the PyPI 'mvnx' package is not installed; running ours only. "
              "Install it with: .venv/bin/pip install -e '.[bench]'  (or: pip install mvnx)")  # fmt: skip
    names = ["ours", "mvnx"] if have_mvnx else ["ours"]
    runs: dict[str, list[dict]] = {n: [] for n in names}
    for _ in range(args.repeats):
        for n in names:
            runs[n].append(run_child(CHILD[n], path))
    frames = runs["ours"][0]["frames"]
    print(f"file: {path.name}, {size_mb:.1f} MB, {frames} normal frames x 23 segments at {FPS:g} Hz "
          f"({frames / FPS / 60:.1f} min), 14 per-frame elements, 3 calibration frames")  # fmt: skip
    print(f"machine: {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, numpy {runs['ours'][0]['numpy']}")
    label = {"ours": "dualhuman read_mvnx (streaming)", "mvnx": "mvnx 0.2 MVNX(path) (PyPI)"}
    med = {}
    figures: dict = {"file": {"mb": size_mb, "frames": frames, "minutes": frames / FPS / 60, "segments": 23, "hz": FPS}}
    print(f"{'reader':34s} {'seconds':>9s} {'peak RSS MB':>12s} {'RSS after imports MB':>21s}   (median of {args.repeats})")
    for n in names:
        s = statistics.median(r["seconds"] for r in runs[n])
        peak = statistics.median(r["peak_kb"] for r in runs[n]) / 1024
        base = statistics.median(r["base_kb"] for r in runs[n]) / 1024
        med[n] = (s, peak, base)
        figures[n] = {"seconds": s, "peak_rss_mb": peak, "rss_after_imports_mb": base, "mb_per_s": size_mb / s,
                      "runs_s": [r["seconds"] for r in runs[n]]}  # fmt: skip
        print(f"{label[n]:34s} {s:9.2f} {peak:12.0f} {base:21.0f}")
        if any(r["frames"] != frames for r in runs[n]):
            print(f"  warning: {n} read {[r['frames'] for r in runs[n]]} frames")
    if have_mvnx:
        (s_o, p_o, b_o), (s_m, p_m, b_m) = med["ours"], med["mvnx"]
        figures["mvnx_over_ours"] = {"seconds": s_m / s_o, "peak_rss": p_m / p_o,
                                     "peak_rss_above_imports": (p_m - b_m) / max(p_o - b_o, 1e-9)}  # fmt: skip
        print(f"mvnx / ours: time {s_m / s_o:.2f}x, peak RSS {p_m / p_o:.2f}x, "
              f"peak RSS above imports {(p_m - b_m) / max(p_o - b_o, 1e-9):.2f}x; "
              f"ours reads {size_mb / s_o:.0f} MB/s, mvnx {size_mb / s_m:.0f} MB/s")  # fmt: skip
        if not args.no_check:
            code = CHECK
            proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                                  cwd=Path(__file__).resolve().parents[1])  # fmt: skip
            if proc.returncode == 0:
                diffs = json.loads(proc.stdout.strip().splitlines()[-1])
                figures["agreement_max_abs"] = diffs
                print("agreement (max |ours converted back - mvnx|): "
                      + ", ".join(f"{k} {v:.1e}" for k, v in diffs.items()))  # fmt: skip
            else:
                print(f"agreement check failed:\n{proc.stderr[-2000:]}")
    if tmp is not None:
        tmp.cleanup()
    rows = [["ours (`read_mvnx`, streaming)", "ours.seconds", "ours.peak_rss_mb", "ours.rss_after_imports_mb"]]
    if have_mvnx:
        rows += [["PyPI `mvnx` 0.2", "mvnx.seconds", "mvnx.peak_rss_mb", "mvnx.rss_after_imports_mb"],
                 ["`mvnx` / ours", "mvnx_over_ours.seconds", "mvnx_over_ours.peak_rss", ""]]  # fmt: skip
    table = Table(f"MVNX import, {figures['file']['minutes']:.3g} min, 23 segments, {FPS:g} Hz, "
                  f"{size_mb:.0f} MB (median of {args.repeats}, fresh process each)",
                  ["reader", "seconds", "peak RSS MB", "RSS after imports MB"], rows)  # fmt: skip
    path = write_results("mvnx", figures, params={"minutes": args.minutes, "repeats": args.repeats, "mvnx": have_mvnx},
                         tables=[table], out=args.out,
                         notes="" if have_mvnx else "The `mvnx` package was not installed: ours only.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
