"""The contact sheet: one PNG that shows what a render and its annotations look like.

A grid of up to ``max_views`` camera views (rows) by ``max_frames`` frames (columns) from a render
folder (layout in :mod:`dualhuman_builder.render.stage`), each tile the RGB image with

* the instance mask tinted over it (actor 1 blue, actor 2 orange) and its outline drawn,
* both actors' 22 keypoints and skeleton: a filled dot for a joint the depth test calls visible, a
  hollow ring for a hidden one;

and, under the grid, the two meshes of the same frames from one side view with the vertices in
contact painted yellow (from the contacts stage's labels), so the contact annotation can be checked
by eye against the images. Frames are spread over the rendered frames and always include the frame
with the most contact vertices.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np

from dualhuman_builder.body.joints import JOINT22_PARENTS
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.workspace.runner import Stage

#: Tint of each actor's mask (RGB 0-255) and the skeleton colours: actor 1 orange-red, actor 2 blue,
#: as the meshes of the contact row (and the demo's previews).
MASK_COLOURS = ((235, 110, 60), (60, 110, 230))
SKELETON_COLOURS = ((150, 50, 10), (20, 50, 160))
MESH_COLOURS = ((0.80, 0.35, 0.25), (0.25, 0.45, 0.80))
CONTACT_COLOUR = (0.98, 0.85, 0.15)


def pick_frames(rendered: np.ndarray, contact_counts: np.ndarray | None, n: int) -> list[int]:
    """``n`` frame numbers out of ``rendered`` (sorted sequence frame numbers), spread evenly, with the
    frame of most contact (``contact_counts (T,)`` per sequence frame) swapped in for the nearest."""
    rendered = np.asarray(rendered, dtype=int)
    n = max(1, min(int(n), len(rendered)))
    pos = np.linspace(0, len(rendered) - 1, n).round().astype(int)
    chosen = list(rendered[pos])
    if contact_counts is not None and len(contact_counts) and contact_counts[rendered].max() > 0:
        peak = int(rendered[np.argmax(contact_counts[rendered])])
        if peak not in chosen:
            chosen[int(np.argmin([abs(c - peak) for c in chosen]))] = peak
    return sorted(int(c) for c in chosen)


def _tile(rgb_path: Path, mask_path: Path, kps: np.ndarray, scale: float):
    """One annotated tile: ``kps (2, 22, 3)`` pixel u, v and visibility of both actors."""
    from PIL import Image, ImageDraw, ImageFilter

    img = Image.open(rgb_path).convert("RGB")
    mask = np.asarray(Image.open(mask_path))
    arr = np.asarray(img).astype(np.float32)
    for k, colour in enumerate(MASK_COLOURS):
        m = mask == k + 1
        arr[m] = 0.6 * arr[m] + 0.4 * np.asarray(colour, np.float32)
    img = Image.fromarray(arr.clip(0, 255).astype(np.uint8))
    for k, colour in enumerate(MASK_COLOURS):  # outline: the mask minus its erosion
        m = Image.fromarray(((mask == k + 1) * 255).astype(np.uint8))
        edge = np.asarray(m).astype(bool) & ~np.asarray(m.filter(ImageFilter.MinFilter(3))).astype(bool)
        a = np.asarray(img).copy()
        a[edge] = colour
        img = Image.fromarray(a)
    if scale != 1.0:
        img = img.resize((round(img.width * scale), round(img.height * scale)), Image.Resampling.LANCZOS)
    draw = ImageDraw.Draw(img)
    r = max(2, round(2.5 * max(scale, 0.6)))
    for k in range(2):
        uv = kps[k, :, :2] * scale
        vis = kps[k, :, 2] > 0.5
        for j, p in enumerate(JOINT22_PARENTS):
            if p >= 0 and np.isfinite(uv[[j, p]]).all():
                draw.line([tuple(uv[p]), tuple(uv[j])], fill=SKELETON_COLOURS[k], width=max(1, r // 2))
        for j in range(len(uv)):
            if not np.isfinite(uv[j]).all():
                continue
            box = [uv[j, 0] - r, uv[j, 1] - r, uv[j, 0] + r, uv[j, 1] + r]
            if vis[j]:
                draw.ellipse(box, fill=MASK_COLOURS[k], outline=(255, 255, 255))
            else:
                draw.ellipse(box, outline=MASK_COLOURS[k], width=max(1, r // 2))
    return img


def _contact_row(sequence, labels: np.ndarray, faces: np.ndarray, frames: list[int], tile_width: int, spp: int):
    """Per frame, both meshes with the contact vertices painted, framed on the contact (the contact
    vertices' box grown by 15 cm) seen across the line between the actors; the whole pair when the
    frame has no contact. ``labels (2, T, V)``."""
    from PIL import Image, ImageDraw

    from dualhuman_builder.render.preview import render_preview

    # only the shown frames: a whole take's meshes are skinned frame by frame (165 MB per 1,000 frames)
    verts = [a.compute(frames=np.asarray(frames))["vertices"] for a in sequence.actors]
    size = (tile_width, round(tile_width * 0.8))
    row = Image.new("RGB", (tile_width * len(frames), size[1]), (255, 255, 255))
    with tempfile.TemporaryDirectory(prefix="dualhuman-sheet-") as tmp:
        for n, f in enumerate(frames):
            meshes, touching = [], []
            for i in range(2):
                rgb = np.tile(np.asarray(MESH_COLOURS[i]), (verts[i].shape[1], 1))
                rgb[labels[i, f]] = CONTACT_COLOUR
                meshes.append((verts[i][n], faces, rgb))
                touching.append(verts[i][n][labels[i, f]])
            pts = np.concatenate(touching)
            if len(pts):
                bounds = (pts.min(0) - 0.15, pts.max(0) + 0.15)
            else:
                allv = np.concatenate([v[n] for v in verts])
                bounds = (allv.min(0), allv.max(0))
            across = np.asarray(sequence.actors[1].transl[f] - sequence.actors[0].transl[f], dtype=float)
            azimuth = float(np.degrees(np.arctan2(-across[2], across[0])))  # across the actors' line, actor 1 on the left
            tile = Path(tmp) / f"{n}.png"
            render_preview(meshes, tile, size=size, spp=spp, azimuth_deg=azimuth, elevation_deg=15.0, bounds=bounds, floor_y=0.0)
            img = Image.open(tile).convert("RGB")
            ImageDraw.Draw(img).text((6, 4), f"frame {f}: {int(labels[0, f].sum())} + {int(labels[1, f].sum())} contact vertices",
                                     fill=(20, 20, 20))  # fmt: skip
            row.paste(img, (n * tile_width, 0))
    return row


def write_contact_sheet(render_dir: str | Path, path: str | Path, sequence=None, contact_labels=None, faces=None,
                        max_views: int = 4, max_frames: int = 4, tile_width: int = 256, spp: int = 16,
                        title: str = "") -> dict:  # fmt: skip
    """Write the contact sheet PNG of the render in ``render_dir`` to ``path``.

    ``sequence`` (the rendered :class:`~dualhuman_builder.tracks.InteractionSequence`), ``contact_labels``
    ``(2, T, V)`` bool and ``faces (F, 3)`` add the row of contact-coloured meshes; without them the
    sheet has only the image grid. Returns ``{"frames", "views", "size", "contact_row"}``.
    """
    from PIL import Image, ImageDraw

    render_dir = Path(render_dir)
    try:
        info = json.loads((render_dir / "cameras.json").read_text())
        with np.load(render_dir / "keypoints.npz", allow_pickle=False) as z:
            joints, rendered, view_names = z["joints"], z["frames"], [str(v) for v in z["views"]]
    except FileNotFoundError as e:
        raise DualhumanError(f"{render_dir} is not a complete render (missing {Path(e.filename).name})",
                             fix="run `dualhuman render WS --take T` first") from None  # fmt: skip
    counts = None
    if contact_labels is not None:
        counts = np.asarray(contact_labels).sum(axis=(0, 2))
    frames = pick_frames(rendered, counts, max_frames)
    vsel = np.linspace(0, len(view_names) - 1, min(max_views, len(view_names))).round().astype(int)
    cams = {c["name"]: c for c in info["cameras"]}
    w0 = cams[view_names[0]]["width"]
    scale = tile_width / w0
    tiles = []
    for vi in vsel:
        row = []
        for f in frames:
            fi = int(np.searchsorted(rendered, f))
            d = render_dir / "views" / view_names[vi]
            row.append(_tile(d / "rgb" / f"{f:05d}.png", d / "mask" / f"{f:05d}.png", joints[vi, fi], scale))
        tiles.append(row)
    tw, th = tiles[0][0].size
    head, label_w = 28, 70
    strip = None
    if sequence is not None and contact_labels is not None and faces is not None:
        # the contact row shows the grid's frames, but always the take's frame of most contact too
        # (rendered or not: a short contact can fall between rendered frames)
        row_frames = list(frames)
        if counts.max() > 0 and int(np.argmax(counts)) not in row_frames:
            peak = int(np.argmax(counts))
            row_frames[int(np.argmin([abs(c - peak) for c in row_frames]))] = peak
        strip = _contact_row(sequence, np.asarray(contact_labels), faces, row_frames, tw, spp)
    W = label_w + tw * len(frames)
    H = head + th * len(vsel) + (strip.height + 18 if strip is not None else 0) + 18
    sheet = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    fps = sequence.fps if sequence is not None else None
    draw.text((6, 6), title or f"{render_dir.name}: {info.get('variant', '?')}, {info.get('spp', '?')} spp", fill=(0, 0, 0))
    for c, f in enumerate(frames):
        draw.text((label_w + c * tw + 4, head - 12), f"frame {f}" + (f" ({f / fps:.2f} s)" if fps else ""), fill=(0, 0, 0))
    for r, vi in enumerate(vsel):
        draw.text((4, head + r * th + th // 2), view_names[vi], fill=(0, 0, 0))
        for c in range(len(frames)):
            sheet.paste(tiles[r][c], (label_w + c * tw, head + r * th))
    y = head + th * len(vsel)
    if strip is not None:
        draw.text((4, y + 4), "contact vertices (yellow), close-up of the contact (whole pair when none)", fill=(0, 0, 0))
        sheet.paste(strip, (label_w, y + 18))
        y += strip.height + 18
    draw.text((4, y + 3), "masks: actor 1 orange, actor 2 blue; keypoints: filled = visible, ring = hidden", fill=(60, 60, 60))
    path = Path(path)
    sheet.save(path)
    return {"frames": frames, "views": [view_names[i] for i in vsel], "size": [W, H], "contact_row": strip is not None}


__all__ = ["write_contact_sheet", "pick_frames", "MASK_COLOURS", "SHEET", "run_sheet"]


SHEET = Stage("sheet", per="take", artifacts=("contact_sheet.png",), reads=("render", "contacts", "fit"),
              command="dualhuman render {ws} --take {take}")  # fmt: skip


def run_sheet(ws, take: str, force: bool = False, log=print):
    """The ``sheet`` workspace stage: ``contact_sheet.png`` of the take's render, with the contacts
    stage's labels on the meshes when that stage is complete (not when it is stale: then a note
    says so, and the next contacts run makes the sheet stale)."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.contacts.stage import CONTACTS, load_contacts
    from dualhuman_builder.fit.stage import load_bodies
    from dualhuman_builder.render.stage import RENDER

    RENDER.artifact(ws, take, "render.json")  # a clear error when the render is not done
    have_contacts = CONTACTS.done(ws, take)
    if CONTACTS.state(ws, take) == "stale":
        log(f"the contacts of {take} are stale: the sheet is drawn without them (run `{CONTACTS.how_to_run(ws, take)}`, "
            "then the sheet again)")  # fmt: skip

    def compute(out):
        seq = load_bodies(ws, take)
        labels = load_contacts(ws, take).labels if have_contacts else None
        log("drawing the contact sheet...")
        info = write_contact_sheet(ws.artifact_dir("render", take), out.path("contact_sheet.png"), seq, labels,
                                   get_body_model().faces.cpu().numpy(), title=f"take {take}")  # fmt: skip
        return info

    depends = [("render", None)] + ([("contacts", None)] if have_contacts else [])
    return ws.run_stage(SHEET, compute, take=take, params={"contacts": have_contacts}, depends_on=depends, force=force)
