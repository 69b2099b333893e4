"""Where the toolkit's bundled data lives, found with :mod:`importlib.resources`.

* :data:`RIGS_DIR` — the rigs (``sim.toml``, ``studio.toml``), the MVN -> anny segment mapping
  (``mvn_anny.toml``) and the body-part regions (``anny_regions.toml``);
* :data:`RENDER_TEMPLATES_DIR` — the render templates (``studio.json``, ``outdoor.json``);
* :data:`VOCABULARY_PATH` — the interaction-label vocabulary.

In a checkout the first two are the top-level ``rigs/`` and ``render_templates/`` folders; the
package ships them as the subpackages ``dualhuman_builder.rigs`` and
``dualhuman_builder.render_templates`` (``[tool.setuptools.package-dir]`` in ``pyproject.toml``),
so an installed wheel finds them from any working directory.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def _folder(package: str) -> Path:
    return Path(str(files(package)))


RIGS_DIR = _folder("dualhuman_builder.rigs")
RENDER_TEMPLATES_DIR = _folder("dualhuman_builder.render_templates")
VOCABULARY_PATH = _folder("dualhuman_builder") / "vocabulary.toml"
