"""Probe: skinning scattered (frame, vertex) points with a gradient, warp kernels against tensor
operations. The fitter's collision passes read their contacts' positions this way
(:meth:`~dualhuman_builder.fit.skeleton.BodyRig.skin_at`); this measures the choice of the kernels
on the CPU (decision record 0020).

Compares, for a batch of posed frames (one actor, the driven rotations and hand openings
differentiable) and ``M`` random (frame, vertex) points:

* ``warp``: the two warp CPU kernels, forward and backward (``_SkinAt``: what runs on the CPU in
  float32);
* ``torch``: the same linear blend in tensor operations (``BodyRig._skin_at_torch``: what runs
  elsewhere).

Both include the bones' posing (``BodyRig.pose`` without vertices) and its backward. Prints the
median of ``--repeats`` runs (after two warm-ups) per point count, forward alone and forward with
backward, and the ratio torch / warp, both measured in the same run; checks that both give the same
points and gradients (it stops if they do not).

    .venv/bin/python benchmarks/probes/probe_skin_at.py               # 5,000 / 20,000 / 50,000 points, 30 frames
    .venv/bin/python benchmarks/probes/probe_skin_at.py --points 100000 --frames 48 --repeats 21

Writes ``benchmarks/results/probe_skin_at.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from results_file import Table, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, nargs="+", default=[5000, 20000, 50000])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/probe_skin_at.json)")
    args = ap.parse_args(argv)

    import roma
    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.skeleton import BodyRig

    torch.set_num_threads(1)  # as the fitter runs
    model = get_body_model("cpu")
    rig = BodyRig(model, {})
    g = torch.Generator().manual_seed(0)
    B = args.frames
    seg = roma.rotvec_to_rotmat(0.3 * torch.randn(B, 23, 3, generator=g))
    transl = torch.randn(B, 3, generator=g)
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, 1 thread; {B} frames, medians of {args.repeats}")
    print(f"{'points':>8} {'warp fwd':>10} {'torch fwd':>10} {'warp f+b':>10} {'torch f+b':>10} {'f+b ratio':>10}")
    rows = []
    for M in args.points:
        frames = torch.randint(0, B, (M,), generator=g)
        verts = torch.randint(0, rig.num_vertices, (M,), generator=g)
        w = torch.randn(M, 3, generator=g)

        def run(skin, backward):
            delta = torch.zeros(B, 23, 3, requires_grad=True)
            opening = torch.full((B, 4), 0.3, requires_grad=True)
            posed = rig.pose(roma.rotvec_to_rotmat(delta) @ seg, transl, False, opening)
            p = skin(posed, frames, verts)
            if not backward:
                return p, None
            return p, torch.autograd.grad((p * w).sum(), (delta, opening))

        skins = {"warp": rig.skin_at, "torch": rig._skin_at_torch}
        (pw, gw), (pt, gt) = run(skins["warp"], True), run(skins["torch"], True)
        assert (pw - pt).abs().max() < 1e-5, "the two paths give different points"
        for x, y in zip(gw, gt):
            assert (x - y).abs().max() <= 1e-4 * y.abs().max(), "the two paths give different gradients"
        ms = {}
        for name, skin in skins.items():
            for backward in (False, True):
                for _ in range(2):
                    run(skin, backward)
                ts = []
                for _ in range(args.repeats):
                    t = time.perf_counter()
                    run(skin, backward)
                    ts.append(time.perf_counter() - t)
                ms[name, backward] = 1000 * statistics.median(ts)
        ratio = ms["torch", True] / ms["warp", True]
        rows.append({"points": M, "warp_forward_ms": ms["warp", False], "torch_forward_ms": ms["torch", False],
                     "warp_forward_backward_ms": ms["warp", True], "torch_forward_backward_ms": ms["torch", True],
                     "torch_over_warp_forward_backward": ratio})  # fmt: skip
        print(f"{M:>8} {ms['warp', False]:>8.2f}ms {ms['torch', False]:>8.2f}ms {ms['warp', True]:>8.2f}ms "
              f"{ms['torch', True]:>8.2f}ms {ratio:>9.2f}x")  # fmt: skip
    figures = {"frames": B, "repeats": args.repeats, "torch_threads": 1, "points": rows,
               "same_points_and_gradients": True}  # fmt: skip
    table = Table(f"{B} frames, the bones' posing included, ms (median of {args.repeats})",
                  ["points", "warp forward", "torch forward", "warp forward+backward", "torch forward+backward",
                   "torch / warp, forward+backward"],
                  [[f"{r['points']:,}"] + [f"points.{k}.{c}" for c in ("warp_forward_ms", "torch_forward_ms",
                   "warp_forward_backward_ms", "torch_forward_backward_ms", "torch_over_warp_forward_backward")]
                   for k, r in enumerate(rows)])  # fmt: skip
    path = write_results("probe_skin_at", figures, params={"points": args.points, "frames": B, "repeats": args.repeats},
                         tables=[table], out=args.out,
                         notes="Both paths give the same points (1e-5 m) and gradients (1e-4 relative); the probe "
                               "stops before timing when they do not.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
