"""Where the toolkit's data folders live.

The toolkit runs from a checkout (``scripts/setup.sh`` installs it editable), so ``rigs/`` and
``render_templates/`` are the folders at the repository root.
"""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
RIGS_DIR = REPO_ROOT / "rigs"
RENDER_TEMPLATES_DIR = REPO_ROOT / "render_templates"


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment for a ``python -m dualhuman_builder...`` child, with this source
    tree first on ``PYTHONPATH`` (so the child imports the same code), plus ``extra``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO_ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra or {})
    return env
