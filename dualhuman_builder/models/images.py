"""Rendered images of two people with their 3D targets, read from a dataset export, for the pose estimator.

:class:`ImageFrames` has one item per (sequence, camera, rendered frame) of one split of an export whose
sequences have renders and their targets (``renders/targets.npz``, written by the export writer wherever a
render, its cameras and the motion exist; ``docs/guides/export.md``). An item is the camera's RGB image
cropped to a square around both people and resized to ``size`` x ``size`` pixels, with:

* ``"K" (3, 3)``: the crop's intrinsics in its own pixels: a crop of side ``s`` source pixels whose
  top-left corner is ``(x0, y0)`` maps a source pixel ``(u, v)`` to ``((u - x0) S / s, (v - y0) S / s)``
  (pixel centres at +0.5), so ``K_crop = diag(S / s, S / s, 1) [[1, 0, -x0], [0, 1, -y0], [0, 0, 1]] K``;
* ``"joints_cam" (2, 22, 3)``: both persons' joints in the camera's frame (metres, +X right, +Y down,
  +Z forward), persons a, b in the export's order;
* ``"transl" (2, 3)``: the paper's translation target of each root (the pelvis, joint 0) over the crop,
  :func:`~dualhuman_builder.export.writer.normalised_root`: ``(2 u / S - 1, 2 v / S - 1, z S / fx)`` with
  ``(u, v)`` the root's crop pixel, ``z`` its camera depth and ``fx`` the crop's focal length, so ``z S / fx
  = z 2 tan(fov / 2)`` with ``fov`` the crop's field of view (it does not depend on the focal length);
  :func:`~dualhuman_builder.export.writer.root_from_normalised` inverts it;
* ``"prob" (2,)``: the saliency target, the share of each person's 22 joints visible in the image;
* ``"keypoints2d" (2, 22, 3)``: the render's keypoints ``u, v`` in crop pixels and their visibility (0/1);
  a joint behind the camera (no pixel) is placed at its projection and marked hidden;
* ``"prev_root" (2, 3)``, ``"has_prev"``: the previous rendered frame's roots seen by the same camera,
  expressed as ``transl`` in *this* item's crop (and flip), for the track queries; ``has_prev`` is False at
  the first rendered frame of a sequence and, with ``augment``, for a share :data:`DROP_PREV` of items;
* ``"seq_id"``, ``"camera"``, ``"frame"`` (the sequence frame index).

The crop: the union of both persons' boxes (``targets.npz`` ``box``, from the instance masks; without them
the keypoints inside the image; without those the whole image), squared, times :data:`MARGIN`. Pixels
outside the image are black. ``augment=True`` draws per item and epoch (seeded by ``seed``, the epoch of
:meth:`set_epoch` and the item index): a horizontal flip with probability 0.5, which mirrors the image,
``u`` and camera ``x`` (``K``'s principal point becomes ``S - cx``) and swaps left and right joints
(:data:`~dualhuman_builder.export.features.MIRROR_PERM`) but keeps each person's identity, and a scale
(``exp(U(-JITTER_SCALE, JITTER_SCALE))``) and shift (``U(-JITTER_SHIFT, JITTER_SHIFT)`` of the side) of the
crop; every target follows, so ``K joints_cam`` stays ``keypoints2d``.

Decoded image regions (the crop with room for every jitter, uint8) are cached in memory up to ``cache_mb``
per process. Paths come from the manifest and are read confined to the export folder; nothing is unpickled.
"""

from __future__ import annotations

import io
import json
from collections import OrderedDict
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.features import MIRROR_PERM
from dualhuman_builder.export.files import read_manifest, read_npz
from dualhuman_builder.export.writer import normalised_root
from dualhuman_builder.fileio import read_confined
from dualhuman_builder.models.data import split_ids

#: Square crop side over the larger side of both persons' box.
MARGIN = 1.25
#: Augmentation: crop scale factor within exp(+-JITTER_SCALE), centre shift within +-JITTER_SHIFT of the side.
JITTER_SCALE, JITTER_SHIFT = 0.2, 0.1
#: Augmentation: share of items whose previous roots are dropped (``has_prev`` False).
DROP_PREV = 0.2
#: Largest targets, keypoints or cameras file read (bytes), and largest image.
MAX_TARGET_BYTES = 1 << 30
MAX_IMAGE_BYTES = 256 << 20
#: Decoded image regions kept per dataset by default (MB).
CACHE_MB = 1024.0
_FIX_RENDER = ("export a dataset with renders: render the takes (`dualhuman render WS --take T`) and export again, "
               "or make a ground-truth dataset with `dualhuman synth WS --path ground-truth --export OUT --render`")  # fmt: skip
_FIX_EXPORT = "re-export the dataset, or run `dualhuman export verify` on it"


def _crop_box(box: np.ndarray, kp: np.ndarray, width: int, height: int) -> tuple[float, float, float]:
    """``(cx, cy, side)`` of the square crop (source pixels) around both persons: their boxes
    ``box (2, 4)`` (zeros: no pixel), else their keypoints ``kp (2, 22, 3)`` inside the image, else the image."""
    have = (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
    if have.any():
        b = box[have]
        x0, y0, x1, y1 = b[:, 0].min(), b[:, 1].min(), b[:, 2].max(), b[:, 3].max()
    else:
        uv = kp[..., :2].reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            inside = np.isfinite(uv).all(-1) & (uv >= 0).all(-1) & (uv[:, 0] <= width) & (uv[:, 1] <= height)
        if inside.sum() >= 2:
            x0, y0 = uv[inside].min(axis=0)
            x1, y1 = uv[inside].max(axis=0)
        else:
            return width / 2.0, height / 2.0, float(max(width, height))
    side = max(float(x1 - x0), float(y1 - y0), 4.0) * MARGIN
    return (x0 + x1) / 2.0, (y0 + y1) / 2.0, side


class ImageFrames:
    """Rendered frames of one split of an export with their targets (module docstring).

    ``export_dir``: the export folder. ``split``: one of :data:`~dualhuman_builder.models.data.SPLITS`. ``size``: side ``S`` of
    the square images (pixels). ``augment``: flip and crop jitter (module docstring). ``seed``: of the
    augmentation draws (with :meth:`set_epoch`). ``views``: camera names to use (None: every rendered
    view). ``cache_mb``: decoded image regions kept in memory.

    Attributes: ``manifest``, ``ids`` (the split's sequences used), ``without_renders`` (sequences of
    the split without ``renders/targets.npz``, left out), ``views`` (camera names used, sorted),
    ``index`` (``(sequence, camera, rendered frame)`` per item). DualhumanError with a fix for a folder
    that is not an export, an unknown split, a split without rendered targets, or unreadable renders.
    """

    def __init__(self, export_dir: str | Path, split: str = "train", size: int = 64, augment: bool = False,
                 seed: int = 0, views: Sequence[str] | None = None, cache_mb: float = CACHE_MB):  # fmt: skip
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 8 <= size <= 4096:
            raise DualhumanError(f"image size must be 8 to 4096 pixels, got {size!r}", fix="use e.g. --set size=64")
        if views is not None and (isinstance(views, str) or not all(isinstance(v, str) for v in views)):
            raise DualhumanError(f"views must be a list of camera names, got {views!r}", fix="e.g. views=['view00']")
        self.folder, self.split, self.size = Path(export_dir), split, int(size)
        self.augment, self.seed, self.epoch = bool(augment), int(seed), 0
        self.cache_bytes = int(max(0.0, float(cache_mb)) * (1 << 20))
        self._cache: OrderedDict[tuple[int, int, int], tuple[np.ndarray, int, int]] = OrderedDict()
        self._cached = 0
        if not self.folder.is_dir():
            raise DualhumanError(f"{self.folder} is not a folder", fix=_FIX_RENDER)
        try:
            self.manifest = read_manifest(self.folder)
        except ValueError as e:
            raise DualhumanError(str(e), fix="pass the folder `dualhuman export` wrote (it holds manifest.json)") from None
        files = self.manifest.get("files") if isinstance(self.manifest.get("files"), dict) else {}
        wanted = None if views is None else set(views)
        self.without_renders: list[str] = []
        self.ids: list[str] = []
        without_views = 0
        self._seqs: list[dict[str, Any]] = []
        index: list[tuple[int, int, int]] = []
        for sid in split_ids(self.folder, self.manifest, split):
            if f"sequences/{sid}/renders/targets.npz" not in files:
                self.without_renders.append(sid)
                continue
            s = self._read_sequence(sid, wanted)
            if s is None:
                without_views += 1
                continue
            k = len(self._seqs)
            self._seqs.append(s)
            self.ids.append(sid)
            index.extend((k, c, r) for c in s["cams"] for r in range(len(s["frames"])))
        if not index:
            n = len(self.ids) + len(self.without_renders) + without_views
            if without_views:
                raise DualhumanError(f"{self.folder}: split {split!r} ({n} sequence{'s' * (n != 1)}) has no views "
                                     f"{sorted(wanted)}", fix="name views the export rendered, or leave views out")  # fmt: skip
            raise DualhumanError(f"{self.folder}: split {split!r} ({n} sequence{'s' * (n != 1)}) has no rendered targets "
                                 "(renders/targets.npz)", fix=_FIX_RENDER)  # fmt: skip
        self.index = np.asarray(index, dtype=np.int64).reshape(-1, 3)
        self.views = sorted({s["views"][c] for s in self._seqs for c in s["cams"]})

    # ------------------------------------------------------------------ reading
    def _read(self, rel: str, cap: int) -> bytes:
        """The bytes of ``rel``, read confined to the export (a missing, outside or oversized file is a
        DualhumanError with a fix)."""
        try:
            return read_confined(self.folder, rel, cap, f"{rel} of {self.folder}")
        except DualhumanError as e:
            if e.fix:
                raise
            raise DualhumanError(e.message, fix=_FIX_EXPORT, path=e.path) from None

    def _read_sequence(self, sid: str, wanted: set[str] | None) -> dict[str, Any] | None:
        base = f"sequences/{sid}"

        def npz(rel: str, keys) -> dict[str, np.ndarray]:
            data = self._read(f"{base}/{rel}", MAX_TARGET_BYTES)
            try:
                return read_npz(data, keys)
            except ValueError as e:
                raise DualhumanError(f"{self.folder}/{base}/{rel}: {e}", fix=_FIX_EXPORT) from None

        t = npz("renders/targets.npz", ("joints_cam", "transl", "prob", "box", "frames", "views"))
        kp = npz("renders/keypoints.npz", ("joints", "frames", "views"))
        raw = self._read(f"{base}/cameras.json", MAX_TARGET_BYTES)
        try:
            cams = {c["name"]: c for c in json.loads(raw.decode("utf-8"))["cameras"]}
        except (UnicodeDecodeError, ValueError, KeyError, TypeError) as e:
            raise DualhumanError(f"{self.folder}/{base}/cameras.json: no camera list ({type(e).__name__}: {e})",
                                 fix=_FIX_EXPORT) from None  # fmt: skip
        views = [str(v) for v in t["views"].tolist()]
        C, R = len(views), len(t["frames"])
        shapes = {"joints_cam": (C, R, 2, 22, 3), "transl": (C, R, 2, 3), "prob": (C, R, 2), "box": (C, R, 2, 4)}
        bad = [k for k, shp in shapes.items() if t[k].shape != shp]
        if bad or kp["joints"].shape != (C, R, 2, 22, 3) or [str(v) for v in kp["views"].tolist()] != views \
                or not np.array_equal(kp["frames"], t["frames"]):  # fmt: skip
            raise DualhumanError(f"{self.folder}/{base}: renders/targets.npz does not match renders/keypoints.npz "
                                 f"({', '.join(bad) or 'views, frames or keypoints'})", fix=_FIX_EXPORT)  # fmt: skip
        K, sizes = np.zeros((C, 3, 3)), np.zeros((C, 2), np.int64)
        use = []
        for c, v in enumerate(views):
            if wanted is not None and v not in wanted:
                continue
            try:
                K[c] = np.asarray(cams[v]["K"], dtype=np.float64).reshape(3, 3)
                sizes[c] = int(cams[v]["width"]), int(cams[v]["height"])
            except (KeyError, TypeError, ValueError) as e:
                raise DualhumanError(f"{self.folder}/{base}/cameras.json: no usable K, width and height for view {v!r} "
                                     f"({type(e).__name__}: {e})", fix=_FIX_EXPORT) from None  # fmt: skip
            if not (np.isfinite(K[c]).all() and K[c, 0, 0] > 0 and K[c, 1, 1] > 0 and (sizes[c] > 0).all()):
                raise DualhumanError(f"{self.folder}/{base}/cameras.json: view {v!r} has unusable intrinsics", fix=_FIX_EXPORT)
            use.append(c)
        if not use:
            return None
        for k in ("joints_cam", "transl", "prob", "box"):
            if not np.isfinite(t[k]).all():
                raise DualhumanError(f"{self.folder}/{base}/renders/targets.npz: {k} holds NaN or inf", fix=_FIX_EXPORT)
        return {"seq_id": sid, "views": views, "cams": use, "frames": np.asarray(t["frames"], dtype=np.int64),
                "joints_cam": t["joints_cam"].astype(np.float64), "prob": t["prob"].astype(np.float32),
                "box": t["box"].astype(np.float64), "keypoints": kp["joints"].astype(np.float64), "K": K,
                "sizes": sizes}  # fmt: skip

    def _region(self, k: int, c: int, r: int, cx: float, cy: float, side: float,
                need: tuple[float, float, float, float]) -> tuple[np.ndarray, int, int]:  # fmt: skip
        """``(uint8 (h, w, 3), x0, y0)``: the decoded source image around the crop ``(cx, cy, side)``
        with room for every jitter and at least ``need`` (``x0, y0, x1, y1``), black outside the image;
        cached up to ``cache_mb``."""
        key = (k, c, r)
        hit = self._cache.get(key)
        if hit is not None and hit[1] <= need[0] and hit[2] <= need[1] and need[2] <= hit[1] + hit[0].shape[1] \
                and need[3] <= hit[2] + hit[0].shape[0]:  # fmt: skip
            self._cache.move_to_end(key)
            return hit
        from PIL import Image

        s = self._seqs[k]
        rel = f"sequences/{s['seq_id']}/renders/views/{s['views'][c]}/rgb/{int(s['frames'][r]):05d}.png"
        data = self._read(rel, MAX_IMAGE_BYTES)
        half = side * (np.exp(JITTER_SCALE) * (0.5 + JITTER_SHIFT) if self.augment else 0.5) + 1.0
        x0, y0 = int(np.floor(min(cx - half, need[0]))), int(np.floor(min(cy - half, need[1])))
        x1, y1 = int(np.ceil(max(cx + half, need[2]))), int(np.ceil(max(cy + half, need[3])))
        try:
            with Image.open(io.BytesIO(data)) as im:
                w, h = im.size
                if (w, h) != tuple(s["sizes"][c]):
                    raise DualhumanError(f"{self.folder}/{rel}: {w}x{h} pixels, cameras.json says "
                                         f"{s['sizes'][c][0]}x{s['sizes'][c][1]}", fix=_FIX_EXPORT)  # fmt: skip
                region = np.asarray(im.convert("RGB").crop((x0, y0, x1, y1)), dtype=np.uint8)
        except DualhumanError:
            raise
        except Exception as e:  # noqa: BLE001 - untrusted bytes: PIL raises OSError, SyntaxError, zlib.error, ...
            raise DualhumanError(f"{self.folder}/{rel}: not a readable PNG ({type(e).__name__}: {e})",
                                 fix=_FIX_EXPORT) from None  # fmt: skip
        out = (region, x0, y0)
        if hit is not None:
            self._cached -= self._cache.pop(key)[0].nbytes
        if region.nbytes <= self.cache_bytes:
            self._cache[key] = out
            self._cached += region.nbytes
            while self._cached > self.cache_bytes:
                _, (old, _, _) = self._cache.popitem(last=False)
                self._cached -= old.nbytes
        return out

    # ------------------------------------------------------------------ items
    def set_epoch(self, epoch: int) -> None:
        """Draw the augmentations afresh, reproducibly, for ``epoch``."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.index)

    def _draws(self, i: int) -> tuple[bool, float, float, float, bool]:
        """``(flip, scale, shift_x, shift_y, drop_prev)`` of item ``i`` in this epoch."""
        if not self.augment:
            return False, 1.0, 0.0, 0.0, False
        rng = np.random.default_rng([self.seed, self.epoch, int(i)])
        flip, u = rng.random() < 0.5, rng.uniform(-1.0, 1.0, 3)
        return bool(flip), float(np.exp(JITTER_SCALE * u[0])), float(JITTER_SHIFT * u[1]), float(JITTER_SHIFT * u[2]), \
            bool(rng.random() < DROP_PREV)  # fmt: skip

    def item(self, i: int) -> dict[str, Any]:
        """Item ``i`` (unbatched; module docstring for the keys), with this epoch's augmentation draws."""
        i = self._check(i)
        return self.augmented(i, *self._draws(i))

    def _check(self, i) -> int:
        n = len(self)
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -n <= i < n:
            raise IndexError(f"item {i!r} of {n}")
        return int(i) % n

    def augmented(self, i: int, flip: bool = False, scale: float = 1.0, shift_x: float = 0.0, shift_y: float = 0.0,
                  drop_prev: bool = False) -> dict[str, Any]:  # fmt: skip
        """Item ``i`` with the given augmentation instead of drawn ones: ``flip`` horizontally, the crop's
        side times ``scale`` and its centre moved by ``shift_x``, ``shift_y`` times the side, the previous
        roots dropped with ``drop_prev``. With ``augment=False`` the crop's cached region has no room for
        jitter, and a crop beyond it decodes the image again."""
        i = self._check(i)
        if not (np.isfinite(scale) and scale > 0 and np.isfinite(shift_x) and np.isfinite(shift_y)):
            raise ValueError(f"scale must be > 0 and shifts finite, got {scale}, {shift_x}, {shift_y}")
        flip, dx, dy, drop = bool(flip), float(shift_x), float(shift_y), bool(drop_prev)
        k, c, r = (int(x) for x in self.index[i])
        s = self._seqs[k]
        S = self.size
        W, H = (int(x) for x in s["sizes"][c])
        cx, cy, side = _crop_box(s["box"][c, r], s["keypoints"][c, r], W, H)
        full = side
        side *= scale
        x0, y0 = cx + dx * side - side / 2.0, cy + dy * side - side / 2.0
        region, rx, ry = self._region(k, c, r, cx, cy, full, (x0, y0, x0 + side, y0 + side))
        from PIL import Image

        box = (x0 - rx, y0 - ry, x0 - rx + side, y0 - ry + side)
        img = Image.fromarray(region).resize((S, S), Image.BILINEAR, box=box)
        rgb = np.asarray(img, dtype=np.float32) / 255.0
        f = S / side
        K = np.diag([f, f, 1.0]) @ np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ s["K"][c]
        joints = s["joints_cam"][c, r].copy()
        kp = s["keypoints"][c, r].copy()
        uv = kp[..., :2]
        ok = np.isfinite(uv).all(-1)
        proj = joints @ s["K"][c].T
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = proj[..., :2] / proj[..., 2:3]
        uv[~ok] = np.nan_to_num(proj[~ok], nan=0.0, posinf=0.0, neginf=0.0)
        kp[~ok, 2] = 0.0
        uv[:] = (uv - [x0, y0]) * f
        prev = s["joints_cam"][c, r - 1, :, 0].copy() if r > 0 else np.zeros((2, 3))
        if flip:
            rgb = rgb[:, ::-1]
            K = np.array([[-1.0, 0.0, S], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ K @ np.diag([-1.0, 1.0, 1.0])
            joints = joints[:, MIRROR_PERM] * [-1.0, 1.0, 1.0]
            kp = kp[:, MIRROR_PERM]
            kp[..., 0] = S - kp[..., 0]
            prev = prev * [-1.0, 1.0, 1.0]
        has_prev = r > 0 and not drop
        return {
            "image": torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))),
            "K": torch.from_numpy(K.astype(np.float32)),
            "joints_cam": torch.from_numpy(joints.astype(np.float32)),
            "transl": torch.from_numpy(normalised_root(joints[:, 0], K, S, S).astype(np.float32)),
            "prob": torch.from_numpy(s["prob"][c, r].copy()),
            "keypoints2d": torch.from_numpy(kp.astype(np.float32)),
            "prev_root": torch.from_numpy((normalised_root(prev, K, S, S) if has_prev else np.zeros((2, 3))).astype(np.float32)),
            "has_prev": torch.tensor(bool(has_prev)),
            "seq_id": s["seq_id"],
            "camera": s["views"][c],
            "frame": torch.tensor(int(s["frames"][r]), dtype=torch.int64),
        }

    def __getitem__(self, i: int) -> dict[str, Any]:
        return self.item(i)

    def batch(self, indices: Sequence[int] | np.ndarray) -> dict[str, Any]:
        """Items ``indices`` stacked along a new first dimension (strings as lists)."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if len(idx) == 0:
            raise IndexError("a batch needs at least one item")
        items = [self.item(int(i)) for i in idx]
        stack = {k: isinstance(v, torch.Tensor) for k, v in items[0].items()}
        return {k: torch.stack([it[k] for it in items]) if stack[k] else [it[k] for it in items] for k in stack}


__all__ = ["ImageFrames", "MARGIN", "JITTER_SCALE", "JITTER_SHIFT", "DROP_PREV"]
