"""``schema.json``: the machine-readable description of every array in an export.

Each array of ``motion.npz``, ``contacts.npz`` and a render's ``keypoints.npz`` and ``targets.npz`` with its file,
shape in symbolic dimensions, dtype, units and meaning, plus the JSON files' fields; the 269
motion-feature slices come from :data:`~dualhuman_builder.export.features.FEATURE_SCHEMA`.
"""

from __future__ import annotations

from typing import Any, Mapping

from dualhuman_builder.export.features import FEATURE_DIM, FEATURE_SCHEMA
from dualhuman_builder.export.files import FORMAT, FORMAT_VERSION, PERSONS


def build_schema(body_model: Mapping[str, Any]) -> dict[str, Any]:
    """The machine-readable description of every array in the export (``schema.json``).

    ``dims``: sizes of the symbolic dimensions (``T`` is per sequence, in the manifest; ``T-1`` is
    the number of feature rows; ``C``/``R`` are a render's cameras and rendered frames).
    ``arrays``: ``{file, name, shape, dtype, units, meaning, stage}``; ``file`` holds ``{seq_id}``.
    """
    J, P, V = int(body_model["num_bones"]), int(body_model["num_shape_params"]), int(body_model["num_vertices"])
    motion = "sequences/{seq_id}/motion.npz"
    contacts = "sequences/{seq_id}/contacts.npz"
    keypoints = "sequences/{seq_id}/renders/keypoints.npz"
    targets = "sequences/{seq_id}/renders/targets.npz"
    arrays = []
    for p, who in zip(PERSONS, ("actor 0", "actor 1")):
        arrays += [
            {"file": motion, "name": f"{p}.pose", "shape": ["T", "J", 3], "dtype": "float32", "units": "rad",
             "meaning": f"{who}: per-frame rotation vector of each anny bone (anny local-ref parameterisation in "
                        "Y-up world-aligned axes; bone 0 = root = global orientation)", "stage": "motion"},
            {"file": motion, "name": f"{p}.transl", "shape": ["T", 3], "dtype": "float32", "units": "m",
             "meaning": f"{who}: world position of the root bone head (pelvis centre)", "stage": "motion"},
            {"file": motion, "name": f"{p}.shape", "shape": ["P"], "dtype": "float32", "units": "1",
             "meaning": f"{who}: anny phenotype values in [0, 1], order body_model.shape_names", "stage": "motion"},
            {"file": motion, "name": f"{p}.joints", "shape": ["T", 22, 3], "dtype": "float32", "units": "m",
             "meaning": f"{who}: the 22 HumanML3D joints (anny bone heads), world frame", "stage": "motion"},
            {"file": motion, "name": f"{p}.features", "shape": ["T-1", FEATURE_DIM], "dtype": "float32",
             "units": "see fields", "meaning": f"{who}: 269-dim motion features of {p}.joints (HumanML3D 263 + "
             "initial facing and translation); row t describes frame t and the step t -> t+1",
             "fields": FEATURE_SCHEMA, "stage": "motion"},
        ]  # fmt: skip
    arrays += [
        {"file": contacts, "name": "labels_packed", "shape": [2, "T", "V8"], "dtype": "uint8", "units": "bits",
         "meaning": "per-vertex contact labels (2, T, V) bool of actor 0 / actor 1, np.packbits along V (big bit "
                    "order); unpack with np.unpackbits(x, axis=2, count=num_vertices)", "stage": "contacts"},
        {"file": contacts, "name": "num_vertices", "shape": [], "dtype": "int64", "units": "1",
         "meaning": "V, the vertex count the labels were packed from", "stage": "contacts"},
        {"file": contacts, "name": "distances", "shape": [2, "T", "V"], "dtype": "float16", "units": "m",
         "meaning": "signed distance of each vertex to the other body (negative inside); NaN beyond the contact "
                    "band, -inf inside deeper than it", "stage": "contacts"},
        {"file": contacts, "name": "frame_contact", "shape": ["T"], "dtype": "bool", "units": "1",
         "meaning": "any vertex of either actor in contact on the frame", "stage": "contacts"},
        {"file": keypoints, "name": "joints", "shape": ["C", "R", 2, 22, 3], "dtype": "float32", "units": "px, px, 0/1",
         "meaning": "per camera, rendered frame and actor: the 22 joints projected (u, v) and visible flag",
         "stage": "keypoints"},
        {"file": keypoints, "name": "coco", "shape": ["C", "R", 2, 17, 3], "dtype": "float32", "units": "px, px, 0/1",
         "meaning": "the same for the 17 COCO keypoints regressed from the vertices", "stage": "keypoints"},
        {"file": keypoints, "name": "frames", "shape": ["R"], "dtype": "int64", "units": "frame",
         "meaning": "the sequence frame index of each rendered frame", "stage": "keypoints"},
        {"file": keypoints, "name": "views", "shape": ["C"], "dtype": "str", "units": "",
         "meaning": "camera names (views/<name>/ and cameras.json)", "stage": "keypoints"},
        {"file": targets, "name": "joints_cam", "shape": ["C", "R", 2, 22, 3], "dtype": "float32", "units": "m",
         "meaning": "per camera, rendered frame and actor: the 22 joints of motion.npz in the camera's frame "
                    "(R x + t of cameras.json; +X right, +Y down, +Z forward); K of each gives keypoints.npz's u, v",
         "stage": "targets"},
        {"file": targets, "name": "transl", "shape": ["C", "R", 2, 3], "dtype": "float32", "units": "1, 1, m",
         "meaning": "the root's translation target over the full image: (2 u / W - 1, 2 v / H - 1, z W / fx), "
                    "(u, v) the pelvis pixel, z its camera depth, W the image width (z W / fx = z 2 tan(fov_x / 2)); "
                    "u, v = 0 behind the camera", "stage": "targets"},
        {"file": targets, "name": "prob", "shape": ["C", "R", 2], "dtype": "float32", "units": "1",
         "meaning": "saliency target: share of the actor's 22 joints visible (keypoints.npz's visible flags)",
         "stage": "targets"},
        {"file": targets, "name": "box", "shape": ["C", "R", 2, 4], "dtype": "float32", "units": "px",
         "meaning": "the actor's box in the instance mask: x0, y0, x1, y1 pixel edges (columns x0 .. x1 - 1); "
                    "zeros where the actor covers no pixel", "stage": "targets"},
        {"file": targets, "name": "frames", "shape": ["R"], "dtype": "int64", "units": "frame",
         "meaning": "the sequence frame index of each rendered frame (as keypoints.npz)", "stage": "targets"},
        {"file": targets, "name": "views", "shape": ["C"], "dtype": "str", "units": "",
         "meaning": "camera names, in keypoints.npz's order", "stage": "targets"},
    ]  # fmt: skip
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "dims": {"J": J, "P": P, "V": V, "V8": (V + 7) // 8,
                 "T": "frames of the sequence (manifest sequences.<id>.frames)", "T-1": "feature rows: T - 1",
                 "C": "cameras of the render", "R": "rendered frames"},  # fmt: skip
        "arrays": arrays,
        "json": {
            "sequences/{seq_id}/text.json": {"labels": "list[str] (names in labels.json)", "multi_hot": "list[int] (K)",
                                             "symmetric": "bool | null", "texts": "list[str]",
                                             "roles": "[str, str] | null (person a's, person b's)",
                                             "annotations": "list of {annotator, annotated_at, sequence}"},
            "labels.json": "{version, size, labels: [{index, name, description, one_sided, sources}]}",
            "sequences/{seq_id}/contact_events.json": "list of {region_a, region_b, start, end (exclusive), "
            "contact_frames, peak_vertices, min_distance_m (null: deeper than the band), start_s, end_s}",
            "sequences/{seq_id}/cameras.json": "{convention, cameras: [{name, width, height, K, R, t, ...}], ...}",
        },
    }

