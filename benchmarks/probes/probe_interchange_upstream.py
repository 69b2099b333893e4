"""Probe: the upstream projects' own code read against our HumanML3D and InterHuman output.

Runs, from checkouts the user points to (nothing is downloaded or copied into this repository):

* HumanML3D (``--humanml3d``, a checkout of EricGuo5513/HumanML3D): its ``common/skeleton.py``
  ``Skeleton.forward_kinematics_cont6d`` through the notebook ``motion_representation.ipynb``'s
  ``recover_from_rot`` and ``recover_from_ric``, on ``dualhuman export humanml3d`` output; the
  largest distance (mm) from our ``new_joints`` over every joint and frame, per motion, with the
  skeleton's offsets from each motion's first frame (as HumanML3D's own preprocessing sets them);
  and how far the vectors lie from HumanML3D's distribution: ``|z|`` under the checkout's shipped
  ``HumanML3D/Mean.npy`` and ``Std.npy`` (the largest over every dimension and row, the feature group
  it is in, and the 99th percentile), each both as converted (``--retarget none``) and retargeted to
  HumanML3D's reference skeleton (``--retarget humanml3d``, with its bone-length ratios);
* InterGen (``--intergen``, a checkout of tr3e/InterGen): its ``utils/preprocess.py`` ``load_motion``
  with ``swap=True`` (the left/right mirroring of half its training samples) and ``utils/utils.py``
  ``process_motion_np`` (its canonicalisation, which turns each person to face +Z with
  ``qbetween_np``), on ``dualhuman export interhuman`` output: the orthonormality error of the
  mirrored rotations and whether any processed value is non-finite.

The motions: pairs of rigid-limbed synthetic bodies, the second facing the first (exactly -Z at
frame 0), both turning in place by 0, 180, 360 and 720 degrees over the take; the motions of any
export given with ``--export`` (the demo's fitted handshake: ``--export demo-workspace/export``); and
the ground truth of any generated scene given with ``--scene`` (a ``dualhuman scene make`` file: both
actors' body-model joints, converted as an export at the scene's fps; a scene that turns in place:
``dualhuman scene make --type dance_turn --seed 4 --fps 20 --out dance_turn.npz``).

    .venv/bin/python benchmarks/probes/probe_interchange_upstream.py \\
        --humanml3d ~/src/HumanML3D --intergen ~/src/InterGen --scene dance_turn.npz

Writes ``benchmarks/results/probe_interchange_upstream.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from results_file import Goal, Table, write_results  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

FPS = 30.0
FRAMES = 90
TURNS = (0.0, 0.5, 1.0, 2.0)
BONE_LENGTHS = (0.0, 0.1, 0.1, 0.12, 0.4, 0.4, 0.14, 0.42, 0.42, 0.05, 0.12, 0.12, 0.2, 0.12, 0.12, 0.1, 0.15,
                0.15, 0.27, 0.27, 0.25, 0.25)  # fmt: skip


def _rigid_body(frames: int, yaw: np.ndarray, root_xz, seed: int) -> np.ndarray:
    """``(T, 22, 3)`` Y-up metres: a T-pose-like template whose bones swing smoothly (lengths kept),
    turned by ``yaw (T,)`` about +Y, its root at ``root_xz``."""
    from scipy.spatial.transform import Rotation

    from dualhuman_builder.body.joints import JOINT22_PARENTS
    from dualhuman_builder.export.features import REST_DIRECTIONS

    rng = np.random.default_rng(seed)
    parents = JOINT22_PARENTS
    template = np.zeros((22, 3))
    template[0] = (0.0, 0.95, 0.0)
    for j in range(1, 22):  # HumanML3D's rest directions, plausible bone lengths (m)
        template[j] = template[parents[j]] + REST_DIRECTIONS[j] * BONE_LENGTHS[j]
    t = np.arange(frames) / FPS
    local = np.repeat(template[None], frames, axis=0)
    for j in range(1, 22):
        rv = 0.4 * np.sin(2 * np.pi * (0.3 + rng.random(3)) * t[:, None] + 6.28 * rng.random(3))
        local[:, j] = local[:, parents[j]] + Rotation.from_rotvec(rv).apply(template[j] - template[parents[j]])
    local[..., 1] -= local[..., 1].min() - 0.01
    local -= template[0] * [1, 0, 1]
    world = np.einsum("tij,tkj->tki", Rotation.from_euler("y", yaw[:, None]).as_matrix(), local)
    return (world + np.array([root_xz[0], 0.0, root_xz[1]])).astype(np.float32)


def _write_export(root: Path, pairs: dict, fps: float, text: str) -> Path:
    """The least of an export the converters read (a manifest with every file's SHA-256, each
    sequence's joints and text) of ``{sid: (joints a, joints b)}``."""
    import hashlib

    files, sequences = {}, {}
    for sid, (a, b) in pairs.items():
        base = root / "sequences" / sid
        base.mkdir(parents=True)
        np.savez(base / "motion.npz", **{"a.joints": np.float32(a), "b.joints": np.float32(b)})
        (base / "text.json").write_text(json.dumps({"texts": [text]}))
        for name in ("motion.npz", "text.json"):
            files[f"sequences/{sid}/{name}"] = {"sha256": hashlib.sha256((base / name).read_bytes()).hexdigest()}
        sequences[sid] = {"split": "train"}
    manifest = {"format": "dualhuman-export", "format_version": 2, "fps": fps, "sequences": sequences, "files": files}
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


def _export(root: Path) -> Path:
    """One synthetic pair per turn of :data:`TURNS`, as an export."""
    pairs = {}
    for k, turns in enumerate(TURNS):
        yaw = np.linspace(0.0, 2 * np.pi * turns, FRAMES)
        pairs[f"turn{k}"] = (_rigid_body(FRAMES, yaw, (0.0, 0.0), seed=k),
                             _rigid_body(FRAMES, np.pi - yaw, (0.0, 0.8), seed=10 + k))  # fmt: skip
    return _write_export(root, pairs, FPS, "two people turn in place.")


def _scene_export(scene_path: Path, root: Path) -> Path:
    """The ground truth of a generated scene (both actors' body-model joints) as an export at its fps."""
    from dualhuman_builder.sim.scenes import Scene

    scene = Scene.load(scene_path)
    seq = scene.sequence
    a, b = (np.asarray(t.joints(), dtype=np.float32) for t in seq.actors)
    return _write_export(root, {scene_path.stem: (a, b)}, float(seq.fps), f"two people: {scene.params.type}.")


def _use_checkout(root: Path) -> None:
    """Make ``root`` the one upstream checkout imported from: both projects have top-level packages
    named ``common`` and ``utils``."""
    for other in [p for p in sys.path if p.startswith("/") and Path(p, "common").is_dir() and p != str(root)]:
        sys.path.remove(other)
    for name in [m for m in sys.modules if m.split(".")[0] in ("common", "utils", "paramUtil", "datasets")]:
        del sys.modules[name]
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))


def _z_figures(vec: np.ndarray, mean: np.ndarray, std: np.ndarray) -> dict:
    """``|z|`` of ``vec (N, 263)`` under HumanML3D's Mean/Std: the largest, its dimension and feature group,
    the 99th percentile, and the largest per feature group (``z_max_by_field``)."""
    from dualhuman_builder.export.features import FEATURE_FIELDS

    z = np.abs((vec.astype(np.float64) - mean) / std)
    dim = int(np.unravel_index(np.argmax(z), z.shape)[1])
    fields = [f for f in FEATURE_FIELDS if f.stop <= z.shape[1]]
    field = next(f.name for f in fields if f.start <= dim < f.stop)
    return {"z_max": float(z.max()), "z_max_dim": dim, "z_max_field": field, "z_p99": float(np.percentile(z, 99)),
            "z_max_by_field": {f.name: float(z[:, f.slice].max()) for f in fields}}


def humanml3d_errors(hml_root: Path, export: Path, work: Path, retarget: str = "none") -> dict:
    import torch

    np.float = float  # the upstream code predates NumPy 1.24
    _use_checkout(hml_root)
    from common.skeleton import Skeleton  # noqa: F401 - used by the notebook's code
    from common.quaternion import qinv, qrot, quaternion_to_cont6d  # noqa: F401
    from paramUtil import t2m_kinematic_chain, t2m_raw_offsets

    from dualhuman_builder.export.convert import to_humanml3d

    nb = json.loads((hml_root / "motion_representation.ipynb").read_text())
    code = next("".join(c["source"]) for c in nb["cells"] if "def recover_from_rot" in "".join(c["source"]))
    ns = {"torch": torch, "qinv": qinv, "qrot": qrot, "quaternion_to_cont6d": quaternion_to_cont6d}
    exec(code, ns)  # the upstream definitions, run as they are
    doc = to_humanml3d(export, work / f"humanml3d-{retarget}", retarget=retarget)
    dest = Path(doc["dest"])
    stats = [hml_root / "HumanML3D" / f"{n}.npy" for n in ("Mean", "Std")]
    mean, std = (np.load(p).astype(np.float64) for p in stats) if all(p.is_file() for p in stats) else (None, None)
    out = {}
    for f in sorted((dest / "new_joint_vecs").glob("*.npy")):
        vec = torch.from_numpy(np.load(f)).float()
        joints = np.load(dest / "new_joints" / f.name)
        skel = Skeleton(torch.from_numpy(t2m_raw_offsets).float(), t2m_kinematic_chain, "cpu")
        skel.get_offsets_joints(torch.from_numpy(joints[0]).float())
        n = len(vec)
        rot = ns["recover_from_rot"](vec, 22, skel).numpy()
        ric = ns["recover_from_ric"](vec, 22).numpy()
        out[f.stem] = {"recover_from_rot_mm": float(1000 * np.linalg.norm(rot - joints[:n], axis=-1).max()),
                       "recover_from_ric_mm": float(1000 * np.linalg.norm(ric - joints[:n], axis=-1).max())}
        if mean is not None:
            out[f.stem].update(_z_figures(np.load(f), mean, std))
        if retarget != "none":
            sid, _, person = f.stem.rpartition("_")
            r = doc["sequences"][sid]["retarget"][person]
            out[f.stem].update({"bone_ratio_min": r["ratio_min"], "bone_ratio_max": r["ratio_max"],
                                "bone_ratio_mean": r["ratio_mean"], "root_scale": r["root_scale"]})
    return out


def intergen_checks(ig_root: Path, export: Path, work: Path) -> dict:
    np.float = float
    _use_checkout(ig_root)
    from utils.preprocess import load_motion
    from utils.utils import process_motion_np

    from dualhuman_builder.export.convert import to_interhuman

    dest = Path(to_interhuman(export, work / "interhuman")["dest"])
    out = {}
    for f in sorted((dest / "motions_processed" / "person1").glob("*.npy")):
        worst_ortho, finite = 0.0, True
        for person in ("person1", "person2"):
            motion, swapped = load_motion(str(dest / "motions_processed" / person / f.name), 15, swap=True)
            for m in (motion, swapped):
                six = m[:, 66:].reshape(len(m), 21, 6)
                mats = six.reshape(len(m), 21, 3, 2)  # InterHuman: rot_mat[..., :2] flattened by row
                gram = np.einsum("tjki,tjkl->tjil", mats, mats)
                worst_ortho = max(worst_ortho, float(np.abs(gram - np.eye(2)).max()))
                for start in range(0, len(m) - 1, 7):  # InterGen canonicalises at a random window start
                    proc = process_motion_np(m[start:], 0.001, 0, n_joints=22)[0]
                    finite &= bool(np.isfinite(proc).all())
        out[f.stem] = {"mirrored_orthonormality_error": worst_ortho, "all_finite": finite}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--humanml3d", type=Path, required=True, help="a checkout of EricGuo5513/HumanML3D")
    ap.add_argument("--intergen", type=Path, required=True, help="a checkout of tr3e/InterGen")
    ap.add_argument("--export", type=Path, action="append", default=[],
                    help="also score this dataset export (e.g. the demo's, demo-workspace/export); repeatable; its "
                         "motions are named <folder>/<motion>")  # fmt: skip
    ap.add_argument("--scene", type=Path, action="append", default=[],
                    help="also score the ground truth of this generated scene (`dualhuman scene make ... --out "
                         "X.npz`); repeatable; its motions are named scene:<file stem>/<motion>")  # fmt: skip
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    hml, hml_rt, ig = {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        exports = [("", _export(work / "export"))]
        exports += [(f"{e.absolute().parent.name}/", e.resolve()) for e in args.export]
        exports += [(f"scene:{p.stem}/", _scene_export(p, work / f"scene{k}")) for k, p in enumerate(args.scene)]
        for k, (prefix, export) in enumerate(exports):
            here = work / str(k)
            here.mkdir()
            hml_root = args.humanml3d.resolve()
            hml.update({prefix + n: r for n, r in humanml3d_errors(hml_root, export, here).items()})
            hml_rt.update({prefix + n: r for n, r in humanml3d_errors(hml_root, export, here, "humanml3d").items()})
            ig.update({prefix + n: r for n, r in intergen_checks(args.intergen.resolve(), export, here).items()})
    for name, r in {**hml, **ig}.items():
        print(name, r)
    for name, r in hml_rt.items():
        print(name, "retargeted", r)
    both = [*hml.values(), *hml_rt.values()]
    summary = {
        "recover_from_rot_worst_mm": max(r["recover_from_rot_mm"] for r in both),
        "recover_from_ric_worst_mm": max(r["recover_from_ric_mm"] for r in both),
        "mirrored_orthonormality_worst": max(r["mirrored_orthonormality_error"] for r in ig.values()),
        "intergen_all_finite": int(all(r["all_finite"] for r in ig.values())),
    }
    scenes = {n: r for n, r in hml.items() if n.startswith("scene:")}
    if scenes:
        summary["scene_recover_from_rot_worst_mm"] = max(r["recover_from_rot_mm"] for r in scenes.values())
        summary["scene_recover_from_rot_worst_mm_retargeted"] = max(hml_rt[n]["recover_from_rot_mm"] for n in scenes)
    if all("z_max" in r for r in both):
        summary["z_max_none"] = max(r["z_max"] for r in hml.values())
        summary["z_max_retargeted"] = max(r["z_max"] for r in hml_rt.values())
        summary["z_p99_none"] = max(r["z_p99"] for r in hml.values())
        summary["z_p99_retargeted"] = max(r["z_p99"] for r in hml_rt.values())
        for field in ("ric_positions", "rotations_6d", "joint_velocities", "root_height"):
            for tag, rs in (("none", hml), ("retargeted", hml_rt)):
                summary[f"z_max_{field}_{tag}"] = max(r["z_max_by_field"][field] for r in rs.values())
    figures = {"humanml3d": hml, "humanml3d_retargeted": hml_rt, "intergen": ig, "summary": summary}
    rows = [[name, f"humanml3d.{name}.recover_from_rot_mm", f"humanml3d_retargeted.{name}.recover_from_rot_mm",
             f"humanml3d.{name}.recover_from_ric_mm"] for name in hml]  # fmt: skip
    z_rows = [[name, f"humanml3d.{name}.z_max", f"humanml3d_retargeted.{name}.z_max", f"humanml3d.{name}.z_p99",
               f"humanml3d_retargeted.{name}.z_p99", f"humanml3d.{name}.z_max_by_field.ric_positions",
               f"humanml3d_retargeted.{name}.z_max_by_field.ric_positions"]
              for name in hml if "z_max" in hml[name]]  # fmt: skip
    write_results(
        "probe_interchange_upstream", figures,
        params={"fps": FPS, "frames": FRAMES, "turns_degrees": [360 * t for t in TURNS],
                "exports": [e.absolute().parent.name + "/" + e.name for e in args.export],
                "scenes": [p.name for p in args.scene]},
        goals=[Goal("summary.recover_from_rot_worst_mm", "<=", 10.0, "mm", "HumanML3D recover_from_rot, worst joint"),
               Goal("summary.recover_from_ric_worst_mm", "<=", 1.0, "mm", "HumanML3D recover_from_ric, worst joint"),
               Goal("summary.mirrored_orthonormality_worst", "<=", 1e-5, "",
                    "InterGen-mirrored rotations, orthonormality"),
               Goal("summary.intergen_all_finite", ">=", 1, "", "InterGen's processing gives no NaN/inf")],
        tables=[Table("HumanML3D's own recovery of our motions (worst joint, mm)",
                      ["motion", "recover_from_rot", "recover_from_rot (retargeted)", "recover_from_ric"], rows),
                Table("|z| under HumanML3D's shipped Mean/Std", ["motion", "max", "max (retargeted)", "p99",
                                                                 "p99 (retargeted)", "max of ric positions",
                                                                 "max of ric positions (retargeted)"], z_rows)],
        notes="Upstream code run from the checkouts given on the command line; motions converted by "
              "`dualhuman export humanml3d` / `interhuman` from synthetic rigid-limbed pairs turning in place "
              "(turn0..turn3), from the exports given with --export (named <folder>/<motion>) and from the ground "
              "truth of the scenes given with --scene (named scene:<stem>/<motion>); 'retargeted' is "
              "`--retarget humanml3d`. The HumanML3D motions are resampled to 20 fps, so their limbs are rigid only "
              "to the interpolation. |z| uses HumanML3D's HumanML3D/Mean.npy and Std.npy from the checkout.",
        out=args.out)  # fmt: skip


if __name__ == "__main__":
    main()
