"""The fit report: self-contained HTML with inline matplotlib SVG charts, and a matplotlib PNG summary."""

from __future__ import annotations

import html
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from html.parser import HTMLParser

import numpy as np
import pytest
from PIL import Image

from dualhuman_builder.fit.report import (
    DROPOUT_COLOUR,
    PALETTE,
    VALID_COLOUR,
    decimate_minmax,
    is_validity_chart,
    write_fit_report,
)

PLOT_PX = 790  # pixel columns of an HTML chart's plot (report._PLOT_PX): the decimation width
VOID = {"meta", "br", "hr", "img", "input", "link"}
SVG = "{http://www.w3.org/2000/svg}"


class _Checker(HTMLParser):
    """Parses the page strictly: every non-void tag must be closed in order."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.tags: list[tuple[str, dict]] = []
        self.text: list[str] = []
        self.comments: list[str] = []  # matplotlib writes each drawn string as a comment next to its glyphs
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

    def handle_comment(self, data):
        self.comments.append(html.unescape(data.strip()))


def _parse(path):
    c = _Checker()
    c.feed(path.read_text(encoding="utf-8"))
    c.close()
    assert c.errors == [] and c.stack == [], (c.errors, c.stack)
    return c


def _svgs(path) -> list[ET.Element]:
    """The page's inline charts, each parsed as a standalone XML document (so each is well-formed SVG)."""
    return [ET.fromstring(s) for s in re.findall(r"<svg .*?</svg>", path.read_text(encoding="utf-8"), re.DOTALL)]


def _by_id(svg: ET.Element, gid: str) -> ET.Element | None:
    return next((e for e in svg.iter() if e.get("id") == gid), None)


def _pieces(d: str) -> list[np.ndarray]:
    """Split a matplotlib SVG path's ``d`` (M/L commands) into its subpaths, each an (N, 2) array."""
    out = []
    for sub in re.split(r"\s*M\s*", d.strip())[1:]:
        nums = [float(v) for v in re.split(r"[\sL]+", sub.strip().rstrip("z").strip()) if v]
        out.append(np.array(nums).reshape(-1, 2))
    return out


def _line(svg: ET.Element, gid: str) -> tuple[list[np.ndarray], str, tuple[float, float, float, float]]:
    """Subpaths, stroke colour and plot rectangle (x, y, w, h from its clip path) of the line ``gid``."""
    (path,) = _by_id(svg, gid).iter(SVG + "path")
    clip = path.get("clip-path")[len("url(#") : -1]
    rect = _by_id(svg, clip).find(SVG + "rect")
    box = tuple(float(rect.get(k)) for k in ("x", "y", "width", "height"))
    return _pieces(path.get("d")), re.search(r"stroke: (#[0-9a-f]{6})", path.get("style")).group(1), box


def _rects(group: ET.Element) -> list[tuple[float, float, str]]:
    """(x, width, fill) of each rectangle path in a ``broken_barh`` group."""
    out = []
    for path in group.iter(SVG + "path"):
        (pts,) = _pieces(path.get("d"))
        out.append((pts[:, 0].min(), np.ptp(pts[:, 0]), re.search(r"fill: (#[0-9a-f]{6})", path.get("style")).group(1)))
    return sorted(out)


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
    assert [p.name for p in out.parent.iterdir()] == ["r.html"]  # no temporary file left behind
    c = _parse(out)
    assert [a["aria-label"] for tag, a in c.tags if tag == "svg"] == list(series)
    svgs = _svgs(out)
    assert len(svgs) == 4 and all(s.tag == SVG + "svg" for s in svgs)
    # self-contained: no scripts or stylesheets, every reference is to an id in the page, and the only
    # URLs are XML namespace names
    page = out.read_text(encoding="utf-8")
    assert not any(tag in ("script", "link", "img", "iframe", "object") for tag, _ in c.tags)
    refs = [v for _, a in c.tags for k, v in a.items() if k in ("href", "xlink:href", "src")]
    assert refs and all(v.startswith("#") for v in refs), refs
    assert "url(http" not in page and "@import" not in page
    assert set(re.findall(r"https?://[^\"'\s<>)]+", page)) == {
        "http://www.w3.org/2000/svg",
        "http://www.w3.org/1999/xlink",
    }
    ns_uses = re.findall(r"(\S+)=\"https?://", page)
    assert set(ns_uses) == {"xmlns", "xmlns:xlink"}, ns_uses
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
    # the charts draw their legends, strip labels and time axis
    drawn = set(c.comments)
    assert {"sim-a", "sim-b", "SIM-A-LHAND", "SIM-B-RHAND", "before collision term", "after", "time (s)"} <= drawn
    # one line per label, in legend order, in palette colours
    colours = [
        _line(svgs[k - 1], f"chart-{k}-line-{i}")[1] for k, n in ((1, 2), (2, 1), (3, 2)) for i in range(1, n + 1)
    ]
    assert colours == [PALETTE[0], PALETTE[1], PALETTE[0], PALETTE[0], PALETTE[1]]
    # one time axis: every chart's plot spans the same horizontal extent
    boxes = [_line(svgs[k - 1], f"chart-{k}-line-1")[2] for k in (1, 2, 3)]
    strip = _by_id(svgs[3], "chart-4-valid-1")
    (pts,) = _pieces(next(strip.iter(SVG + "path")).get("d"))
    clip = _by_id(svgs[3], next(strip.iter(SVG + "path")).get("clip-path")[5:-1]).find(SVG + "rect")
    boxes.append((float(clip.get("x")), 0.0, float(clip.get("width")), 0.0))
    assert len({(x, w) for x, _, w, _ in boxes}) == 1, boxes
    assert pts[:, 0].min() == pytest.approx(boxes[0][0])  # the first strip starts at 0 s


def test_nan_gaps_break_the_line(tmp_path):
    y = np.arange(50, dtype=float)
    y[10:13] = np.nan
    y[[29, 31]] = np.nan  # frame 30 is an isolated point
    out = write_fit_report(
        tmp_path / "r.html", take="t", fps=10.0, series={"Residual (mm)": {"a": y}}, sync={}, summary={}
    )
    _parse(out)
    (svg,) = _svgs(out)
    pieces, _, (x0, _, w, _) = _line(svg, "chart-1-line-1")
    pieces = [p for p in pieces if len(p) > 1]  # a moveto alone (the isolated frame) draws nothing
    frame_x = x0 + np.arange(50) / 49 * w
    np.testing.assert_allclose([p[0, 0] for p in pieces], frame_x[[0, 13, 32]], atol=1e-3)
    np.testing.assert_allclose([p[-1, 0] for p in pieces], frame_x[[9, 28, 49]], atol=1e-3)
    # y decreases as values grow: within a piece, points climb monotonically
    assert all(np.all(np.diff(p[:, 1]) < 0) for p in pieces)
    # the lone frame is drawn as a dot, at its value on the same scale as the line
    dots = list(_by_id(svg, "chart-1-dots-1").iter(SVG + "use"))
    assert len(dots) == 1
    piece = pieces[1]  # frames 13..28, values 13..28
    y_of = np.polyfit([13.0, 28.0], [piece[0, 1], piece[-1, 1]], 1)
    assert float(dots[0].get("x")) == pytest.approx(frame_x[30], abs=1e-3)
    assert float(dots[0].get("y")) == pytest.approx(np.polyval(y_of, 30.0), abs=1e-3)


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
    png = tmp_path / "r.png"
    out = write_fit_report(
        tmp_path / "r.html", take="long", fps=30.0, series=series, sync=SYNC, summary={}, png_path=png
    )
    size = out.stat().st_size
    assert size < 1_000_000, size  # 14 noisy lines of 18,000 frames: decimated, ~45 kB a line whatever T
    _parse(out)
    svg = _svgs(out)[0]
    pieces, _, (x0, _, w, h) = _line(svg, "chart-1-line-1")
    pts = np.concatenate(pieces)
    assert len(pts) <= 2 * PLOT_PX  # min/max per pixel column, not 18,000 points
    top = int(np.argmin(pts[:, 1]))
    others = np.delete(pts[:, 1], top)
    assert pts[top, 1] < others.min() - 0.5 * h  # the one-frame spike stands far above the rest
    assert pts[top, 0] == pytest.approx(x0 + spike / (t - 1) * w, abs=1e-3)
    assert len(pieces) == 2  # the single NaN frame still breaks the line
    assert _by_id(svg, "chart-1-dots-1") is None
    # the PNG shows the spike too: a tall stroke of line colour, where the spike's time falls on the plot (whose width the full-length validity strips give)
    with Image.open(png) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    blue = np.all(np.abs(rgb - [0x1F, 0x77, 0xB4]) < 40, axis=-1)[: rgb.shape[0] // 4]  # first of 4 charts
    tall = np.flatnonzero(blue.sum(0) > 60)  # columns with a long vertical stroke (the noise is ~3 px high)
    strip_cols = np.flatnonzero(np.all(rgb == [0xCF, 0xE8, 0xCF], axis=-1).any(0))
    left, width = strip_cols[0], strip_cols[-1] + 1 - strip_cols[0]
    assert tall.size and np.ptp(tall) <= 2, tall
    assert tall.mean() == pytest.approx(left + spike / (t - 1) * width, abs=2)

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
    out = write_fit_report(
        tmp_path / "r.html",
        take="t",
        fps=30.0,
        series={"Tracker valid": {"LH": v, "RH": np.ones(t)}},
        sync={},
        summary={},
    )
    c = _parse(out)
    (svg,) = _svgs(out)
    assert not [e for e in svg.iter() if (e.get("id") or "").startswith("chart-1-line")]  # strips, not lines
    (valid,) = _rects(_by_id(svg, "chart-1-valid-1"))
    x0, w = valid[0], valid[1] * (t - 1) / t  # the valid strip spans all t frames; the axis ends at frame t - 1
    assert valid[2] == VALID_COLOUR
    rects = _rects(_by_id(svg, "chart-1-dropouts-1"))
    assert len(rects) == 2 and all(fill == DROPOUT_COLOUR for *_, fill in rects)
    col = w / PLOT_PX  # one pixel column
    assert rects[0][0] == pytest.approx(x0 + 100 / (t - 1) * w, abs=col)
    assert rects[0][1] == pytest.approx(10 / (t - 1) * w, abs=1.5 * col)
    assert rects[1][0] == pytest.approx(x0 + 250 / (t - 1) * w, abs=col)
    assert rects[1][1] == pytest.approx(
        col * np.ceil(251 * PLOT_PX / (t - 1)) - col * np.floor(250 * PLOT_PX / (t - 1))
    )
    # in a 10-minute take one frame is 1/23 of a pixel column: its dropout is still drawn one column wide
    long = np.ones(18000)
    long[5000] = 0
    out2 = write_fit_report(
        tmp_path / "r2.html", take="t", fps=30.0, series={"Tracker valid": {"LH": long}}, sync={}, summary={}
    )
    ((x, width, fill),) = _rects(_by_id(_svgs(out2)[0], "chart-1-dropouts-1"))
    assert fill == DROPOUT_COLOUR and width == pytest.approx(col) and x == pytest.approx(x0 + 5000 / 17999 * w, abs=col)
    assert _by_id(svg, "chart-1-dropouts-2") is None and _by_id(svg, "chart-1-valid-2") is not None
    assert {"LH", "RH"} <= set(c.comments)  # one labelled row per label
    text = " ".join(c.text)
    assert "96.3 %" in text and "0.33 s" in text  # 289/300 valid, longest dropout 10 frames
    assert is_validity_chart("Tracker valid") and is_validity_chart("tracker-VALID")
    assert not is_validity_chart("Tracker invalid") and not is_validity_chart("valid residual (mm)")


def test_data_strings_are_escaped(tmp_path):
    evil = "<b>x</b>"
    money = r"cost $\frac$ -->"  # not matplotlib math text, and no end of an HTML comment
    out = write_fit_report(
        tmp_path / "r.html",
        take=evil,
        fps=30.0,
        series={f"{evil} residual": {evil: np.ones(5), money: np.zeros(5)}, "Tracker valid": {evil: np.ones(5)}},
        sync=SYNC,
        summary={evil: evil},
        png_path=tmp_path / "r.png",
    )
    page = out.read_text(encoding="utf-8")
    assert evil not in page and "<xsens>" not in page
    assert page.count("&lt;b&gt;x&lt;/b&gt;") >= 6  # take, title, chart, labels, mount actor, summary
    assert "clock &lt;xsens&gt; drift above 50 ppm" in page
    c = _parse(out)
    assert [t for t, _ in c.tags].count("b") == 1  # only the page's own bold reference clock
    # drawn literally in the legends: no markup, no math text, and the label cannot end its comment early
    assert evil in c.comments and r"cost $\frac$ - ->" in c.comments


def test_png_summary(tmp_path):
    t = 600
    x = np.linspace(0, 6, t)
    v = np.ones(t)
    v[200:260] = 0
    series = {"Residual (deg)": {"a": np.sin(x) + 2, "b": np.cos(x) + 2}, "Tracker valid": {"LH": v}}
    png = tmp_path / "img" / "r.png"
    write_fit_report(tmp_path / "r.html", take="t", fps=30.0, series=series, sync={}, summary={}, png_path=png)
    assert sorted(p.name for p in png.parent.iterdir()) == ["r.png"]
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size == (1200, 800)
        rgb = np.asarray(im.convert("RGB"))
    packed = np.unique((rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2])
    hexes = {f"#{int(v):06x}" for v in packed}
    assert {PALETTE[0], PALETTE[1], DROPOUT_COLOUR, VALID_COLOUR} <= hexes

    # the dropout sits at frames 200..260 of the strip's time axis (which ends at frame 599)
    def mask(hex_colour):
        return np.all(rgb == [int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)], axis=-1)

    strip_cols = np.flatnonzero(mask(VALID_COLOUR).any(0) | mask(DROPOUT_COLOUR).any(0))
    red_cols = np.flatnonzero(mask(DROPOUT_COLOUR).any(0))
    left, width = strip_cols[0], strip_cols[-1] + 1 - strip_cols[0]
    assert red_cols[0] == pytest.approx(left + 200 / 599 * width, abs=2)
    assert red_cols[-1] + 1 == pytest.approx(left + 260 / 599 * width, abs=2)
    assert np.all(np.diff(red_cols) == 1)
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
    out = write_fit_report(
        tmp_path / "r2.html",
        take="t",
        fps=30.0,
        series={"Empty (mm)": {}, "All NaN (mm)": {"a": np.full(4, np.nan)}, "Tracker valid": {}},
        sync={},
        summary={},
        png_path=png,
    )
    c = _parse(out)
    assert [t for t, _ in c.tags].count("svg") == 3
    assert c.comments.count("no data") == 3
    line = _by_id(_svgs(out)[1], "chart-2-line-1")
    assert line is not None and not list(line.iter(SVG + "path")) and "a" in c.comments  # in the legend only
    assert "No sync report." in " ".join(c.text)


def test_sync_with_odd_shapes_is_rendered_not_rejected(tmp_path):
    sync = {"clocks": [1, 2], "lags": {"vive": 4.0}, "mounts": {"a": "none"}, "warnings": []}
    c = _parse(write_fit_report(tmp_path / "r.html", take="t", fps=30.0, series={}, sync=sync, summary={}))
    text = " ".join(c.text)
    assert "[1, 2]" in text and "4.00" in text and "none" in text and "Other" in text


@pytest.mark.slow
def test_reports_are_written_from_threads_without_pyplot(tmp_path):
    rng = np.random.default_rng(2)

    def one(k):
        series = {
            "Residual (mm)": {"a": rng.normal(size=2000)},
            "Tracker valid": {"a": np.r_[np.ones(1000), np.zeros(1000)]},
        }
        return write_fit_report(
            tmp_path / f"r{k}.html",
            take=f"t{k}",
            fps=30.0,
            series=series,
            sync={},
            summary={},
            png_path=tmp_path / f"r{k}.png",
        )

    with ThreadPoolExecutor(4) as pool:
        outs = list(pool.map(one, range(6)))
    for k, out in enumerate(outs):
        assert len(_svgs(out)) == 2 and f"Fit report: t{k}" in out.read_text(encoding="utf-8")
        with Image.open(tmp_path / f"r{k}.png") as im:
            assert im.size == (1200, 800)
    # a fresh interpreter writing a report never imports pyplot (no global figure state, no GUI backend)
    code = (
        "import sys, pathlib, numpy as np\n"
        "from dualhuman_builder.fit.report import write_fit_report\n"
        f"p = pathlib.Path({str(tmp_path)!r})\n"
        "write_fit_report(p / 'x.html', take='x', fps=30.0, series={'R': {'a': np.ones(3)}}, sync={}, summary={},"
        " png_path=p / 'x.png')\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


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
    assert "time (min:s)" in c.comments
    ticks = [s for s in c.comments if re.fullmatch(r"\d+:\d\d", s)]
    assert ticks == ["0:00", "2:00", "4:00", "6:00", "8:00"]  # 0 to 9:59.97, every two minutes
