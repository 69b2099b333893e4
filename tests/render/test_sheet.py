"""The contact sheet's frame choice (the sheet itself is drawn and checked in the demo test)."""

import numpy as np
import pytest

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.render.sheet import pick_frames, write_contact_sheet


def test_frames_spread_and_include_the_peak_of_contact():
    rendered = np.arange(0, 120, 10)
    assert pick_frames(rendered, None, 4) == [0, 40, 70, 110]
    counts = np.zeros(120)
    counts[90] = 5  # most contact at a rendered frame that the even spread misses
    assert pick_frames(rendered, counts, 4) == [0, 40, 90, 110]
    counts[:] = 0
    counts[85] = 9  # a peak between rendered frames cannot be shown in the image grid
    assert pick_frames(rendered, counts, 4) == [0, 40, 70, 110]
    assert pick_frames(rendered[:2], counts, 4) == [0, 10]


def test_incomplete_render_is_named(tmp_path):
    with pytest.raises(DualhumanError, match="not a complete render .missing cameras.json"):
        write_contact_sheet(tmp_path, tmp_path / "sheet.png")
