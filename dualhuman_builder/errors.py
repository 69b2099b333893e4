"""The toolkit's exceptions: each names what went wrong, where, and how to fix it.

The CLI prints ``error: <message>`` and, when present, ``fix: <fix>``, and exits with status 2.
"""

from __future__ import annotations

from pathlib import Path


class DualhumanError(Exception):
    """Base of every error the toolkit raises on purpose (bad input, missing pieces)."""

    def __init__(self, message: str, *, fix: str | None = None, path: str | Path | None = None):
        self.message = message
        self.fix = fix
        self.path = Path(path) if path is not None else None
        text = f"{path}: {message}" if path is not None else message
        super().__init__(text if fix is None else f"{text} (fix: {fix})")


class FormatError(DualhumanError):
    """A file is malformed, truncated or of another kind than expected."""


class FormatVersionError(FormatError):
    """A file or workspace was written by a newer format version than this toolkit reads."""


class WorkspaceError(DualhumanError):
    """A workspace is missing, corrupt, not writable, or its catalog disagrees with its files."""


class RigError(DualhumanError):
    """A rig or segment-mapping file names unknown segments, bones, or malformed fields."""


class BodyModelError(DualhumanError):
    """The body model cannot be built or is given inputs of the wrong shape."""
