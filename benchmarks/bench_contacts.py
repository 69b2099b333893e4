"""Contacts stage: frame pairs per second of ours against brute-force libigl and trimesh, in one run.

On ground-truth scenes (``--types``, seed 0, ``--fps``), a window of ``--frames`` frames centred
on the scene's contact phase (its busiest frames), vertices precomputed:

* **ours**: :func:`~dualhuman_builder.contacts.contacts_from_vertices` in this process (box
  broad phase, warp narrow phase in two threads, banded libigl on the sub-mesh for possible
  contacts and float64 pseudonormal distances for the rest, both ways, deep-penetration flood
  fill, labels, events); median of ``--repeats`` runs;
* **(a) brute force**: ``igl.signed_distance`` of every vertex against the whole closed mesh, both
  ways, same band (one run; its cost hardly depends on the pose); its labels are checked
  identical to ours, and its distances against ours in float64 (:func:`contact_frame`): the
  largest difference below the threshold and above it is printed;
* **(b) trimesh** ``proximity.signed_distance`` (opposite sign convention): on ``--trimesh-frames``
  frames and ``--trimesh-points`` vertices per direction, extrapolated to all vertices; needs
  the ``rtree`` package;
* **(c)** for reference, the warp BVH ``PairDistance`` the scene generator uses (not libigl);
* **(d)** ours on a longer sequence, the whole scene tiled ``--tile`` times, in this process and
  in ``--workers`` worker processes (:mod:`dualhuman_builder.contacts.workers`; ``igl`` holds
  the GIL, so threads cannot help: the GIL check is printed); one run each, results checked
  identical.

Also: ours over the whole scene, F1 against the scene's own contacts, and the time to compute
the vertices (``BodyTrack.vertices``), which the stage pays on top. Prints a table with ratios
to ours.

Goals: 50 frame pairs/s on the hug's contact window (``GOAL_HUG_PAIRS_PER_S``); labels identical
to the brute force, and distances within 1e-9 m of it below the threshold and 1e-7 m above it, on
every scene type measured. Writes ``benchmarks/results/contacts.json`` (``--out`` elsewhere).

    .venv/bin/python benchmarks/bench_contacts.py [--fps 15] [--frames 30] [--repeats 5] [--tile 4] [--workers 2]
        [--scene-cache benchmarks/cache]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from results_file import Goal, Table, write_results  # noqa: E402

#: Frame pairs per second the contacts stage must reach on a hug's contact phase, in one process.
GOAL_HUG_PAIRS_PER_S = 50.0
#: How far our distances may lie from the brute-force libigl query's, below and above the threshold (m).
GOAL_DISTANCE_BELOW_M, GOAL_DISTANCE_ABOVE_M = 1e-9, 1e-7


def load_scene(kind: str, fps: float, cache: Path | None):
    from dualhuman_builder.sim.scenes import Scene, SceneParams, make_scene

    path = cache / f"scene_{kind}_seed0_{fps:g}fps.npz" if cache else None
    if path is not None and path.is_file():
        return Scene.load(path), 0.0
    t0 = time.perf_counter()
    sc = make_scene(SceneParams(type=kind, seed=0, fps=fps))
    seconds = time.perf_counter() - t0
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        sc.save(path)
    return sc, seconds


def gil_held_by_igl(topo, A, B) -> bool:
    """Whether a Python thread stalls while ``igl.signed_distance`` runs (the GIL is held)."""
    import igl

    count, stop = [0], [False]

    def spin():
        while not stop[0]:
            count[0] += 1

    th = threading.Thread(target=spin)
    th.start()
    time.sleep(0.05)
    c0, t0 = count[0], time.perf_counter()
    igl.signed_distance(A, B, topo.faces, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
    during, dt = count[0] - c0, time.perf_counter() - t0
    c1 = count[0]
    time.sleep(dt)
    idle = count[0] - c1
    stop[0] = True
    th.join()
    return during < 0.3 * idle


def bench_scene(kind, sc, topo, args) -> dict:
    import igl

    from dualhuman_builder.contacts import contact_frame, contacts_from_vertices
    from dualhuman_builder.evaluation.contacts import contacts_for_scene

    band, thr = args.band, args.threshold
    va_all, vb_all = (a.vertices() for a in sc.sequence.actors)
    gt = sc.contact_labels(thr)
    touching = np.flatnonzero(gt[0].any(1) | gt[1].any(1))
    T = sc.sequence.num_frames
    mid = (int(touching[0]) + int(touching[-1])) // 2 if len(touching) else T // 2
    lo = max(0, min(mid - args.frames // 2, T - args.frames))
    sel = np.arange(lo, min(T, lo + args.frames))
    va, vb = va_all[sel], vb_all[sel]
    n = len(sel)
    out: dict = {"window": [int(sel[0]), int(sel[-1]) + 1], "frames": n,
                 "contact_frames_in_window": int(np.isin(sel, touching).sum())}  # fmt: skip

    # ours
    times, res = [], None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        res = contacts_from_vertices(va, vb, topo, threshold_m=thr, band_m=band, workers=1)
        times.append(time.perf_counter() - t0)
    ours = n / statistics.median(times)
    out["ours_fps"] = ours
    out["ours_queried_vertices_per_frame"] = res.stats["queried_vertices"] / n
    out["ours_queried_faces_per_frame"] = res.stats["queried_faces"] / n
    out["ours_pseudonormal_vertices_per_frame"] = res.stats["pseudonormal_vertices"] / n
    out["ours_skipped_far_frames"] = res.stats["skipped_far_frames"]

    # (a) brute force, same band, and label agreement
    PN = igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL
    same = True
    brute = []
    t0 = time.perf_counter()
    for t in range(n):
        A, B = va[t].astype(np.float64), vb[t].astype(np.float64)
        for i, (P, Q) in enumerate(((A, B), (B, A))):
            S = igl.signed_distance(P, Q, topo.faces, sign_type=PN, lower_bound=-band, upper_bound=band)[0]
            brute.append(S)
            lab = np.nan_to_num(S, nan=np.inf) < thr
            # ours may also flag vertices deeper than the band (NaN to banded igl): compare the rest
            deep = np.isneginf(res.distances[i, t].astype(np.float32))
            same &= bool(np.array_equal(lab[~deep], res.labels[i, t][~deep]))
    out["brute_fps"] = n / (time.perf_counter() - t0)
    out["ours_over_brute"] = ours / out["brute_fps"]
    out["labels_identical_to_brute_force"] = same
    # distances in float64 (contact_frame), against the brute force: libigl's own answers below the
    # threshold, pseudonormals on the BVH's face above it
    below = above = 0.0
    for t in range(n):
        frame = contact_frame(topo, va[t], vb[t], band, threshold_m=thr)
        if frame is None:  # boxes farther apart than the band: nothing within it (the labels check covers it)
            continue
        d = frame[0]
        for i in range(2):
            S = brute[2 * t + i]
            ok = np.isfinite(S)
            err = np.abs(d[i][ok] - S[ok])
            below = max(below, float(err[S[ok] < thr].max(initial=0.0)))
            above = max(above, float(err[S[ok] >= thr].max(initial=0.0)))
    out["max_distance_error_below_threshold_m"] = below
    out["max_distance_error_above_threshold_m"] = above

    # (b) trimesh
    try:
        import trimesh

        import rtree  # noqa: F401  (trimesh's closest_point needs it)

        k = min(args.trimesh_points, topo.num_vertices)
        pts = np.linspace(0, topo.num_vertices - 1, k).astype(int)
        frames = np.linspace(0, n - 1, args.trimesh_frames).astype(int)
        agree = []
        t0 = time.perf_counter()
        for t in frames:
            A, B = va[t].astype(np.float64), vb[t].astype(np.float64)
            for i, (P, Q) in enumerate(((A, B), (B, A))):
                s = -trimesh.proximity.signed_distance(trimesh.Trimesh(Q, topo.faces, process=False), P[pts])
                d = res.distances[i, t, pts].astype(np.float64)
                ok = np.isfinite(d) & (np.abs(s) > 1e-3)
                agree.append(np.mean(np.sign(s[ok]) == np.sign(d[ok])) if ok.any() else 1.0)
        per_frame = (time.perf_counter() - t0) / len(frames) * topo.num_vertices / k
        out["trimesh_fps"] = 1.0 / per_frame
        out["trimesh_sign_agreement_in_band"] = float(np.mean(agree))
    except ImportError as e:
        out["trimesh_fps"] = None
        out["trimesh_unavailable"] = f"{e}"

    # (c) warp PairDistance (the scene generator's ground truth)
    from dualhuman_builder.geometry.distance import get_pair_distance

    pair = get_pair_distance()
    pair(va[0], vb[0], band)
    t0 = time.perf_counter()
    for t in range(n):
        pair(va[t], vb[t], band)
    out["warp_fps"] = n / (time.perf_counter() - t0)

    # (d) a longer sequence (the whole scene tiled) in this process and in worker processes
    long_a, long_b = np.concatenate([va_all] * args.tile), np.concatenate([vb_all] * args.tile)
    by_workers = {}
    for w in (1, args.workers):
        t0 = time.perf_counter()
        by_workers[w] = contacts_from_vertices(long_a, long_b, topo, threshold_m=thr, band_m=band, workers=w)
        out[f"tiled_workers{w}_fps"] = len(long_a) / (time.perf_counter() - t0)
    out["tiled_frames"] = len(long_a)
    out["tiled_identical"] = bool(np.array_equal(by_workers[1].labels, by_workers[args.workers].labels)
                                  and np.array_equal(by_workers[1].distances, by_workers[args.workers].distances,
                                                     equal_nan=True))  # fmt: skip

    # whole scene, and F1 against its own contacts
    full, score = contacts_for_scene(sc, thr, band, topology=topo)
    out["whole_scene"] = {"frames": T, "fps": full.stats["frame_pairs_per_s"],
                          "skipped_far_frames": full.stats["skipped_far_frames"],
                          "f1": score["f1"], "precision": score["precision"], "recall": score["recall"],
                          "events": len(full.events)}  # fmt: skip
    t0 = time.perf_counter()
    for a in sc.sequence.actors:
        a.compute(frames=sel)  # not cached: what the stage pays to get the vertices
    out["vertices_s_per_frame_pair"] = (time.perf_counter() - t0) / n
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--types", default="hug,handshake")
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threshold", type=float, default=0.02)
    ap.add_argument("--band", type=float, default=0.05)
    ap.add_argument("--tile", type=int, default=4, help="row (d): the whole scene repeated this many times")
    ap.add_argument("--workers", type=int, default=2, help="row (d): worker processes")
    ap.add_argument("--trimesh-frames", type=int, default=2)
    ap.add_argument("--trimesh-points", type=int, default=2000)
    ap.add_argument("--scene-cache", type=Path, default=None,
                    help="keep generated scenes here, e.g. benchmarks/cache (a hug takes ~80 s)")
    ap.add_argument("--out", "--json", type=Path, default=None,
                    help="results file (default benchmarks/results/contacts.json)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    from dualhuman_builder.contacts import ContactTopology

    topo = ContactTopology.for_model()
    load0 = os.getloadavg()[0]
    results = {}
    gil = None
    for kind in args.types.split(","):
        sc, gen_s = load_scene(kind, args.fps, args.scene_cache)
        if gil is None:
            v = [a.vertices()[0].astype(np.float64) for a in sc.sequence.actors]
            gil = gil_held_by_igl(topo, v[0], v[1])
        results[kind] = bench_scene(kind, sc, topo, args)
        results[kind]["generation_s"] = round(gen_s, 1)

    print(f"contacts, band {1000 * args.band:g} mm, threshold {1000 * args.threshold:g} mm, {os.cpu_count()} CPUs, "
          f"load {load0:.2f} -> {os.getloadavg()[0]:.2f}; igl holds the GIL: {gil}")  # fmt: skip
    head = f"{'scene (window)':24s}{'method':44s}{'frame pairs/s':>14s}{'x ours':>9s}"
    print(head)
    print("-" * len(head))
    for kind, r in results.items():
        name = f"{kind} {r['window'][0]}-{r['window'][1]} ({r['contact_frames_in_window']} touch)"
        rows = [("ours (warp BVH + igl on possible contacts)", r["ours_fps"]),
                ("(a) brute-force igl, all vertices, banded", r["brute_fps"]),
                ("(b) trimesh.proximity.signed_distance", r["trimesh_fps"]),
                ("(c) warp PairDistance (reference)", r["warp_fps"]),
                (f"(d) ours, scene x{args.tile} ({r['tiled_frames']} fr), 1 process", r["tiled_workers1_fps"]),
                (f"(d) ours, scene x{args.tile}, {args.workers} worker processes", r[f"tiled_workers{args.workers}_fps"])]  # fmt: skip
        for label, fps in rows:
            if fps is None:
                print(f"{name:24s}{label:44s}{'n/a':>14s}{'':>9s}  ({r.get('trimesh_unavailable', '')})")
            else:
                print(f"{name:24s}{label:44s}{fps:14.2f}{fps / r['ours_fps']:9.3f}")
            name = ""
        w = r["whole_scene"]
        print(f"{'':24s}ours, whole scene ({w['frames']} frames, {w['skipped_far_frames']} far): {w['fps']:.1f} "
              f"frame pairs/s; F1 {w['f1']:.4f} (P {w['precision']:.4f}, R {w['recall']:.4f}), {w['events']} events")
        print(f"{'':24s}(d) worker processes identical to one: {r['tiled_identical']}")
        print(f"{'':24s}distances against the brute force: max {r['max_distance_error_below_threshold_m']:.1e} m below "
              f"the threshold, {r['max_distance_error_above_threshold_m']:.1e} m above it")
        print(f"{'':24s}labels identical to brute force: {r['labels_identical_to_brute_force']}; queried per frame: "
              f"{r['ours_queried_vertices_per_frame']:.0f} vertices, {r['ours_queried_faces_per_frame']:.0f} faces "
              f"to igl, {r['ours_pseudonormal_vertices_per_frame']:.0f} vertices in float64 on the BVH's face "
              f"(both ways); vertices from the body model: {1000 * r['vertices_s_per_frame_pair']:.1f} ms/frame pair")
    figures = {"scenes": results, "igl_holds_gil": gil, "load": {"before": load0, "after": os.getloadavg()[0]}}
    kinds = list(results)
    methods = [("ours (warp BVH + libigl on the possible contacts), one process", "ours_fps"),
               ("(a) brute-force `igl.signed_distance`, all vertices, same band", "brute_fps"),
               ("(b) `trimesh.proximity.signed_distance`", "trimesh_fps"),
               ("(c) warp `PairDistance` (float32; the scene generator's)", "warp_fps"),
               ("ours / brute force", "ours_over_brute"),
               ("ours, whole scene (far frames skipped), one process", "whole_scene.fps"),
               (f"(d) ours, whole scene x{args.tile}, one process", "tiled_workers1_fps"),
               (f"(d) the same, {args.workers} worker processes", f"tiled_workers{args.workers}_fps"),
               ("F1 of the whole scene against its own contacts", "whole_scene.f1"),
               ("labels identical to the brute force", "labels_identical_to_brute_force"),
               ("max distance error below the threshold, m", "max_distance_error_below_threshold_m"),
               ("max distance error above the threshold, m", "max_distance_error_above_threshold_m")]  # fmt: skip
    table = Table(f"frame pairs/s on a {args.frames}-frame window on the contact phase, {args.fps:g} fps (median of "
                  f"{args.repeats} for ours)", ["method"] + kinds,
                  [[label] + [f"scenes.{k}.{key}" for k in kinds] for label, key in methods])  # fmt: skip
    goals = [Goal("scenes.hug.ours_fps", ">=", GOAL_HUG_PAIRS_PER_S, "frame pairs/s",
                  label="hug, contact window, one process")] if "hug" in results else []  # fmt: skip
    for k in kinds:
        goals += [Goal(f"scenes.{k}.labels_identical_to_brute_force", ">=", 1, label=f"{k}: labels identical to the brute force"),
                  Goal(f"scenes.{k}.max_distance_error_below_threshold_m", "<=", GOAL_DISTANCE_BELOW_M, "m",
                       label=f"{k}: distances against the brute force, below the threshold"),
                  Goal(f"scenes.{k}.max_distance_error_above_threshold_m", "<=", GOAL_DISTANCE_ABOVE_M, "m",
                       label=f"{k}: distances against the brute force, above the threshold")]  # fmt: skip
    params = {k: v for k, v in vars(args).items() if k not in ("out", "scene_cache")}
    path = write_results("contacts", figures, params=params, goals=goals, tables=[table], out=args.out,
                         notes=f"Band {1000 * args.band:g} mm, threshold {1000 * args.threshold:g} mm; libigl holds the "
                               f"GIL: {gil}. The ratio to the brute force carries across days; the rates drift with "
                               "the machine.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
