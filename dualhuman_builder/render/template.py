"""Render templates: the look of a scene (floor, lights, actor materials, integrator) as JSON.

A template is a JSON file in ``render_templates/`` (name ``studio`` -> ``studio.json``) or any
path. Format ``dualhuman-render-template/1`` (documented with examples in
``render_templates/README.md``); colours are **linear** RGB in [0, 1], positions world metres
(+Y up, floor y = 0)::

    {"format": "dualhuman-render-template/1", "name": "...", "description": "...",
     "integrator": {Mitsuba integrator dict, passed through},      # default path, max_depth 5
     "sampler": "independent" | "multijitter" | ...,                # default independent
     "floor": null | {"size_m": 12, "color": [r, g, b],
                      "checker": {"color": [r, g, b], "tile_m": 0.5}},   # checker optional
     "lights": [
        {"type": "area", "position": [x, y, z], "look_at": [x, y, z], "size_m": [w, h],
         "radiance": [r, g, b]},                                     # one-sided rectangle
        {"type": "constant", "radiance": [r, g, b]},
        {"type": "directional", "direction": [x, y, z], "irradiance": [r, g, b]},
        {"type": "sky", "resolution": [w, h], "zenith": [..], "horizon": [..], "ground": [..],
         "sun_azimuth_deg": a, "sun_elevation_deg": e, "sun_radiance": [..],
         "sun_size_deg": 3, "scale": 1}                              # procedural lat-long envmap
     ],
     "actors": [{"skin": [..], "clothing": [..], "shoes": [..], "texture": "anny_uv" | "none"},
                {... second actor ...}]}

``sky`` lights are generated in memory when the scene is built (:func:`sky_latlong`; no file,
no download). ``texture: "anny_uv"`` paints the body through anny's UV map
(:func:`actor_texture`): head and hands in the skin colour, feet in the shoe colour, the rest
(arms, legs, torso: a capture suit) in the clothing colour; ``"none"`` or a body model without
UVs gives one diffuse clothing colour.

:func:`load_template` validates a file and raises :class:`TemplateError` naming the field at
fault; :meth:`RenderTemplate.scene_dict` gives the Mitsuba dict of everything but the actors and
sensors. A template Mitsuba refuses (an unknown integrator type, say) is reported by the renderer
as a :class:`TemplateError` carrying Mitsuba's own text.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.resources import RENDER_TEMPLATES_DIR

TEMPLATE_FORMAT = "dualhuman-render-template/1"
DEFAULT_TEMPLATE = "studio"
LIGHT_TYPES = ("area", "constant", "directional", "sky")
TEXTURE_KINDS = ("anny_uv", "none")

#: anny's body-part colours (data/segmentation/body_parts_segmentation.yaml) -> material slot.
_SEGMENT_SLOTS = {
    "head": "skin", "hand.R": "skin", "hand.L": "skin", "foot.L": "shoes", "foot.R": "shoes",
    "eye_back.L": "eye", "eye_front.L": "eye", "eye_back.R": "eye", "eye_front.R": "eye",
    "eye_cavity.R": "eye", "eye_cavity.L": "eye", "mouth_cavity": "mouth", "tongue": "mouth",
}  # fmt: skip


class TemplateError(DualhumanError):
    """A render template that is missing, malformed, or that Mitsuba refuses."""


@dataclass(frozen=True)
class ActorLook:
    """One actor's material: linear RGB colours in [0, 1] and the texture kind."""

    skin: tuple[float, float, float]
    clothing: tuple[float, float, float]
    shoes: tuple[float, float, float]
    texture: str = "anny_uv"


@dataclass
class RenderTemplate:
    """A validated template (see the module docstring); ``path`` the file it came from."""

    name: str
    path: Path
    description: str
    integrator: dict
    sampler: str
    floor: dict | None
    lights: list[dict]
    actors: tuple[ActorLook, ActorLook]
    raw: dict = field(default_factory=dict, repr=False)

    def scene_dict(self, mi) -> dict:
        """Mitsuba ``load_dict`` entries (integrator, floor, lights) for the current variant."""
        d: dict = {"type": "scene", "integrator": dict(self.integrator)}
        if self.floor is not None:
            s = float(self.floor["size_m"]) / 2.0
            color = {"type": "rgb", "value": list(self.floor["color"])}
            if "checker" in self.floor:
                n = float(self.floor["size_m"]) / float(self.floor["checker"]["tile_m"]) / 2.0  # tiles per uv unit
                color = {"type": "checkerboard", "color0": color,
                         "color1": {"type": "rgb", "value": list(self.floor["checker"]["color"])},
                         "to_uv": mi.ScalarTransform4f().scale([n, n, 1.0])}  # fmt: skip
            d["floor"] = {
                "type": "rectangle",  # spans [-1, 1]^2 in its xy plane, normal +Z -> rotated to +Y
                "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90) @ mi.ScalarTransform4f().scale([s, s, 1.0]),
                "bsdf": {"type": "diffuse", "reflectance": color},
            }
        for k, light in enumerate(self.lights):
            d[f"light{k}"] = _light_dict(mi, light)
        return d


# --------------------------------------------------------------------------------------------- files
def template_path(template: str | Path) -> Path:
    """The file of ``template``: a name in ``render_templates/`` or a path to a JSON file."""
    p = Path(template)
    if p.suffix == ".json" or p.parent != Path("."):
        return p
    return RENDER_TEMPLATES_DIR / f"{template}.json"


def available_templates() -> list[str]:
    """Names of the templates shipped in ``render_templates/``."""
    return sorted(p.stem for p in RENDER_TEMPLATES_DIR.glob("*.json"))


def load_template(template: str | Path | RenderTemplate = DEFAULT_TEMPLATE) -> RenderTemplate:
    """Read and validate a template (a name, a path, or an already loaded one)."""
    if isinstance(template, RenderTemplate):
        return template
    path = template_path(template)
    if not path.is_file():
        raise TemplateError(f"render template {str(template)!r} not found (looked for {path})",
                            fix=f"use one of {', '.join(available_templates()) or '(none)'} or a path to a JSON template")  # fmt: skip
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise TemplateError(f"not valid JSON: {e}", path=path) from e
    if not isinstance(doc, dict):
        raise TemplateError("a template is a JSON object", path=path)
    if doc.get("format") != TEMPLATE_FORMAT:
        raise TemplateError(f"\"format\" must be {TEMPLATE_FORMAT!r}, got {doc.get('format')!r}", path=path)
    try:
        return _parse(doc, path)
    except TemplateError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise TemplateError(f"malformed template: {type(e).__name__}: {e}", path=path) from e


def _rgb(value, what: str, path: Path, hdr: bool = False) -> tuple[float, float, float]:
    try:
        v = tuple(float(x) for x in value)
    except TypeError:
        raise TemplateError(f"{what} must be a list of 3 numbers, got {value!r}", path=path) from None
    if len(v) != 3 or not all(math.isfinite(x) and x >= 0 for x in v) or (not hdr and max(v) > 1):
        rng = ">= 0" if hdr else "in [0, 1]"
        raise TemplateError(f"{what} must be 3 finite numbers {rng} (linear RGB), got {list(value)}", path=path)
    return v


def _vec(value, n: int, what: str, path: Path) -> tuple[float, ...]:
    try:
        v = tuple(float(x) for x in value)
    except TypeError:
        raise TemplateError(f"{what} must be a list of {n} numbers, got {value!r}", path=path) from None
    if len(v) != n or not all(math.isfinite(x) for x in v):
        raise TemplateError(f"{what} must be {n} finite numbers, got {list(value)}", path=path)
    return v


def _parse(doc: dict, path: Path) -> RenderTemplate:
    integrator = doc.get("integrator", {"type": "path", "max_depth": 5})
    if not isinstance(integrator, dict) or "type" not in integrator:
        raise TemplateError("\"integrator\" must be a Mitsuba integrator dict with a \"type\"", path=path)
    sampler = str(doc.get("sampler", "independent"))
    floor = doc.get("floor")
    if floor is not None:
        if not isinstance(floor, dict):
            raise TemplateError("\"floor\" must be null or an object", path=path)
        size = float(floor.get("size_m", 12.0))
        if not (math.isfinite(size) and size > 0):
            raise TemplateError(f"floor.size_m must be > 0, got {size}", path=path)
        floor = {"size_m": size, "color": _rgb(floor.get("color", (0.5, 0.5, 0.5)), "floor.color", path)}
        checker = doc["floor"].get("checker")
        if checker is not None:
            tile = float(checker.get("tile_m", 0.5))
            if not (math.isfinite(tile) and tile > 0):
                raise TemplateError(f"floor.checker.tile_m must be > 0, got {tile}", path=path)
            floor["checker"] = {"color": _rgb(checker.get("color"), "floor.checker.color", path), "tile_m": tile}
    lights_in = doc.get("lights")
    if not isinstance(lights_in, list) or not lights_in:
        raise TemplateError("\"lights\" must be a non-empty list (an unlit scene renders black)", path=path)
    lights = [_parse_light(x, k, path) for k, x in enumerate(lights_in)]
    actors_in = doc.get("actors")
    if not isinstance(actors_in, list) or len(actors_in) != 2:
        raise TemplateError("\"actors\" must list exactly two actor materials", path=path)
    actors = []
    for k, a in enumerate(actors_in):
        if not isinstance(a, dict):
            raise TemplateError(f"actors[{k}] must be an object", path=path)
        tex = str(a.get("texture", "anny_uv"))
        if tex not in TEXTURE_KINDS:
            raise TemplateError(f"actors[{k}].texture must be one of {TEXTURE_KINDS}, got {tex!r}", path=path)
        actors.append(ActorLook(_rgb(a.get("skin"), f"actors[{k}].skin", path),
                                _rgb(a.get("clothing"), f"actors[{k}].clothing", path),
                                _rgb(a.get("shoes", (0.04, 0.04, 0.04)), f"actors[{k}].shoes", path), tex))  # fmt: skip
    return RenderTemplate(name=str(doc.get("name", path.stem)), path=path, description=str(doc.get("description", "")),
                          integrator=dict(integrator), sampler=sampler, floor=floor, lights=lights,
                          actors=(actors[0], actors[1]), raw=doc)  # fmt: skip


def _parse_light(x, k: int, path: Path) -> dict:
    what = f"lights[{k}]"
    if not isinstance(x, dict) or x.get("type") not in LIGHT_TYPES:
        raise TemplateError(f"{what}.type must be one of {LIGHT_TYPES}, got {x.get('type') if isinstance(x, dict) else x!r}",
                            path=path)  # fmt: skip
    t = x["type"]
    if t == "area":
        size = _vec(x.get("size_m", (1.0, 1.0)), 2, f"{what}.size_m", path)
        if min(size) <= 0:
            raise TemplateError(f"{what}.size_m must be positive, got {list(size)}", path=path)
        pos, tgt = _vec(x.get("position"), 3, f"{what}.position", path), _vec(x.get("look_at"), 3, f"{what}.look_at", path)
        if np.linalg.norm(np.subtract(tgt, pos)) < 1e-6:
            raise TemplateError(f"{what}: position and look_at coincide", path=path)
        return {"type": t, "position": pos, "look_at": tgt, "size_m": size,
                "radiance": _rgb(x.get("radiance"), f"{what}.radiance", path, hdr=True)}  # fmt: skip
    if t == "constant":
        return {"type": t, "radiance": _rgb(x.get("radiance"), f"{what}.radiance", path, hdr=True)}
    if t == "directional":
        d = _vec(x.get("direction"), 3, f"{what}.direction", path)
        if np.linalg.norm(d) < 1e-9:
            raise TemplateError(f"{what}.direction must not be zero", path=path)
        return {"type": t, "direction": d, "irradiance": _rgb(x.get("irradiance"), f"{what}.irradiance", path, hdr=True)}
    res = _vec(x.get("resolution", (512, 256)), 2, f"{what}.resolution", path)
    if min(res) < 4:
        raise TemplateError(f"{what}.resolution must be at least 4 x 4, got {list(res)}", path=path)
    return {"type": t, "resolution": (int(res[0]), int(res[1])),
            "zenith": _rgb(x.get("zenith", (0.25, 0.4, 0.8)), f"{what}.zenith", path, hdr=True),
            "horizon": _rgb(x.get("horizon", (0.8, 0.85, 0.9)), f"{what}.horizon", path, hdr=True),
            "ground": _rgb(x.get("ground", (0.3, 0.28, 0.25)), f"{what}.ground", path, hdr=True),
            "sun_azimuth_deg": float(x.get("sun_azimuth_deg", 30.0)),
            "sun_elevation_deg": float(x.get("sun_elevation_deg", 45.0)),
            "sun_radiance": _rgb(x.get("sun_radiance", (2000.0, 1900.0, 1700.0)), f"{what}.sun_radiance", path, hdr=True),
            "sun_size_deg": float(x.get("sun_size_deg", 3.0)), "scale": float(x.get("scale", 1.0))}  # fmt: skip


# --------------------------------------------------------------------------------------------- Mitsuba pieces
def _light_dict(mi, light: dict) -> dict:
    t = light["type"]
    if t == "area":
        w, h = light["size_m"]
        # the rectangle emits along its +Z; look_at points +Z at the target
        up = (0.0, 1.0, 0.0) if abs(np.subtract(light["look_at"], light["position"])[1]) < 0.99 * np.linalg.norm(
            np.subtract(light["look_at"], light["position"])) else (0.0, 0.0, 1.0)  # fmt: skip
        to_world = mi.ScalarTransform4f().look_at(origin=list(light["position"]), target=list(light["look_at"]), up=list(up))
        return {"type": "rectangle", "to_world": to_world @ mi.ScalarTransform4f().scale([w / 2, h / 2, 1.0]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(light["radiance"])}}}  # fmt: skip
    if t == "constant":
        return {"type": "constant", "radiance": {"type": "rgb", "value": list(light["radiance"])}}
    if t == "directional":
        return {"type": "directional", "direction": list(light["direction"]),
                "irradiance": {"type": "rgb", "value": list(light["irradiance"])}}  # fmt: skip
    return {"type": "envmap", "bitmap": mi.Bitmap(sky_latlong(**{k: v for k, v in light.items() if k not in ("type", "scale")})),
            "scale": float(light["scale"])}  # fmt: skip


def envmap_directions(width: int, height: int) -> np.ndarray:
    """World directions ``(height, width, 3)`` of the pixel centres of a lat-long map as Mitsuba's
    ``envmap`` reads it (identity ``to_world``): row 0 is the zenith (+Y), the middle row the
    horizon; column ``u`` has azimuth ``phi = 2 pi u`` with direction ``(sin phi sin theta,
    cos theta, -cos phi sin theta)``."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi, theta = np.meshgrid(2 * np.pi * u, np.pi * v)
    return np.stack([np.sin(phi) * np.sin(theta), np.cos(theta), -np.cos(phi) * np.sin(theta)], axis=-1)


def sun_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit world vector towards the sun: azimuth from +Z towards +X, elevation above the floor."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])


def sky_latlong(resolution=(512, 256), zenith=(0.25, 0.4, 0.8), horizon=(0.8, 0.85, 0.9), ground=(0.3, 0.28, 0.25),
                sun_azimuth_deg=30.0, sun_elevation_deg=45.0, sun_radiance=(2000.0, 1900.0, 1700.0),
                sun_size_deg=3.0) -> np.ndarray:  # fmt: skip
    """A procedural sky: ``(height, width, 3)`` float32 linear radiance in Mitsuba's lat-long layout
    (:func:`envmap_directions`). Above the horizon the colour blends from ``horizon`` to ``zenith``
    with sqrt(elevation sine); below it is ``ground``; a disc of angular diameter ``sun_size_deg``
    around :func:`sun_direction` has ``sun_radiance`` (HDR)."""
    w, h = int(resolution[0]), int(resolution[1])
    d = envmap_directions(w, h)
    y = d[..., 1:2]
    t = np.sqrt(np.clip(y, 0.0, 1.0))
    img = np.where(y >= 0, (1 - t) * np.asarray(horizon) + t * np.asarray(zenith), np.asarray(ground))
    s = sun_direction(sun_azimuth_deg, sun_elevation_deg)
    cos_r = math.cos(math.radians(max(sun_size_deg, 1e-3) / 2))
    img[(d @ s) >= cos_r] = sun_radiance
    # a sun smaller than a pixel would vanish: light the pixel nearest to it
    if not ((d @ s) >= cos_r).any():
        i = np.unravel_index(np.argmax(d @ s), d.shape[:2])
        img[i] = sun_radiance
    return img.astype(np.float32)


def anny_segmentation_image() -> tuple[np.ndarray, dict] | None:
    """anny's body-part segmentation in UV space ``(H, W, 3) uint8`` (row 0 is v = 1) and its
    colour table, or None when the installed anny does not ship them."""
    try:
        import yaml
        from PIL import Image

        from anny.paths import get_anny_root_dir
    except ImportError:
        return None
    root = Path(get_anny_root_dir()) / "data" / "segmentation"
    png, table = root / "body_parts_segmentation.png", root / "body_parts_segmentation.yaml"
    if not (png.is_file() and table.is_file()):
        return None
    with open(table) as f:
        colors = yaml.safe_load(f)["colors"]
    return np.asarray(Image.open(png).convert("RGB")), colors


def actor_texture(look: ActorLook, size: int = 512) -> np.ndarray | None:
    """An actor's albedo texture ``(size, size, 3)`` float32 linear RGB in Mitsuba's orientation
    (row 0 is v = 1, i.e. the image as stored), painted from anny's UV body-part segmentation;
    None when ``look.texture`` is ``"none"`` or anny ships no segmentation."""
    if look.texture == "none":
        return None
    seg = anny_segmentation_image()
    if seg is None:
        return None
    img, colors = seg
    step = max(1, img.shape[0] // int(size))
    img = img[::step, ::step]
    slots = {"skin": look.skin, "shoes": look.shoes, "eye": tuple(0.3 * c for c in look.skin),
             "mouth": (0.35, 0.08, 0.08)}  # fmt: skip
    out = np.empty(img.shape, np.float32)
    out[:] = look.clothing
    for label, slot in _SEGMENT_SLOTS.items():
        if label in colors:
            out[np.all(img == np.asarray(colors[label], np.uint8), axis=-1)] = slots[slot]
    return out


__all__ = ["ActorLook", "RenderTemplate", "TemplateError", "DEFAULT_TEMPLATE", "TEMPLATE_FORMAT", "actor_texture",
           "anny_segmentation_image", "available_templates", "envmap_directions", "load_template", "sky_latlong",
           "sun_direction", "template_path"]  # fmt: skip
