"""The gates on a simulated take through the whole path (scene, devices through real transports,
sync, fuse, fit), with the realistic device errors: its real tracker losses and overlap exceed a
test config's thresholds, it is flagged, and `export` leaves it out unless asked to include it."""

from __future__ import annotations

import json

import pytest

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.quality.gates import check_take

pytestmark = pytest.mark.slow


def test_a_simulated_take_is_flagged_on_its_real_figures_and_left_out_of_the_export(tmp_path, body_model):
    from dualhuman_builder.export.collect import run_export
    from dualhuman_builder.fit.fitter import FitConfig
    from dualhuman_builder.fit.stage import run_fit
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.sim.stage import DEFAULT_ACTORS, ensure_actors, simulate_take
    from dualhuman_builder.workspace import Workspace

    quiet = lambda _m: None
    with Workspace.init(tmp_path / "ws") as ws:
        ws.add_rig(RIGS_DIR / "sim.toml")
        shapes = ensure_actors(ws, DEFAULT_ACTORS, body_model, quiet)
        simulate_take(ws, "T", "handshake", {"type": "handshake", "seed": 11, "fps": 15.0}, DEFAULT_ACTORS, shapes,
                      model=body_model, log=quiet, preset="realistic")  # fmt: skip
        # a collision term too weak to part the hands: the fit leaves penetration for the gate to find on
        # every recording (the product's weight leaves anywhere from none to 2 mm, by the transports' timing)
        run_fit(ws, "T", FitConfig(collision_weight=1.0, collision_rounds=1), log=quiet, fps=15.0)
        fuse = json.loads(ws.artifacts("fuse", "T")["fuse.json"].read_text())
        bridged = {s: v["bridged_frames"] / (v["valid_frames"] + v["bridged_frames"])
                   for a in fuse.values() for s, v in a["trackers"].items()}  # fmt: skip
        summary = ws.stage_record("fit", "T")["summary"]
        worst = max(bridged.values())
        assert worst > 0 and summary["max_penetration_after_mm"] > 0, (bridged, summary)
        cfg = {"tracker_loss": {"max_share": worst / 2}, "penetration": {"max_mm": summary["max_penetration_after_mm"] / 2}}
        flags = check_take(ws, "T", cfg)
        assert {"tracker_loss", "penetration"} <= {f.gate for f in flags}, flags
        with pytest.raises(WorkspaceError, match="every fitted take is flagged"):
            run_export(ws, tmp_path / "export", log=quiet)
        m = run_export(ws, tmp_path / "export", log=quiet, include_flagged=True)
        assert list(m["sequences"]) == ["T"] and list(m["quality"]["included"]) == ["T"]
