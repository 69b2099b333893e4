"""The layout's rules hold: import-linter's contracts (``pyproject.toml``) and the package list."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(config: Path, pythonpath: Path) -> subprocess.CompletedProcess:
    env = {"PYTHONPATH": str(pythonpath), "PATH": "/usr/bin:/bin"}
    return subprocess.run([str(LINT), "--config", str(config), "--no-cache"], cwd=config.parent, env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip


def test_import_contracts_are_kept():
    r = _lint(REPO / "pyproject.toml", REPO)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


@pytest.mark.parametrize("module, line, contract", [
    ("capture/samples.py", "import dualhuman_builder.sim.scenes", "Capture imports no later stage"),
    ("workspace/catalog.py", "import dualhuman_builder.fit.fuse", "The workspace imports no stage"),
    ("sync/clock.py", "import dualhuman_builder.fit.fuse", "Stage packages follow the pipeline's order"),
    ("render/cameras.py", "import dualhuman_builder.capture.samples", "Render never imports capture"),
    ("tracks.py", "import dualhuman_builder.cli", "the CLI on top (nothing imports it)"),
])  # fmt: skip
def test_a_broken_contract_fails_the_lint(tmp_path, module, line, contract):
    """A copy of the package with one forbidden import added: ``lint-imports`` exits non-zero and
    names the contract."""
    shutil.copytree(REPO / "dualhuman_builder", tmp_path / "dualhuman_builder",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / "dualhuman_builder" / module
    target.write_text(target.read_text() + f"\n{line}  # added by the test\n")
    r = _lint(tmp_path / "pyproject.toml", tmp_path)
    assert r.returncode != 0, r.stdout
    broken = r.stdout[r.stdout.index("Broken contracts"):] if "Broken contracts" in r.stdout else r.stdout
    assert contract in " ".join(broken.split()), r.stdout


def test_every_package_is_listed_for_the_wheel():
    """``[tool.setuptools] packages`` lists every folder of the package (it is a list, not
    discovery, because rigs/ and render_templates/ ship inside it)."""
    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "dualhuman_builder").rglob("__init__.py")}
    found |= {"dualhuman_builder.rigs", "dualhuman_builder.render_templates"}
    assert listed == found, f"missing: {sorted(found - listed)}; stale: {sorted(listed - found)}"


def test_no_import_cycles():
    """No import cycle between the package's modules, counting imports inside functions too (a
    cycle hidden in a function still ties two modules' designs together)."""
    import grimp

    graph = grimp.build_graph("dualhuman_builder")
    cycles = []
    for m in sorted(graph.modules):
        for other in graph.find_modules_directly_imported_by(m):
            if other == m:
                continue
            chain = graph.find_shortest_chain(importer=other, imported=m)
            if chain:
                cycles.append(" -> ".join((m, *chain)))
    assert not cycles, "import cycles:\n" + "\n".join(cycles[:10])
