"""Where the toolkit's data folders live.

The toolkit runs from a checkout (``scripts/setup.sh`` installs it editable), so ``rigs/`` and
``render_templates/`` are the folders at the repository root.
"""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
RIGS_DIR = REPO_ROOT / "rigs"
RENDER_TEMPLATES_DIR = REPO_ROOT / "render_templates"
