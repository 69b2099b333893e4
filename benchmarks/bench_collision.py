"""Collision machinery: time per frame pair and depth accuracy of the fit's collision term, against
the other ways to compute penetration, in the same run.

Compares, through :class:`~dualhuman_builder.geometry.collision.CollisionTerm` (same broad phase, same
query vertices, same outputs):

* warp mesh queries (``wp.Mesh`` per body, refit per frame), pseudonormal sign, with a banded
  first query and the sign flood fill, for several bands; with the winding-number sign; and
  without a band (one full query per candidate vertex);
* libigl ``igl.signed_distance`` (pseudonormal) on the candidate vertices with
  ``lower_bound=-inf, upper_bound=band``;
* Jiang et al.'s voxel grid of the inside distance (32^3 per body per frame, filled by warp
  queries) sampled with ``torch.nn.functional.grid_sample``.

Scenes (anny average body, rest A-pose, body b turned 180 deg about +Y): ``hug`` b 0.15 m in
front of a (front to front; the feet interleave, 9 cm deepest, ~5,000 vertices inside each way),
``back 3cm`` back to back overlapping by 3 cm, ``thin`` back to back overlapping by 3 mm,
``far`` 2 m apart. Reference: ``igl.signed_distance`` with the generalised winding-number sign
on the body surface (the obstacle is anny's body component; see the module docstring).

Times are the median of ``--repeats`` runs of ``penetration()`` (both directions, no gradient)
after one warm-up; ``call+bwd`` is the loss with its backward pass. Also prints the mesh facts
that decide which sign to trust.

    .venv/bin/python benchmarks/bench_collision.py [--repeats 7] [--quick]

Writes ``benchmarks/results/collision.json`` (``--out`` elsewhere). No goals: the figures back the
choice of method (decision record 0010).
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from results_file import Table, write_results  # noqa: E402

METHODS = [
    ("warp, band 1 cm, flood if >1500 far (default)", {}),
    ("warp, band 1 cm, always flood fill", {"flood_min": 0}),
    ("warp, band 1 cm, never flood fill", {"flood_min": 10**9}),
    ("warp, band 0.5 cm, flood if >1500 far", {"band_m": 0.005}),
    ("warp, band 2 cm, flood if >1500 far", {"band_m": 0.02}),
    ("warp, band 3 cm, flood if >1500 far", {"band_m": 0.03}),
    ("warp, winding sign, band 1 cm", {"sign": "winding"}),
    ("warp, no band (full queries)", {"band_m": 10.0, "pad_m": 0.01}),
    ("warp, band 1 cm, 1 query thread", {"threads": 1}),
    ("igl.signed_distance, band 1 cm", {"method": "igl"}),
    ("grid 32^3 + grid_sample (Jiang)", {"method": "grid"}),
]


def build_scenes(model):
    import torch

    import igl

    pose = torch.zeros(2, model.num_bones, 3)
    pose[1, 0, 1] = math.pi  # b turned 180 deg about +Y: faces -Z
    with torch.no_grad():
        v = model.forward(pose, None, torch.tensor([[0.0, 0.95, 0.0], [0.0, 0.95, 0.0]])).vertices
    a, b = v[:1], v[1:]

    def shifted(dx=0.0, dz=0.0):
        return a, b + torch.tensor([dx, 0.0, dz])

    scenes = {"hug": shifted(dz=0.15), "back 3cm": None, "thin": None, "far": shifted(dx=2.0)}
    # back to back: b behind a; find the shift giving 3 cm and 3 mm deepest (reference depth)
    faces = model.faces.numpy()
    from dualhuman_builder.body.topology import collision_faces

    fs = faces[collision_faces(faces, model.num_vertices)]

    def deepest(dz):
        aa, bb = shifted(dz=dz)
        return reference(aa, bb, fs)[2]

    for name, target in (("back 3cm", 0.03), ("thin", 0.003)):
        dz = -0.17
        for _ in range(4):  # secant-like: the deepest point moves ~1:1 with the shift along z
            dz = dz - (deepest(dz) - target)
        scenes[name] = shifted(dz=dz)
    del igl
    return scenes, fs


def reference(a, b, fs):
    """Winding-number-signed depths on the body surface: ``(depth_a, depth_b, deepest)``."""
    import igl

    A = a[0].double().numpy()
    Bv = b[0].double().numpy()
    surf = np.zeros(len(A), bool)
    surf[np.unique(fs)] = True
    wn = igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER
    sa = igl.signed_distance(A, Bv, fs, wn)[0]
    sb = igl.signed_distance(Bv, A, fs, wn)[0]
    da = np.where(surf, np.maximum(-sa, 0.0), 0.0)
    db = np.where(surf, np.maximum(-sb, 0.0), 0.0)
    return da, db, float(max(da.max(), db.max()))


def mesh_facts(model, scenes):
    import igl

    from dualhuman_builder.body.topology import collision_faces, mesh_report

    faces = model.faces.numpy()
    a, b = scenes["hug"]
    A = a[0].double().numpy()
    Bv = b[0].double().numpy()
    rep = mesh_report(A, faces)
    em = igl.is_edge_manifold(faces)
    em = bool(em[0] if isinstance(em, tuple) else em)
    loops = igl.boundary_loop(faces)
    fs = faces[collision_faces(faces, model.num_vertices)]
    out = {"edge_manifold": em, "boundary_loop_vertices": int(len(loops)), "watertight": rep.watertight,
           "winding_consistent": rep.winding_consistent, "components": list(rep.component_vertex_counts)}  # fmt: skip
    pn, wn = igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL, igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER
    for label, f in (("full mesh", faces), ("body component", fs)):
        s1 = igl.signed_distance(Bv, A, f, pn)[0]
        s2 = igl.signed_distance(Bv, A, f, wn)[0]
        out[f"hug sign disagreements, {label}"] = f"{int(np.sum((s1 < 0) != (s2 < 0)))} of {int(np.sum(s2 < 0))} inside"
    # randomly posed bodies (0.3 rad of noise on every joint) intersect themselves: there the
    # pseudonormal sign and the winding number part ways
    import torch

    g = torch.Generator().manual_seed(1)
    pose = 0.3 * torch.randn(2, model.num_bones, 3, generator=g)
    pose[:, 0] = 0.0
    pose[1, 0, 1] = math.pi
    with torch.no_grad():
        v = model.forward(pose, None, torch.tensor([[0.0, 0.95, 0.0], [0.0, 0.95, 0.2]])).vertices.double().numpy()
    s1 = igl.signed_distance(v[1], v[0], fs, pn)[0]
    s2 = igl.signed_distance(v[1], v[0], fs, wn)[0]
    out["randomly posed sign disagreements, body component"] = (
        f"{int(np.sum((s1 < 0) != (s2 < 0)))} of {int(np.sum(s2 < 0))} inside")
    return out


def time_it(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts) * 1e3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", "--json", type=Path, default=None,
                    help="results file (default benchmarks/results/collision.json)")
    ap.add_argument("--quick", action="store_true", help="only the default, igl and grid methods")
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="torch intra-op threads (default 1: on a loaded 2-core machine two OpenMP threads "
                         "make every small op wait ~40 ms at its barrier)")  # fmt: skip
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.torch_threads)

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.geometry.collision import CollisionTerm

    model = get_body_model()
    scenes, fs = build_scenes(model)
    refs = {k: reference(a, b, fs) for k, (a, b) in scenes.items()}
    facts = mesh_facts(model, scenes)
    print("mesh facts:")
    for k, v in facts.items():
        print(f"  {k}: {v}")
    print("scenes (reference deepest, mm):", {k: round(r[2] * 1000, 2) for k, r in refs.items()})
    print(f"torch threads {torch.get_num_threads()}, {platform.machine()}, median of {args.repeats}")
    methods = METHODS if not args.quick else [m for m in METHODS if m[0].startswith(('warp, band 1 cm, flood', 'igl', 'grid'))]
    rows = []
    names = list(scenes)
    head = f"{'method':46s}" + "".join(f"{n + ' ms':>11s}" for n in names) + f"{'max err mm':>12s}{'missed':>8s}{'false':>7s}"
    print(head)
    print("-" * len(head))
    for label, kw in methods:
        ct = CollisionTerm(model.faces, **kw)
        row = {"method": label, "ms": {}, "max_err_mm": 0.0, "missed": 0, "false": 0}
        for n in names:
            a, b = scenes[n]
            row["ms"][n] = time_it(lambda a=a, b=b, ct=ct: ct.penetration(a, b), args.repeats)
            r = ct.penetration(a, b)
            da, db, _ = refs[n]
            for mine, ref in ((r["depth_a"][0], da), (r["depth_b"][0], db)):
                row["max_err_mm"] = max(row["max_err_mm"], float(np.abs(mine - ref).max() * 1000))
                row["missed"] += int(np.sum((ref > 1e-4) & (mine == 0)))
                row["false"] += int(np.sum((ref == 0) & (mine > 1e-4)))
        rows.append(row)
        print(f"{label:46s}" + "".join(f"{row['ms'][n]:11.1f}" for n in names)
              + f"{row['max_err_mm']:12.3f}{row['missed']:8d}{row['false']:7d}")  # fmt: skip

    # the default with gradients, and batched frames
    ct = CollisionTerm(model.faces)
    extra = {}
    default = {"call_backward_ms": {}, "batch16_ms_per_frame": {}}
    for n in ("hug", "back 3cm", "thin"):
        a, b = scenes[n]

        def call_bwd(a=a, b=b):
            va = a.clone().requires_grad_(True)
            vb = b.clone().requires_grad_(True)
            ct(va, vb).loss.sum().backward()

        extra[f"call+bwd {n} ms"] = default["call_backward_ms"][n] = time_it(call_bwd, args.repeats)
    for n in ("back 3cm", "far"):
        a, b = scenes[n]
        A, Bv = a.expand(16, -1, -1).contiguous(), b.expand(16, -1, -1).contiguous()
        extra[f"batch of 16 '{n}' frames, ms per frame"] = default["batch16_ms_per_frame"][n] = (
            time_it(lambda A=A, Bv=Bv: ct.penetration(A, Bv), 3) / 16)
    print("default method:")
    for k, v in extra.items():
        print(f"  {k}: {v:.1f}")
    figures = {"facts": facts, "reference_deepest_mm": {k: r[2] * 1000 for k, r in refs.items()}, "methods": rows,
               "default": default, "torch_threads": torch.get_num_threads()}  # fmt: skip
    tables = [Table(f"ms per frame pair, both directions, no gradient (median of {args.repeats}); errors against "
                    "`igl.signed_distance` with the winding-number sign",
                    ["method"] + [f"{n} ms" for n in names] + ["max error mm", "inside vertices missed", "false inside"],
                    [[r["method"]] + [f"methods.{k}.ms.{n}" for n in names]
                     + [f"methods.{k}.max_err_mm", f"methods.{k}.missed", f"methods.{k}.false"]
                     for k, r in enumerate(rows)]),
              Table("the default method", ["figure", "ms"],
                    [[f"loss and backward, {n}", f"default.call_backward_ms.{n}"] for n in default["call_backward_ms"]]
                    + [[f"batch of 16 '{n}' frames, per frame", f"default.batch16_ms_per_frame.{n}"]
                       for n in default["batch16_ms_per_frame"]])]  # fmt: skip
    path = write_results("collision", figures, params={"repeats": args.repeats, "quick": args.quick,
                                                       "torch_threads": args.torch_threads},
                         tables=tables, out=args.out,
                         notes="Scenes: anny's average body in its rest pose, the second body turned 180° about +Y: "
                               "a hug 0.15 m apart, back to back 3 cm and 3 mm deep, and 2 m apart (far). The "
                               "reference depths: " + ", ".join(f"{k} {r[2] * 1000:.1f} mm" for k, r in refs.items())
                               + ".")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
