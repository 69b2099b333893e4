"""The dataset card: the ``README.md`` of an export, generated from its manifest (:func:`dataset_card`).

The card's layout section is the rest of this docstring, from "Layout" on, turned into Markdown by
:func:`_layout_section`: it is the reference of the export's folder layout, and any change to it
changes every export's ``README.md``.

Layout
------

::

    OUT/
      manifest.json        written LAST: format, format_version, toolkit_version, body_model (name,
                           version, bone/phenotype names, vertex count), fps, units, axes, split
                           settings, counts, per sequence what it has (motion, contacts, text, cameras,
                           renders + views, keypoints) and its split, the sequences left out with the
                           reason (skipped) or exported without some stage (incomplete), and the
                           sha256 + size of every other file in the export
      schema.json          every array: file, name, shape (symbolic dims: T frames, J bones,
                           P phenotype values, V vertices, ...), dtype, units, meaning; the 269
                           motion-feature slices (export/features.py FEATURE_SCHEMA)
      README.md            this dataset card, generated from the manifest
      labels.json          the interaction vocabulary (export/vocabulary.toml + the project's own):
                           {version, size K, labels: [{index, name, description, one_sided, sources}]}
      splits/train.txt     sequence ids, one per line, sorted (seeded split, 3:1 by default;
      splits/test.txt        optionally subject-disjoint: no subject in both)
      stats/mean.npy       (269,) float32 feature mean over the train split, both persons
      stats/std.npy        (269,) float32 feature std, one value per feature group (feature_stats)
      sequences/<seq_id>/
        sequence.json      seq_id, subjects, roles, take, frame_range, frames, fps, has, meta, and the
                           sha256 of this folder's files (written last in the folder)
        motion.npz         per person p in {a, b}: p.pose (T, J, 3) float32 rotation vectors (rad),
                           p.transl (T, 3) float32 m, p.shape (P,) float32 anny phenotype in [0, 1],
                           p.joints (T, 22, 3) float32 m (HumanML3D joint order, world frame),
                           p.features (T-1, 269) float32 (export/features.py)
        contacts.npz       labels_packed (2, T, ceil(V/8)) uint8 (np.packbits of the (2, T, V) bool
                           labels along V, big bit order), num_vertices () int64 = V,
                           distances (2, T, V) float16 signed distance to the other body (m,
                           negative inside, NaN beyond the contact band, -inf deeper than it),
                           frame_contact (T,) bool
        contact_events.json  region-level events [{region_a, region_b, start, end (exclusive),
                           contact_frames, peak_vertices, min_distance_m (null: deeper than the
                           band), ...}]
        text.json          {"labels": [...], "multi_hot": [K ints 0/1 over labels.json], "symmetric":
                           true | false | null, "texts": [...], "roles": ["actor" | "reactor", the
                           other] for persons a, b | null, "annotations": [{annotator, annotated_at,
                           sequence}]}, UTF-8
        cameras.json       the render's cameras (OpenCV K, world-to-camera R | t, metres)
        renders/           the render folder (hard-linked when on the same filesystem):
                           render.json, keypoints.npz, visibility.json,
                           views/<cam>/rgb/<frame:05d>.png, views/<cam>/depth/<frame:05d>.exr,
                           views/<cam>/mask/<frame:05d>.png (0 background, 1 person a, 2 person b)

World frame: right-handed, +Y up, metres, floor y = 0; a body at identity faces +Z with its left
towards +X. Person ``a`` is actor 0 of the interaction, ``b`` actor 1. Loading never unpickles:
every ``.npz`` is read with ``allow_pickle=False`` (:func:`load_motion`, :func:`load_contacts`).

Writing is crash-safe and resumable: every file is written to a temporary name and renamed
(``os.replace``); a file whose bytes would not change is not rewritten (the ``.npz`` files are
byte-deterministic); a sequence whose ``sequence.json`` records the same inputs and whose files
still match their sha256 is skipped without recomputation; ``manifest.json`` comes last, so a
folder without it is an unfinished export that re-running completes. Sequences are validated
before anything is written: duplicate ids, ids that are not safe folder names and text that is
not valid UTF-8 are errors; a sequence without motion, or whose motion holds NaN, is skipped
with its reason in the manifest (an error with ``strict=True``).
"""

from __future__ import annotations

import re
from typing import Any, Mapping


def _layout_section() -> str:
    """The module docstring's layout section as Markdown (the ``::`` block becomes a code fence)."""
    doc = __doc__ or ""
    start = doc.find("Layout\n------")
    if start < 0:
        return "See schema.json for every array."
    out, in_block = ["## Layout", ""], False
    for line in doc[start:].splitlines()[2:]:
        if line.strip() == "::":
            out.append("```")
            in_block = True
            continue
        if in_block and line and not line.startswith(" "):
            while out[-1] == "":
                out.pop()
            out += ["```", ""]
            in_block = False
        if not line.strip() and out[-1] in ("", "```"):
            continue
        if in_block:
            out.append(line[4:])
        else:
            out.append(re.sub(r":\w+:`([^`]+)`", r"`\1`", line).replace("``", "`"))
    if in_block:
        out.append("```")
    return "\n".join(out).strip()


def dataset_card(manifest: Mapping[str, Any]) -> str:
    """The export's ``README.md`` (Markdown) generated from ``manifest`` (its ``files`` may be empty)."""
    c = manifest["counts"]
    bm = manifest["body_model"]
    lines = [
        "# Two-person interaction dataset (dualhuman-builder export)",
        "",
        f"Written by dualhuman-builder {manifest['toolkit_version']}, format {manifest['format']} "
        f"version {manifest['format_version']}.",
        "",
        "| | |",
        "| --- | --- |",
        f"| sequences | {c['sequences']} ({c['train']} train, {c['test']} test) |",
        f"| frames | {c['frames']} at {manifest['fps']:g} fps ({c['frames'] / manifest['fps']:.1f} s) |",
        f"| subjects | {c['subjects']} |",
        f"| texts | {c['texts']} |",
        f"| with contacts / cameras / renders | {c['with_contacts']} / {c['with_cameras']} / {c['with_renders']} |",
        f"| body model | {bm['name']} {bm['version']}: {bm['num_bones']} bones, {bm['num_shape_params']} "
        f"phenotype values, {bm['num_vertices']} vertices |",
        f"| units, frame | metres, seconds, radians; {manifest['world_frame']} |",
        f"| motion features | {manifest['feature_dim']} per person and frame step (HumanML3D 263 + 6) |",
        f"| split | seed {manifest['split']['seed']}, ratio {manifest['split']['ratio']:g}, "
        f"subject-disjoint: {'yes' if manifest['split']['subject_disjoint'] else 'no'} |",
        "",
        "Every array is described in `schema.json` (shape, dtype, units, meaning); `manifest.json` lists every "
        "file with its SHA-256. Check a download with `dualhuman export verify DIR`.",
        "",
        "Files never need unpickling: read the `.npz` files with `numpy.load(path, allow_pickle=False)`.",
        "",
        _layout_section(),
        "",
    ]
    if manifest.get("source") == "ground-truth":
        lines += ["**Ground truth, not fitted data**: every sequence is a generated scene (`dualhuman synth --path "
                  "ground-truth`), with no simulated devices and no fit; each `sequence.json` says "
                  '`meta.source = "ground-truth"`.', ""]  # fmt: skip
    quality = manifest.get("quality") or {}
    if quality.get("left_out"):
        lines += ["## Left out by the quality gates", ""]
        lines += [f"- `{k}`: {'; '.join(f['gate'] + ' (' + f['message'] + ')' for f in v)}" for k, v in quality["left_out"].items()]
        lines += [""]
    if manifest.get("skipped"):
        lines += ["## Left out", ""] + [f"- `{k}`: {v}" for k, v in manifest["skipped"].items()] + [""]
    if manifest.get("incomplete"):
        lines += ["## Exported without some stages", ""]
        lines += [f"- `{k}`: no {', '.join(v)}" for k, v in manifest["incomplete"].items()] + [""]
    return "\n".join(lines)

