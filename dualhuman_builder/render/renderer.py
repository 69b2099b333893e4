"""The dataset renderer: one Mitsuba 3 scene per sequence, two actor meshes updated per frame.

:class:`SequenceRenderer` builds the scene **once** from a render template
(:mod:`.template`: floor, lights, integrator, per-actor materials) and the cameras
(:mod:`.cameras`, one Mitsuba sensor per camera), then per frame only writes the two actors'
vertex positions and normals through ``mi.traverse`` and ``params.update()`` (no reload per frame:
a reload rebuilds the whole scene and leaks memory over long runs;
docs/decisions/0023-render-own-rays.md). Each actor has its own BSDF, and the scene is
loaded with ``optimize=False``, so Mitsuba keeps the bodies separate shapes.

Variant
    ``cuda_ad_rgb`` when a GPU renders, else ``llvm_ad_rgb``, else ``scalar_rgb``
    (:func:`.mitsuba_env.pick_variant`, probed in a child process). A requested variant that does
    not render here is reported with the probe's reason and replaced by the best working one
    (:attr:`SequenceRenderer.variant_note`). ``mi.set_variant`` is process-wide, so a renderer
    selects its variant again before each call when another one has switched it.

Per view (:meth:`SequenceRenderer.render_view`)
    ``rgb``: the template's integrator through the camera's sensor (box filter), ``spp`` samples;
    linear float or 8-bit sRGB ``(H, W, 3)``.
    ``depth`` ``(H, W)`` float32: **camera z** in metres (OpenCV +Z, not ray length), ``inf`` where
    the pixel sees nothing (the floor and light panels are geometry and have depth).
    ``mask`` ``(H, W)`` uint8: 0 background (floor included), 1 actor a, 2 actor b.
    Depth and mask come from one ray per pixel **centre** (OpenCV camera, pixel ``(u, v)`` covers
    ``[u, u+1) x [v, v+1)``) cast with ``scene.ray_intersect_preliminary``: the hit's shape is
    compared with each actor's ``ShapePtr`` (the ``shape_index`` AOV returns wrong values in JIT
    variants, mitsuba3 #1059/#1734), and ``z = t * d_z`` with ``d`` the unit ray direction in
    camera axes. Unfiltered by construction: no mixing of foreground and background depth at
    silhouettes, and the mask equals a z-buffer rasterisation of the meshes sampled at pixel
    centres (the RGB's box-filtered coverage differs only in partly covered edge pixels).
    In ``scalar_rgb`` the rays are cast one by one in Python (slow; that variant is a last resort).

Texture
    anny ships UVs (``texture_coordinates``, with separate per-face UV indices) and a body-part
    segmentation in UV space, but no skin albedo map. :func:`body_model_uvs` returns the UVs;
    the renderer splits vertices at UV seams ("wedges": 14,898 for anny's 13,718 vertices, gathered
    per frame) and paints a texture from the segmentation (:func:`.template.actor_texture`:
    skin, clothing, shoes). Normals are computed on the unsplit mesh, so seams do not show.
    Without UVs each actor gets one diffuse clothing colour.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.render.cameras import Camera, CameraError
from dualhuman_builder.render.template import RenderTemplate, TemplateError, actor_texture, load_template

DEFAULT_SPP = 16
#: Mask values of the two actors (0 is background).
ACTOR_LABELS = (1, 2)


class RenderError(DualhumanError):
    """Rendering cannot proceed (bad input, no variant, disk full)."""


def choose_variant(requested: str | None = None, log: Callable[[str], None] | None = None) -> tuple[str, str | None]:
    """``(variant, note)``: ``requested`` when it renders here, else the best working variant with
    ``note`` saying which variant was unusable and why (also sent to ``log``)."""
    from dualhuman_builder.render.mitsuba_env import configure_llvm, pick_variant

    configure_llvm()
    if not requested:
        return pick_variant(), None
    try:
        return pick_variant((requested,)), None
    except DualhumanError as e:
        why = e.message.split("(", 1)[-1].rstrip(")") if "(" in e.message else e.message
        fallback = pick_variant()
        note = f"variant {requested} is unusable here ({why}); fell back to {fallback}"
        if log:
            log(f"WARNING: {note}")
        return fallback, note


def body_model_uvs(model=None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(uv (N, 2) float32, face_uv (F, 3) int64)`` of the body model's UV map (OBJ convention,
    v up), or None when the model has none. ``model`` defaults to
    :func:`~dualhuman_builder.body.model.get_body_model`."""
    if model is None:
        from dualhuman_builder.body.model import get_body_model

        model = get_body_model()
    anny = getattr(model, "anny", None)
    uv = getattr(anny, "texture_coordinates", None)
    fuv = getattr(anny, "face_texture_coordinate_indices", None)
    if uv is None or fuv is None or tuple(fuv.shape) != tuple(model.faces.shape):
        return None
    return uv.detach().cpu().numpy().astype(np.float32), fuv.detach().cpu().numpy().astype(np.int64)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``(V, 3)`` float32 of a triangle mesh (outward for
    counter-clockwise faces, as Mitsuba computes them)."""
    v = np.asarray(vertices, dtype=np.float32)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    fn = np.cross(b - a, c - a)
    idx = faces.ravel()
    n = np.stack([np.bincount(idx, weights=np.repeat(fn[:, k], 3), minlength=len(v)) for k in range(3)], axis=1)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.tile(np.float64([0.0, 1.0, 0.0]), (len(v), 1)), where=norm > 0).astype(np.float32)


def _srgb_curve(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


#: Linear value quantised to 1/65535 -> 8-bit sRGB: a table lookup, cheaper than the power law
#: on the encoder threads (docs/decisions/0023-render-own-rays.md); within one 8-bit level of the
#: exact curve (0.1 % of values land on the neighbour).
_SRGB_LUT = (_srgb_curve(np.arange(65536) / 65535.0) * 255.0 + 0.5).astype(np.uint8)


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB floats ``(..., 3)`` to 8-bit sRGB (clipped to [0, 1] first; NaN -> 0)."""
    y = np.multiply(rgb, 65535.0, dtype=np.float32)
    y += 0.5
    np.fmax(y, 0.0, out=y)  # fmax/fmin also map NaN to the other operand
    np.fmin(y, 65535.0, out=y)
    return _SRGB_LUT[y.astype(np.uint16)]


def pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays through the pixel centres of ``camera``, row-major ``(H * W)``: ``(origin (3,), unit
    directions (N, 3) world, zscale (N,))`` where ``zscale`` is the camera-z component of the unit
    direction (camera z of a hit = ray distance x zscale)."""
    h, w = camera.height, camera.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    d_cam = pix @ np.linalg.inv(camera.K).T
    norm = np.linalg.norm(d_cam, axis=1)
    d_cam /= norm[:, None]
    return camera.position, d_cam @ camera.R, d_cam[:, 2]


class SequenceRenderer:
    """A Mitsuba scene of two bodies seen by ``cameras``, built once; see the module docstring.

    ``faces (F, 3)`` int vertex indices of the body mesh (shared by both actors), ``num_vertices``
    V; ``cameras``: :class:`~.cameras.Camera` list (OpenCV, unique names, any sizes); ``template``:
    a template name, path or :class:`~.template.RenderTemplate`; ``spp``: samples per pixel of the
    RGB pass; ``variant``: a Mitsuba variant or None (best available); ``uv (N, 2)`` and
    ``face_uv (F, 3)``: the body's UV map (:func:`body_model_uvs`), or None for plain colours.
    """

    def __init__(self, faces, num_vertices: int, cameras: Sequence[Camera], template: str | RenderTemplate = "studio",
                 spp: int = DEFAULT_SPP, variant: str | None = None, uv: np.ndarray | None = None,
                 face_uv: np.ndarray | None = None, texture_size: int = 512, log: Callable[[str], None] | None = None):  # fmt: skip
        faces = np.asarray(faces.detach().cpu().numpy() if hasattr(faces, "detach") else faces)
        self.num_vertices = int(num_vertices)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces must have shape (F, 3) with F > 0, got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer) or faces.min() < 0 or faces.max() >= self.num_vertices:
            raise ValueError(f"faces must be integer indices in [0, {self.num_vertices}), got {faces.dtype} "
                             f"in [{faces.min()}, {faces.max()}]")  # fmt: skip
        self.faces = faces.astype(np.int64)
        cameras = list(cameras)
        if not cameras:
            raise ValueError("a SequenceRenderer needs at least one camera")
        if not all(isinstance(c, Camera) for c in cameras):
            raise ValueError("cameras must be dualhuman_builder.render.cameras.Camera objects")
        names = [c.name for c in cameras]
        if len(set(names)) != len(names):
            raise CameraError(f"camera names must be unique, got {names}")
        if int(spp) < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        self.cameras = cameras
        self.spp = int(spp)
        self.template = load_template(template)
        self.variant_requested = variant
        self.variant, self.variant_note = choose_variant(variant, log)
        import mitsuba as mi

        mi.set_variant(self.variant)
        self._mi = mi
        self.mitsuba_version = mi.__version__
        self._jit = not self.variant.startswith("scalar")

        # wedges: one mesh vertex per distinct (vertex, uv) corner, so a UV map with seams fits
        if uv is not None and face_uv is not None:
            uv = np.asarray(uv, dtype=np.float32)
            face_uv = np.asarray(face_uv, dtype=np.int64)
            if face_uv.shape != self.faces.shape or uv.ndim != 2 or uv.shape[1] != 2 or face_uv.max() >= len(uv):
                raise ValueError(f"uv must be (N, 2) and face_uv (F, 3) indices into it matching faces {self.faces.shape}, "
                                 f"got {uv.shape} and {face_uv.shape}")  # fmt: skip
            pairs, inverse = np.unique(np.stack([self.faces.ravel(), face_uv.ravel()], 1), axis=0, return_inverse=True)
            self._wedge_vertex = pairs[:, 0]
            wedge_uv = uv[pairs[:, 1]]
            self._mesh_faces = inverse.reshape(-1, 3).astype(np.uint32)
            # Mitsuba's textures have v = 0 at the top row of the image (mesh loaders flip OBJ's v)
            texcoords = np.stack([wedge_uv[:, 0], 1.0 - wedge_uv[:, 1]], 1).astype(np.float32)
        else:
            self._wedge_vertex = np.arange(self.num_vertices)
            self._mesh_faces = self.faces.astype(np.uint32)
            texcoords = None
        self.has_texture = False

        scene = self.template.scene_dict(mi)
        self._meshes = []
        for k, look in enumerate(self.template.actors):
            tex = actor_texture(look, texture_size) if texcoords is not None else None
            if tex is not None:
                self.has_texture = True
                reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(tex), "filter_type": "bilinear", "wrap_mode": "clamp"}
            else:
                reflectance = {"type": "rgb", "value": list(look.clothing)}
            props = mi.Properties()
            try:
                props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": reflectance})
            except Exception as e:
                raise TemplateError(f"Mitsuba ({self.variant}) refuses actor {k}'s material: {e}", path=self.template.path) from e
            mesh = mi.Mesh(f"actor{k}", len(self._wedge_vertex), len(self._mesh_faces), props=props,
                           has_vertex_normals=True, has_vertex_texcoords=texcoords is not None)  # fmt: skip
            p = mi.traverse(mesh)
            p["faces"] = _like(p["faces"], self._mesh_faces.ravel())
            p["vertex_positions"] = _like(p["vertex_positions"], np.zeros(3 * len(self._wedge_vertex), np.float32))
            if texcoords is not None:
                p["vertex_texcoords"] = _like(p["vertex_texcoords"], texcoords.ravel())
            p.update()
            scene[f"actor{k}"] = mesh
            self._meshes.append(mesh)
        film = [{"type": "hdrfilm", "width": c.width, "height": c.height, "rfilter": {"type": "box"}, "pixel_format": "rgba"}
                for c in cameras]  # fmt: skip
        for i, c in enumerate(cameras):
            scene[f"camera{i}"] = c.mitsuba_sensor(self.spp, film[i], sampler=self.template.sampler)
        try:
            self.scene = mi.load_dict(scene, optimize=False)
        except Exception as e:  # Mitsuba raises RuntimeError with its parser's text
            raise TemplateError(f"Mitsuba ({self.variant}) cannot load render template {self.template.name!r}: "
                                f"{' '.join(str(e).split())}", path=self.template.path,
                                fix="check the template's integrator, sampler and light entries") from e  # fmt: skip
        by_id = {s.id(): s for s in self.scene.sensors()}
        self._sensors = [by_id[f"camera{i}"] for i in range(len(cameras))]
        shapes = {s.id(): s for s in self.scene.shapes()}
        self._shapes = [shapes[f"actor{k}"] for k in range(2)]
        self._params = mi.traverse(self.scene)
        self._keys = [(f"actor{k}.vertex_positions", f"actor{k}.vertex_normals") for k in range(2)]
        missing = [k for pair in self._keys for k in pair if k not in self._params]
        if missing:
            raise RenderError(f"Mitsuba {self.mitsuba_version} exposes no {missing} (the renderer needs 3.9's buffer names)")
        self._rays = [self._make_rays(c) for c in cameras]
        self._ptrs = [mi.ShapePtr(s) for s in self._shapes] if self._jit else None
        self.frame_set = False

    # ------------------------------------------------------------------ per frame
    def set_frame(self, verts_a: np.ndarray, verts_b: np.ndarray) -> None:
        """Move the two bodies: ``verts_a``, ``verts_b`` ``(V, 3)`` world metres (Y up)."""
        self._activate()
        for k, v in enumerate((verts_a, verts_b)):
            v = np.asarray(v, dtype=np.float32)
            if v.shape != (self.num_vertices, 3):
                raise ValueError(f"vertices of actor {k} must have shape ({self.num_vertices}, 3), got {v.shape}")
            if not np.isfinite(v).all():
                raise ValueError(f"vertices of actor {k} hold NaN or infinite values ({int((~np.isfinite(v)).any(1).sum())} vertices)")
            n = vertex_normals(v, self.faces)
            kp, kn = self._keys[k]
            self._params[kp] = _like(self._params[kp], v[self._wedge_vertex].ravel())
            self._params[kn] = _like(self._params[kn], n[self._wedge_vertex].ravel())
        self._params.update()
        self.frame_set = True

    def _activate(self) -> None:
        """Make this renderer's variant the current one (another renderer may have switched it)."""
        if self._mi.variant() != self.variant:
            self._mi.set_variant(self.variant)

    def _check_view(self, i: int) -> None:
        self._activate()
        if not self.frame_set:
            raise RenderError("call set_frame(verts_a, verts_b) before rendering")
        if not 0 <= int(i) < len(self.cameras):
            raise IndexError(f"view {i} out of range: this renderer has {len(self.cameras)} cameras")

    def render_rgb(self, i: int, seed: int = 0) -> np.ndarray:
        """Linear RGBA ``(H, W, 4)`` float32 of view ``i`` (alpha: fraction of samples that hit geometry)."""
        self._check_view(i)
        img = self._mi.render(self.scene, sensor=self._sensors[i], spp=self.spp, seed=int(seed))
        return np.array(img, dtype=np.float32, copy=True)

    def render_depth_mask(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(depth (H, W) float32 camera z in metres, inf where nothing is hit; mask (H, W) uint8)``
        of view ``i`` from one ray per pixel centre (module docstring)."""
        self._check_view(i)
        cam = self.cameras[i]
        if not self._jit:
            return self._depth_mask_scalar(i)
        mi, dr = self._mi, _drjit()
        ray, zscale = self._rays[i]
        pi = self.scene.ray_intersect_preliminary(ray, coherent=True)
        hit = pi.is_valid()
        z = dr.select(hit, pi.t * zscale, dr.inf)
        one, two, zero = mi.UInt32(ACTOR_LABELS[0]), mi.UInt32(ACTOR_LABELS[1]), mi.UInt32(0)
        label = dr.select(hit & (pi.shape == self._ptrs[0]), one, dr.select(hit & (pi.shape == self._ptrs[1]), two, zero))
        dr.eval(z, label)
        depth = np.asarray(z, dtype=np.float32).reshape(cam.height, cam.width)
        mask = np.asarray(label).astype(np.uint8).reshape(cam.height, cam.width)
        return depth, mask

    def _depth_mask_scalar(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        mi = self._mi
        cam = self.cameras[i]
        origin, dirs, zscale = self._rays[i]
        depth = np.full(len(dirs), np.inf, np.float32)
        mask = np.zeros(len(dirs), np.uint8)
        o = mi.Point3f(*(float(x) for x in origin))
        ids = [s.id() for s in self._shapes]
        for n, d in enumerate(dirs):
            pi = self.scene.ray_intersect_preliminary(mi.Ray3f(o, mi.Vector3f(*(float(x) for x in d))))
            if pi.is_valid():
                depth[n] = pi.t * zscale[n]
                sid = pi.shape.id()
                mask[n] = ACTOR_LABELS[ids.index(sid)] if sid in ids else 0
        return depth.reshape(cam.height, cam.width), mask.reshape(cam.height, cam.width)

    def render_view(self, i: int, seed: int = 0, srgb: bool = True) -> dict[str, np.ndarray]:
        """``{"rgb": (H, W, 3) uint8 sRGB (or float32 linear with srgb=False), "depth": (H, W)
        float32 camera z (m, inf background), "mask": (H, W) uint8 0/1/2}`` of view ``i``."""
        rgb = self.render_rgb(i, seed)[..., :3]
        depth, mask = self.render_depth_mask(i)
        return {"rgb": linear_to_srgb8(rgb) if srgb else rgb, "depth": depth, "mask": mask}

    # ------------------------------------------------------------------ setup
    def _make_rays(self, cam: Camera):
        origin, dirs, zscale = pixel_rays(cam)
        if not self._jit:
            return origin, dirs, zscale
        mi = self._mi
        far = np.float32(cam.far) / zscale.astype(np.float32)
        d = dirs.astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(*(float(x) for x in origin)), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        ray.maxt = mi.Float(far)
        return ray, mi.Float(zscale.astype(np.float32))

    def describe(self) -> dict:
        """JSON-ready facts about this renderer (variant, spp, template, texture, cameras)."""
        return {"variant": self.variant, "variant_requested": self.variant_requested, "variant_note": self.variant_note,
                "mitsuba": self.mitsuba_version, "spp": self.spp, "template": self.template.name,
                "template_path": str(self.template.path), "uv_texture": self.has_texture,
                "views": [c.name for c in self.cameras]}  # fmt: skip


def _like(current, values: np.ndarray):
    """``values`` as a buffer of the same Dr.Jit type as ``current`` (a mesh buffer: JIT array or,
    in scalar variants, a dynamic CPU array)."""
    return type(current)(np.ascontiguousarray(values))


def _drjit():
    import drjit as dr

    return dr


__all__ = ["ACTOR_LABELS", "DEFAULT_SPP", "RenderError", "SequenceRenderer", "body_model_uvs", "choose_variant",
           "linear_to_srgb8", "pixel_rays", "vertex_normals"]  # fmt: skip
