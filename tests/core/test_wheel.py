"""The package installs as a wheel and works from outside the checkout.

Builds the wheel, installs it into a fresh virtual environment that borrows the already installed
dependencies (a ``.pth`` line pointing at this environment's site-packages, so nothing is
downloaded), and from a folder outside the checkout runs ``dualhuman doctor --no-render`` and makes
a small scene. Rigs, render templates and the label vocabulary must come from the installed package.
"""

from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


#: Building and installing the wheel takes a while.
pytestmark = pytest.mark.slow


def _run(cmd, cwd, timeout=600, **kw):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout, **kw)
    assert r.returncode == 0, f"{cmd} -> {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", tmp / "dist", REPO], cwd=tmp)
    (wheel,) = (tmp / "dist").glob("dualhuman_builder-*.whl")
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=tmp)
    site = Path(sysconfig.get_path("purelib", vars={"base": str(venv), "platbase": str(venv)}))
    (site / "borrowed.pth").write_text(sysconfig.get_path("purelib") + "\n")  # this environment's dependencies
    _run([sys.executable, "-m", "pip", "--python", venv / "bin" / "python", "install", "--no-deps", "--no-index", "-q", wheel],
         cwd=tmp)  # fmt: skip
    outside = tmp / "elsewhere"
    outside.mkdir()
    return wheel, venv, outside


def test_the_wheel_holds_the_package_data_and_no_top_level_cli(installed):
    wheel, _, _ = installed
    names = zipfile.ZipFile(wheel).namelist()
    assert "dualhuman_builder/rigs/sim.toml" in names and "dualhuman_builder/rigs/mvn_anny.toml" in names
    assert "dualhuman_builder/render_templates/studio.json" in names
    assert "dualhuman_builder/vocabulary.toml" in names
    assert "dualhuman_builder/cli/__init__.py" in names
    assert not [n for n in names if "/" not in n], "nothing installs as a top-level module (no cli.py)"
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    text = zipfile.ZipFile(wheel).read(entry_points).decode()
    assert "dualhuman = dualhuman_builder.cli:main" in text and "sim = dualhuman_builder.sim.source:SimSource" in text


def test_the_installed_tool_works_outside_the_checkout(installed):
    _, venv, outside = installed
    py = venv / "bin" / "python"
    where = json.loads(_run([py, "-c", "import json, dualhuman_builder, dualhuman_builder.resources as r; "
                             "print(json.dumps([dualhuman_builder.__file__, str(r.RIGS_DIR), str(r.RENDER_TEMPLATES_DIR)]))"],
                            cwd=outside).stdout)  # fmt: skip
    assert all(p.startswith(str(venv)) for p in where), where
    r = _run([venv / "bin" / "dualhuman", "doctor", "--no-render", "--json"], cwd=outside)
    checks = json.loads(r.stdout)
    assert checks, "doctor reported nothing"
    _run([venv / "bin" / "dualhuman", "scene", "make", "--type", "handshake", "--seed", "1", "--fps", "10",
              "--out", "hs.npz"], cwd=outside)  # fmt: skip
    assert (outside / "hs.npz").stat().st_size > 0
    _run([venv / "bin" / "dualhuman", "rig", "check", Path(where[1]) / "studio.toml"], cwd=outside)
