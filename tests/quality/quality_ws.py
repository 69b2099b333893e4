"""A small workspace whose stage results are written in the stages' own formats, through the stage
runner: take ``BAD`` with a tracker lost for 40 % of the take and bodies overlapping by 14 mm,
take ``GOOD`` within every threshold, take ``RAW`` with no stage run."""

from __future__ import annotations

import json

import numpy as np
import pytest

FPS = 15.0
T = 12


def _bodies(out, model):
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    J, P = model.num_bones, len(model.shape_names)
    tracks = []
    for k, actor in enumerate(("alice", "bob")):
        pose = np.zeros((T, J, 3))
        pose[:, 0, 1] = np.pi * k
        transl = np.stack([np.full(T, 0.8 * k), np.full(T, 0.95), np.linspace(0, 0.2, T)], axis=1)
        tracks.append(BodyTrack.from_model(model, pose, transl, np.full(P, 0.5), FPS, actor=actor))
    InteractionSequence(tuple(tracks), take="T").save(out.path("bodies.npz"))


def build(ws, model, take: str, bad: bool, stages=("fuse", "fit", "contacts", "render")) -> None:
    """Publish ``take``'s results of ``stages`` (the injected faults when ``bad``)."""

    def fuse(out):
        lost = 40 if bad else 0
        stats = {a: {"fused_with_trackers": True, "trackers": {f"{a.upper()}-PELVIS": {
            "valid_frames": 100 - lost, "rejected_jumps": 3 if bad else 0, "bridged_frames": lost}}} for a in ("alice", "bob")}
        out.path("fuse.json").write_text(json.dumps(stats))
        return {"fused_with_trackers": {"alice": True, "bob": True}}

    def fit(out):
        _bodies(out, model)
        np.savez(out.path("frames.npz"), valid=np.ones(T, np.int64),
                 **{"tracker residual (mm)|alice": np.full(T, 8.0), "tracker residual (mm)|bob": np.full(T, 9.0)})
        return {"frames": T, "max_penetration_after_mm": 14.0 if bad else 1.0,
                "penetrating_share_after": 0.03 if bad else 0.0002}

    def contacts(out):
        counts = [0] * 3 + [40] * 6 + [0] * 3
        out.path("contacts.json").write_text(json.dumps({"take": take, "contact_vertices": {"alice": counts, "bob": counts}}))
        return {"frames": T, "contact_frames": 6, "events": 1}

    def render(out):
        out.path("render.json").write_text(json.dumps({"frames": [0, 5], "views": ["view00"]}))
        for f in (0, 5):
            for kind, ext in (("rgb", "png"), ("depth", "exr"), ("mask", "png")):
                out.path(f"views/view00/{kind}/{f:05d}.{ext}").write_bytes(b"image")
        return {"frames": 2}

    computes = {"fuse": (fuse, []), "fit": (fit, [("fuse", None)]), "contacts": (contacts, [("fit", None)]),
                "render": (render, [("fit", None)])}  # fmt: skip
    for stage in stages:
        compute, depends = computes[stage]
        ws.run_stage(stage, compute, take=take, depends_on=depends)


def make_workspace(root, model, stages=("fuse", "fit", "contacts", "render")):
    """The workspace at ``root``, open for writing: takes BAD, GOOD (with ``stages``) and RAW."""
    from dualhuman_builder.workspace import Workspace

    ws = Workspace.init(root)
    for name in ("alice", "bob"):
        ws.add_actor(name, 1.7)
    for take in ("BAD", "GOOD", "RAW"):
        ws.add_take(take, actors=["alice", "bob"])
    build(ws, model, "BAD", bad=True, stages=stages)
    build(ws, model, "GOOD", bad=False, stages=stages)
    return ws


@pytest.fixture
def qws(tmp_path, body_model):
    """:func:`make_workspace` with every stage the gates read but sync (imported by the test modules: a
    ``conftest.py`` here would shadow ``tests/conftest.py``, which other packages' tests import by name)."""
    with make_workspace(tmp_path / "ws", body_model) as ws:
        yield ws
