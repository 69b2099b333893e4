"""The fit report: self-contained HTML with hand-drawn SVG charts, and a Pillow PNG summary."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np
import pytest
from PIL import Image

from dualhuman_builder.fit.report import (
    DROPOUT_COLOUR,
    PALETTE,
    decimate_minmax,
    is_validity_chart,
    write_fit_report,
)

LEFT, PLOT_W, TOP = 150, 790, 12  # the SVG plot frame (see report._LEFT / _PLOT_W / _TOP)
VOID = {"meta", "br", "hr", "img", "input", "link"}


class _Checker(HTMLParser):
    """Parses the page strictly: every non-void tag must be closed in order."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.tags: list[tuple[str, dict]] = []
        self.text: list[str] = []
        self.errors: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def _parse(path):
    c = _Checker()
    c.feed(path.read_text(encoding="utf-8"))
    c.close()
    assert c.errors == [] and c.stack == [], (c.errors, c.stack)
    return c


def _pieces(d: str) -> list[np.ndarray]:
    """Split an SVG path's ``d`` into its subpaths, each an (N, 2) array of points."""
    out = []
    for sub in d.split("M")[1:]:
        sub = sub.replace("h0", "").replace("L", " ")
        out.append(np.array([[float(v) for v in p.split(",")] for p in sub.split()]))
    return out


def _paths(checker, label=None):
    return [a["d"] for t, a in checker.tags if t == "path" and (label is None or a.get("data-label") == label)]


SYNC = {
    "reference": "host",
    "clocks": {
        "xsens": {
            "offset_s": 0.0123,
            "drift_ppm": 12.5,
            "lag_correction_ms": 3.2,
            "host_fit": {"rms_ms": 0.41, "samples": 1000},
            "firmware": "4.2",
        }
    },
    "lags": {"vive": {"lag_ms": 12.34, "std_ms": 0.8, "peak": 0.93}, "can": {"error": "no overlap with host"}},
    "mounts": {
        "<b>x</b>": {
            "LHR-01": {
                "rotation_deg": [1.0, 2.0, 3.0],
                "translation_mm": [10.0, 20.0, 30.5],
                "rotation_std_deg": 0.3,
                "translation_std_mm": 1.2,
                "frames_used": 400,
            }
        }
    },
    "warnings": ["clock <xsens> drift above 50 ppm"],
    "schema": 2,
}


def test_page_parses_one_svg_per_chart_and_tables(tmp_path):
    t = 120
    rng = np.random.default_rng(0)
    series = {
        "Orientation residual (deg)": {"sim-a": rng.normal(2, 0.3, t), "sim-b": rng.normal(3, 0.3, t)},
        "Tracker residual (mm)": {"SIM-A-LHAND": rng.normal(10, 1, t)},
        "Penetration depth (mm)": {"before collision term": np.abs(rng.normal(4, 1, t)), "after": np.zeros(t)},
        "Tracker valid": {"SIM-A-LHAND": np.ones(t), "SIM-B-RHAND": np.r_[np.ones(60), np.zeros(60)]},
    }
    summary = {"frames": t, "mean joint error (mm)": 11.234, "actor a": {"height (m)": 1.7213}}
    out = write_fit_report(
        tmp_path / "sub" / "r.html", take="take_001", fps=30.0, series=series, sync=SYNC, summary=summary
    )
    assert out == tmp_path / "sub" / "r.html"
    c = _parse(out)
    svgs = [a for tag, a in c.tags if tag == "svg"]
    assert len(svgs) == 4
    assert [a["aria-label"] for a in svgs] == list(series)
    assert sum(tag == "script" or (tag == "link") for tag, _ in c.tags) == 0  # nothing external
    text = " ".join(c.text)
    for expected in (
        "11.23",
        "1.72",
        "Clocks",
        "Lags",
        "Tracker mounts",
        "0.012",
        "12.50",
        "rms_ms",
        "0.410",
        "firmware",
        "no overlap with host",
        "[1.00, 2.00, 3.00]",
        "frames_used",
        "schema",
    ):
        assert expected in text, expected
    # one line per label, in legend order, in palette colours
    assert [a["stroke"] for t_, a in c.tags if t_ == "path"] == [
        PALETTE[0],
        PALETTE[1],
        PALETTE[0],
        PALETTE[0],
        PALETTE[1],
    ]


def test_nan_gaps_break_the_line(tmp_path):
    y = np.arange(50, dtype=float)
    y[10:13] = np.nan
    y[[29, 31]] = np.nan  # frame 30 is an isolated point
    c = _parse(
        write_fit_report(
            tmp_path / "r.html", take="t", fps=10.0, series={"Residual (mm)": {"a": y}}, sync={}, summary={}
        )
    )
    (d,) = _paths(c, "a")
    pieces = _pieces(d)
    assert [len(p) for p in pieces] == [10, 16, 1, 18]
    px_per_frame = PLOT_W / 49
    np.testing.assert_allclose([p[0, 0] for p in pieces], LEFT + np.array([0, 13, 30, 32]) * px_per_frame, atol=0.06)
    assert "h0" in d  # the lone point is drawn as a dot
    # y decreases as values grow: within a piece, points climb monotonically
    assert all(np.all(np.diff(p[:, 1]) < 0) for p in pieces if len(p) > 1)


def test_long_series_is_downsampled_but_spike_survives(tmp_path):
    t, spike = 18000, 12345
    rng = np.random.default_rng(1)
    y = rng.uniform(0.0, 1.0, t)
    y[spike] = 50.0
    y[9000] = np.nan
    series = {
        "Orientation residual (deg)": {"sim-a": y, "sim-b": rng.uniform(0, 1, t)},
        "Tracker residual (mm)": {f"T{i}": rng.normal(10, 2, t) for i in range(8)},
        "Penetration depth (mm)": {"before": rng.uniform(0, 8, t), "after": rng.uniform(0, 2, t)},
        "Tracker valid": {f"T{i}": (rng.random(t) > 0.01).astype(float) for i in range(8)},
    }
    out = write_fit_report(tmp_path / "r.html", take="long", fps=30.0, series=series, sync=SYNC, summary={})
    size = out.stat().st_size
    assert size < 600_000, size  # well under 2 MB for a 10-minute take
    c = _parse(out)
    pts = np.concatenate(_pieces(_paths(c, "sim-a")[0]))
    assert len(pts) <= 2 * PLOT_W  # min/max per pixel column, not 18,000 points
    top = int(np.argmin(pts[:, 1]))
    others = np.delete(pts[:, 1], top)
    assert pts[top, 1] < others.min() - 100  # the one-frame spike stands far above the rest
    assert pts[top, 0] == pytest.approx(LEFT + spike / (t - 1) * PLOT_W, abs=0.06)
    assert len(_pieces(_paths(c, "sim-a")[0])) == 2  # the single NaN frame still breaks the line

    idx, starts = decimate_minmax(y, 500)
    assert spike in idx and idx.size <= 1000 and np.all(np.diff(idx) > 0)
    assert starts.tolist() == [0, int(np.searchsorted(idx, 9000))]
    idx2, starts2 = decimate_minmax(np.array([1.0, np.nan, 3.0]), 10)
    assert idx2.tolist() == [0, 2] and starts2.tolist() == [0, 1]
    assert decimate_minmax(np.full(5, np.nan), 10)[0].size == 0


def test_validity_strips_show_dropouts(tmp_path):
    t = 300
    v = np.ones(t)
    v[100:110] = 0
    v[250] = np.nan  # unknown counts as a dropout
    c = _parse(
        write_fit_report(
            tmp_path / "r.html", take="t", fps=30.0, series={"Tracker valid": {"LH": v}}, sync={}, summary={}
        )
    )
    assert _paths(c) == []  # strips, not lines
    rects = [a for tag, a in c.tags if tag == "rect" and a.get("class") == "dropout"]
    assert len(rects) == 2
    px = PLOT_W / (t - 1)
    assert float(rects[0]["x"]) == pytest.approx(LEFT + np.floor(100 * px), abs=1)
    assert float(rects[0]["width"]) == pytest.approx(10 * px, abs=1.5)
    assert all(r["fill"] == DROPOUT_COLOUR for r in rects)
    text = " ".join(c.text)
    assert "96.3 %" in text and "0.33 s" in text  # 289/300 valid, longest dropout 10 frames
    assert is_validity_chart("Tracker valid") and is_validity_chart("tracker-VALID")
    assert not is_validity_chart("Tracker invalid") and not is_validity_chart("valid residual (mm)")


def test_data_strings_are_escaped(tmp_path):
    evil = "<b>x</b>"
    out = write_fit_report(
        tmp_path / "r.html",
        take=evil,
        fps=30.0,
        series={f"{evil} residual": {evil: np.ones(5)}, "Tracker valid": {evil: np.ones(5)}},
        sync=SYNC,
        summary={evil: evil},
    )
    page = out.read_text(encoding="utf-8")
    assert evil not in page and "<xsens>" not in page
    assert page.count("&lt;b&gt;x&lt;/b&gt;") >= 6  # take, title, chart, labels, mount actor, summary
    assert "clock &lt;xsens&gt; drift above 50 ppm" in page
    c = _parse(out)
    assert [t for t, _ in c.tags].count("b") == 1  # only the page's own bold reference clock


def test_png_summary(tmp_path):
    t = 600
    x = np.linspace(0, 6, t)
    v = np.ones(t)
    v[200:260] = 0
    series = {"Residual (deg)": {"a": np.sin(x) + 2, "b": np.cos(x) + 2}, "Tracker valid": {"LH": v}}
    png = tmp_path / "img" / "r.png"
    write_fit_report(tmp_path / "r.html", take="t", fps=30.0, series=series, sync={}, summary={}, png_path=png)
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size == (1200, 800)
        colours = {c for _, c in im.convert("RGB").getcolors(1 << 20)}
    hexes = {"#%02x%02x%02x" % c for c in colours}
    assert {PALETTE[0], PALETTE[1], DROPOUT_COLOUR} <= hexes
    write_fit_report(
        tmp_path / "r.html", take="t", fps=30.0, series=series, sync={}, summary={}, png_path=png, png_size=(640, 360)
    )
    with Image.open(png) as im:
        assert im.size == (640, 360)


def test_empty_series_still_gives_a_report(tmp_path):
    png = tmp_path / "r.png"
    out = write_fit_report(
        tmp_path / "r.html", take="t", fps=30.0, series={}, sync=SYNC, summary={"frames": 0}, png_path=png
    )
    c = _parse(out)
    assert [t for t, _ in c.tags].count("svg") == 0
    text = " ".join(c.text)
    assert "No series." in text and "Tracker mounts" in text and "12.34" in text
    with Image.open(png) as im:
        assert im.size == (1200, 800)
    # a chart with no lines and a line with no finite value are drawn empty, not rejected
    c = _parse(
        write_fit_report(
            tmp_path / "r2.html",
            take="t",
            fps=30.0,
            series={"Empty (mm)": {}, "All NaN (mm)": {"a": np.full(4, np.nan)}},
            sync={},
            summary={},
        )
    )
    assert [t for t, _ in c.tags].count("svg") == 2 and _paths(c) == []
    assert "No sync report." in " ".join(c.text)


def test_sync_with_odd_shapes_is_rendered_not_rejected(tmp_path):
    sync = {"clocks": [1, 2], "lags": {"vive": 4.0}, "mounts": {"a": "none"}, "warnings": []}
    c = _parse(write_fit_report(tmp_path / "r.html", take="t", fps=30.0, series={}, sync=sync, summary={}))
    text = " ".join(c.text)
    assert "[1, 2]" in text and "4.00" in text and "none" in text and "Other" in text


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"series": {"R": {"a": np.zeros((3, 2))}}}, r"series\['R'\]\['a'\]: expected a 1-D .* shape \(3, 2\)"),
        ({"series": {"R": {"a": np.zeros(0)}}}, r"series\['R'\]\['a'\]: empty array"),
        ({"series": {"R": {"a": [0.0, np.inf]}}}, r"1 infinite value\(s\), first at frame 1"),
        ({"series": {"R": {"a": ["x", "y"]}}}, r"series\['R'\]\['a'\]: values must be numbers"),
        ({"series": {"R": [1, 2]}}, r"series\['R'\] must be a dict"),
        ({"series": [1]}, r"series must be a dict"),
        ({"series": {"Tracker valid": {"a": [0, 2]}}}, r"validity chart takes 0/1"),
        ({"fps": 0.0}, r"fps must be a finite number > 0"),
        ({"fps": float("nan")}, r"fps must be a finite number > 0"),
        ({"take": ""}, r"take must be a non-empty string"),
        ({"summary": [1]}, r"summary must be a dict"),
        ({"sync": "x"}, r"sync must be a dict"),
        ({"png_path": "r.png", "png_size": (10, 10)}, r"png_size must be"),
    ],
)
def test_bad_input_raises(tmp_path, kwargs, match):
    args = {"take": "t", "fps": 30.0, "series": {}, "sync": {}, "summary": {}} | kwargs
    if "png_path" in args:
        args["png_path"] = tmp_path / args["png_path"]
    with pytest.raises(ValueError, match=match):
        write_fit_report(tmp_path / "r.html", **args)
    assert not (tmp_path / "r.html").exists()


def test_long_take_uses_minutes_on_the_time_axis(tmp_path):
    c = _parse(
        write_fit_report(
            tmp_path / "r.html", take="t", fps=30.0, series={"R (mm)": {"a": np.ones(18000)}}, sync={}, summary={}
        )
    )
    text = " ".join(c.text)
    assert "time (min:s)" in text and re.search(r"\b8:00\b", text)
