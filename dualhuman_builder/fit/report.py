"""The fit stage's report: one self-contained HTML page (inline SVG charts, tables) and a PNG summary.

No plotting library is needed: the charts are drawn as SVG paths by hand, and the PNG with Pillow.

* ``series`` maps a chart title to ``{line label: per-frame values (T,)}``; frame ``i`` is drawn at
  time ``i / fps`` seconds, ``NaN`` means "no value" and breaks the line there. Every chart shares one
  time axis (0 to the longest series' last frame) so charts line up vertically on the page.
* A chart whose title's last word is ``valid`` (e.g. ``"Tracker valid"``) is drawn as dropout strips:
  one row per label, values >= 0.5 are valid, anything else (0, ``NaN``) is a dropout drawn in red.
* Long series are decimated for drawing: each pixel column keeps the frames holding its smallest and
  largest value, so a one-frame spike in an 18,000-frame take is still drawn; a segment joins two
  kept frames only when no ``NaN`` lies between them in the original series.
"""

from __future__ import annotations

import html
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_fit_report", "decimate_minmax", "is_validity_chart"]

#: Line colours, cycled per chart (colour-blind-friendly "tab10" hues).
PALETTE = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#d62728",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#7f7f7f",
    "#bcbd22",
    "#17becf",
)
DROPOUT_COLOUR = "#d62728"
VALID_COLOUR = "#cfe8cf"

# SVG layout, pixels. The left margin is shared by line charts and strips so time axes align.
_SVG_W = 960
_LEFT = 150
_RIGHT = 20
_PLOT_W = _SVG_W - _LEFT - _RIGHT
_TOP = 12
_LINE_PLOT_H = 220
_AXIS_H = 38
_STRIP_ROW = 14
_STRIP_GAP = 5
_LEGEND_ROW = 18
_CHAR_W = 6.6  # rough width of one 11 px sans-serif character, for legend layout and truncation

_VALID_TITLE = re.compile(r"(^|[^a-z0-9])valid\s*$", re.IGNORECASE)
_TIME_STEPS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200)


def is_validity_chart(title: str) -> bool:
    """True when ``title``'s last word is ``valid`` (case-insensitive): the chart is drawn as strips."""
    return bool(_VALID_TITLE.search(title))


# --------------------------------------------------------------------------------------------------
# input checks


def _check_series(series: Any) -> dict[str, dict[str, np.ndarray]]:
    if not isinstance(series, Mapping):
        raise ValueError(f"series must be a dict {{chart title: {{label: array (T,)}}}}, got {type(series).__name__}")
    out: dict[str, dict[str, np.ndarray]] = {}
    for title, lines in series.items():
        if not isinstance(title, str):
            raise ValueError(f"series: chart title {title!r} must be a string")
        if not isinstance(lines, Mapping):
            raise ValueError(f"series[{title!r}] must be a dict {{label: array (T,)}}, got {type(lines).__name__}")
        checked: dict[str, np.ndarray] = {}
        for label, values in lines.items():
            where = f"series[{title!r}][{label!r}]"
            if not isinstance(label, str):
                raise ValueError(f"{where}: line label must be a string")
            try:
                arr = np.asarray(values, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where}: values must be numbers ({exc})") from None
            if arr.ndim != 1:
                raise ValueError(f"{where}: expected a 1-D per-frame array (T,), got shape {arr.shape}")
            if arr.size == 0:
                raise ValueError(f"{where}: empty array (T = 0); leave the line out instead")
            if np.isinf(arr).any():
                raise ValueError(
                    f"{where}: {int(np.isinf(arr).sum())} infinite value(s), first at frame "
                    f"{int(np.flatnonzero(np.isinf(arr))[0])}; use NaN for frames without a value"
                )
            if is_validity_chart(title):
                fin = arr[np.isfinite(arr)]
                if fin.size and (fin.min() < 0.0 or fin.max() > 1.0):
                    raise ValueError(
                        f"{where}: a validity chart takes 0/1 (or bool) values, got range "
                        f"[{fin.min():g}, {fin.max():g}]"
                    )
            checked[label] = arr
        out[title] = checked
    return out


# --------------------------------------------------------------------------------------------------
# decimation and axes


def decimate_minmax(values: np.ndarray, n_buckets: int) -> tuple[np.ndarray, np.ndarray]:
    """Frames to draw for ``values`` (T,) on ``n_buckets`` pixel columns, and where lines break.

    If ``T <= 2 * n_buckets`` every finite frame is kept; otherwise frames are split into
    ``n_buckets`` equal runs and each keeps its smallest and largest finite value (one frame if they
    coincide), so spikes survive. Returns ``(idx, starts)``: ``idx`` (K,) int64 increasing frame
    indices, and ``starts`` (R,) positions in ``idx`` where a new line piece begins — at the first
    kept frame and wherever a ``NaN`` lies between two consecutive kept frames.
    """
    y = np.asarray(values, dtype=np.float64)
    if y.ndim != 1:
        raise ValueError(f"decimate_minmax: values must be 1-D (T,), got shape {y.shape}")
    if n_buckets < 1:
        raise ValueError(f"decimate_minmax: n_buckets must be >= 1, got {n_buckets}")
    t = y.size
    finite = np.isfinite(y)
    if t <= 2 * n_buckets:
        idx = np.flatnonzero(finite)
    else:
        lo_v = np.where(finite, y, np.inf)
        hi_v = np.where(finite, y, -np.inf)
        edges = (np.arange(n_buckets + 1, dtype=np.int64) * t) // n_buckets
        count = np.concatenate([[0], np.cumsum(finite)])
        keep = []
        for a, b in zip(edges[:-1], edges[1:]):
            if count[b] - count[a] == 0:
                continue
            keep.append(a + int(np.argmin(lo_v[a:b])))
            keep.append(a + int(np.argmax(hi_v[a:b])))
        idx = np.unique(np.asarray(keep, dtype=np.int64))
    idx = idx.astype(np.int64)
    if idx.size == 0:
        return idx, np.zeros(0, dtype=np.int64)
    nan_before = np.concatenate([[0], np.cumsum(~finite)])  # nan_before[i] = NaNs in y[:i]
    gap = nan_before[idx[1:]] - nan_before[idx[:-1] + 1] > 0
    starts = np.concatenate([[0], np.flatnonzero(gap) + 1]).astype(np.int64)
    return idx, starts


def _nice_step(span: float, target: int) -> float:
    raw = span / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * mag >= raw * 0.8:  # up to ~1.25 x target ticks, for rounder steps
            return m * mag
    return 10.0 * mag


def _value_axis(lo: float, hi: float, target: int = 5) -> tuple[float, float, list[float], int]:
    """Axis ``(lo, hi, ticks, decimals)`` covering [lo, hi] with round tick values."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if hi - lo <= 1e-12 * max(1.0, abs(hi), abs(lo)):
        pad = abs(hi) * 0.1 if hi != 0 else 1.0
        lo, hi = lo - pad, hi + pad
    step = _nice_step(hi - lo, target)
    k0 = math.floor(lo / step + 1e-9)
    k1 = math.ceil(hi / step - 1e-9)
    ticks = [k * step for k in range(k0, k1 + 1)]
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    if step * 10**decimals % 1 > 1e-6:  # steps like 2.5 need one more decimal
        decimals += 1
    return k0 * step, k1 * step, ticks, decimals


def _time_axis(t_max: float, target: int = 8) -> tuple[list[float], bool]:
    """Tick times (s) within [0, t_max] and whether to label them as m:ss."""
    raw = t_max / target
    step = next((s for s in _TIME_STEPS if s >= raw), _TIME_STEPS[-1])
    n = int(math.floor(t_max / step + 1e-9))
    return [k * step for k in range(n + 1)], t_max >= 120


def _fmt_tick(v: float, decimals: int) -> str:
    if abs(v) >= 1e6:
        return f"{v:.3g}"
    s = f"{v:.{decimals}f}"
    return "0" if s.lstrip("-").strip("0.") == "" else s


def _fmt_time(t: float, minutes: bool) -> str:
    if minutes:
        m, s = divmod(int(round(t)), 60)
        return f"{m}:{s:02d}"
    return f"{t:g}"


# --------------------------------------------------------------------------------------------------
# value formatting for tables


def _fmt_num(v: Any) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return f"{int(v):,}" if abs(int(v)) >= 10000 else str(int(v))
    v = float(v)
    if math.isnan(v):
        return "–"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    a = abs(v)
    if a == 0:
        return "0"
    if a >= 1e6 or a < 1e-3:
        return f"{v:.3e}"
    if a >= 100:
        return f"{v:.1f}"
    if a >= 1:
        return f"{v:.2f}"
    return f"{v:.3f}"


def _esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating, np.bool_)) and not isinstance(v, str)


def _fmt_value(v: Any) -> str:
    """HTML for one table cell: numbers formatted, vectors bracketed, dicts as nested rows."""
    if v is None:
        return "–"
    if _is_num(v):
        return _esc(_fmt_num(v))
    if isinstance(v, str):
        return _esc(v)
    if isinstance(v, Mapping):
        if not v:
            return "–"
        rows = "".join(f"<tr><th>{_esc(k)}</th><td>{_fmt_value(x)}</td></tr>" for k, x in v.items())
        return f'<table class="inner">{rows}</table>'
    if isinstance(v, (list, tuple, np.ndarray)):
        items = list(np.asarray(v).ravel()) if isinstance(v, np.ndarray) else list(v)
        if items and all(_is_num(x) for x in items):
            shown = ", ".join(_fmt_num(x) for x in items[:12])
            more = f", … ({len(items)} values)" if len(items) > 12 else ""
            return _esc(f"[{shown}{more}]")
        return "<br>".join(_fmt_value(x) for x in items) or "–"
    return _esc(repr(v))


def _kv_rows(d: Mapping, depth: int = 0) -> list[str]:
    rows = []
    for k, v in d.items():
        pad = f' style="padding-left:{0.4 + 1.2 * depth:.1f}em"'
        if isinstance(v, Mapping) and v:
            rows.append(f'<tr class="group"><th colspan="2"{pad}>{_esc(k)}</th></tr>')
            rows.extend(_kv_rows(v, depth + 1))
        else:
            rows.append(f"<tr><th{pad}>{_esc(k)}</th><td>{_fmt_value(v)}</td></tr>")
    return rows


def _kv_table(d: Mapping, css: str = "kv") -> str:
    if not d:
        return '<p class="muted">(none)</p>'
    return f'<table class="{css}">' + "".join(_kv_rows(d)) + "</table>"


def _grid_table(head: list[str], rows: list[list[str]]) -> str:
    """Table from already-escaped cell HTML."""
    h = "".join(f"<th>{_esc(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="grid"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


# --------------------------------------------------------------------------------------------------
# SVG charts


def _truncate(s: str, n: int) -> str:
    return s if len(s) <= n else s[: max(n - 1, 1)] + "…"


def _time_axis_svg(y0: float, t_span: float) -> list[str]:
    ticks, minutes = _time_axis(t_span)
    out = [f'<line x1="{_LEFT}" y1="{y0:.1f}" x2="{_LEFT + _PLOT_W}" y2="{y0:.1f}" stroke="#444"/>']
    for t in ticks:
        x = _LEFT + t / t_span * _PLOT_W
        out.append(f'<line x1="{x:.1f}" y1="{y0:.1f}" x2="{x:.1f}" y2="{y0 + 4:.1f}" stroke="#444"/>')
        out.append(f'<text x="{x:.1f}" y="{y0 + 15:.1f}" text-anchor="middle">{_fmt_time(t, minutes)}</text>')
    label = "time (min:s)" if minutes else "time (s)"
    out.append(f'<text x="{_LEFT + _PLOT_W / 2:.1f}" y="{y0 + 31:.1f}" text-anchor="middle">{label}</text>')
    return out


def _svg_open(title: str, height: float) -> str:
    return (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_SVG_W}" height="{height:.0f}" '
        f'viewBox="0 0 {_SVG_W} {height:.0f}" role="img" aria-label="{_esc(title)}" '
        'font-family="sans-serif" font-size="11">'
    )


def _line_chart_svg(title: str, lines: dict[str, np.ndarray], fps: float, t_span: float) -> str:
    finite = [a[np.isfinite(a)] for a in lines.values()]
    finite = [f for f in finite if f.size]
    lo = min((float(f.min()) for f in finite), default=math.nan)
    hi = max((float(f.max()) for f in finite), default=math.nan)
    y_lo, y_hi, y_ticks, dec = _value_axis(lo, hi)
    top, h = _TOP, _LINE_PLOT_H

    def ypx(v):
        return top + (y_hi - v) / (y_hi - y_lo) * h

    # legend layout below the axis
    legend, x, row = [], 0.0, 0
    for i, label in enumerate(lines):
        shown = _truncate(label, 40)
        w = 34 + _CHAR_W * len(shown)
        if x > 0 and x + w > _PLOT_W:
            x, row = 0.0, row + 1
        legend.append((i, label, shown, _LEFT + x, top + h + _AXIS_H + 6 + row * _LEGEND_ROW))
        x += w
    height = top + h + _AXIS_H + 8 + (row + 1) * _LEGEND_ROW if lines else top + h + _AXIS_H + 8

    out = [_svg_open(title, height)]
    out.append(f'<rect class="frame" x="{_LEFT}" y="{top}" width="{_PLOT_W}" height="{h}" fill="#fff" stroke="#bbb"/>')
    for v in y_ticks:
        y = ypx(v)
        out.append(f'<line x1="{_LEFT}" y1="{y:.1f}" x2="{_LEFT + _PLOT_W}" y2="{y:.1f}" stroke="#e4e4e4"/>')
        out.append(f'<text x="{_LEFT - 6}" y="{y + 4:.1f}" text-anchor="end">{_fmt_tick(v, dec)}</text>')
    out.append(f'<line x1="{_LEFT}" y1="{top}" x2="{_LEFT}" y2="{top + h}" stroke="#444"/>')
    out.extend(_time_axis_svg(top + h, t_span))
    if not lines:
        out.append(
            f'<text x="{_LEFT + _PLOT_W / 2:.1f}" y="{top + h / 2:.1f}" text-anchor="middle" fill="#888">no data</text>'
        )
    for i, (label, arr) in enumerate(lines.items()):
        colour = PALETTE[i % len(PALETTE)]
        idx, starts = decimate_minmax(arr, _PLOT_W)
        if idx.size == 0:
            continue
        xs = _LEFT + idx / fps / t_span * _PLOT_W
        ys = ypx(arr[idx])
        pts = [f"{a:.1f},{b:.1f}" for a, b in zip(xs, ys)]
        bounds = list(starts) + [idx.size]
        pieces = []
        for s, e in zip(bounds[:-1], bounds[1:]):
            # a lone point becomes a zero-length segment: round caps draw it as a dot
            pieces.append(f"M{pts[s]}h0" if e - s == 1 else f"M{pts[s]}L" + " ".join(pts[s + 1 : e]))
        out.append(
            f'<path class="series" data-label="{_esc(label)}" d="{"".join(pieces)}" fill="none" '
            f'stroke="{colour}" stroke-width="1.3" stroke-linejoin="round" stroke-linecap="round"/>'
        )
    for i, label, shown, lx, ly in legend:
        colour = PALETTE[i % len(PALETTE)]
        tip = f"<title>{_esc(label)}</title>" if shown != label else ""
        out.append(
            f'<line x1="{lx:.1f}" y1="{ly:.1f}" x2="{lx + 22:.1f}" y2="{ly:.1f}" stroke="{colour}" stroke-width="3"/>'
        )
        out.append(f'<text x="{lx + 27:.1f}" y="{ly + 4:.1f}">{tip}{_esc(shown)}</text>')
    out.append("</svg>")
    return "".join(out)


def _dropout_runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """Half-open frame ranges [a, b) where ``valid`` is False."""
    bad = np.concatenate([[False], ~valid, [False]]).astype(np.int8)
    d = np.diff(bad)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _pixel_runs(runs: list[tuple[int, int]], px_per_frame: float, width: int) -> list[tuple[int, int]]:
    """Merge frame runs into pixel-column runs [c0, c1) within [0, width), each >= one column wide."""
    merged: list[tuple[int, int]] = []
    for a, b in runs:
        c0 = min(int(math.floor(a * px_per_frame)), width - 1)
        c1 = min(max(int(math.ceil(b * px_per_frame)), c0 + 1), width)
        if merged and c0 <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], c1))
        else:
            merged.append((c0, c1))
    return merged


def _strip_chart_svg(title: str, lines: dict[str, np.ndarray], fps: float, t_span: float) -> str:
    n = max(len(lines), 1)
    top = _TOP
    rows_h = n * (_STRIP_ROW + _STRIP_GAP)
    height = top + rows_h + _AXIS_H + 4
    out = [_svg_open(title, height)]
    px_per_s = _PLOT_W / t_span
    if not lines:
        out.append(
            f'<text x="{_LEFT + _PLOT_W / 2:.1f}" y="{top + 12}" text-anchor="middle" fill="#888">no data</text>'
        )
    for r, (label, arr) in enumerate(lines.items()):
        y = top + r * (_STRIP_ROW + _STRIP_GAP)
        valid = np.nan_to_num(arr, nan=0.0) >= 0.5
        w = min(arr.size / fps * px_per_s, _PLOT_W)
        shown = _truncate(label, 22)
        tip = f"<title>{_esc(label)}</title>" if shown != label else ""
        out.append(f'<text x="{_LEFT - 6}" y="{y + _STRIP_ROW - 3}" text-anchor="end">{tip}{_esc(shown)}</text>')
        out.append(f'<rect x="{_LEFT}" y="{y}" width="{w:.1f}" height="{_STRIP_ROW}" fill="{VALID_COLOUR}"/>')
        for c0, c1 in _pixel_runs(_dropout_runs(valid), px_per_s / fps, _PLOT_W):
            out.append(
                f'<rect class="dropout" x="{_LEFT + c0}" y="{y}" width="{c1 - c0}" '
                f'height="{_STRIP_ROW}" fill="{DROPOUT_COLOUR}"/>'
            )
    out.extend(_time_axis_svg(top + rows_h, t_span))
    out.append("</svg>")
    return "".join(out)


def _swatch(i: int) -> str:
    return f'<span class="sw" style="background:{PALETTE[i % len(PALETTE)]}"></span>'


def _line_stats(lines: dict[str, np.ndarray]) -> str:
    rows = []
    for i, (label, arr) in enumerate(lines.items()):
        f = arr[np.isfinite(arr)]
        if f.size:
            stats = [np.mean(f), np.median(f), np.percentile(f, 95), np.max(f)]
            nums = [_esc(_fmt_num(float(s))) for s in stats]
        else:
            nums = ["–"] * 4
        rows.append([_swatch(i) + _esc(label), _esc(f"{f.size} / {arr.size}"), *nums])
    return _grid_table(["line", "frames with value", "mean", "median", "p95", "max"], rows)


def _strip_stats(lines: dict[str, np.ndarray], fps: float) -> str:
    rows = []
    for label, arr in lines.items():
        valid = np.nan_to_num(arr, nan=0.0) >= 0.5
        runs = _dropout_runs(valid)
        longest = max((b - a for a, b in runs), default=0) / fps
        rows.append(
            [
                _esc(label),
                _esc(f"{100.0 * valid.mean():.1f} %"),
                str(len(runs)),
                _esc(f"{longest:.2f} s"),
                str(arr.size),
            ]
        )
    return _grid_table(["label", "valid", "dropouts", "longest dropout", "frames"], rows)


# --------------------------------------------------------------------------------------------------
# sync tables


def _extra(d: Mapping, known: tuple[str, ...]) -> str:
    rest = {k: v for k, v in d.items() if k not in known}
    return _fmt_value(rest) if rest else ""


def _sync_html(sync: Mapping) -> str:
    if not sync:
        return '<p class="muted">No sync report.</p>'
    parts = []
    used = {"reference", "clocks", "lags", "mounts", "warnings"}
    if "reference" in sync:
        parts.append(f"<p>Reference clock: <b>{_fmt_value(sync['reference'])}</b></p>")

    clocks = sync.get("clocks")
    if isinstance(clocks, Mapping) and clocks:
        known = ("offset_s", "drift_ppm", "lag_correction_ms", "host_fit")
        rows = []
        for name, c in clocks.items():
            c = c if isinstance(c, Mapping) else {"value": c}
            rows.append([_esc(name), *(_fmt_value(c.get(k)) for k in known), _extra(c, known)])
        parts.append(
            "<h3>Clocks</h3>"
            + _grid_table(["clock", "offset (s)", "drift (ppm)", "lag correction (ms)", "host fit", "other"], rows)
        )
    elif clocks is not None:
        used.discard("clocks")

    lags = sync.get("lags")
    if isinstance(lags, Mapping) and lags:
        known = ("lag_ms", "std_ms", "peak", "error")
        rows = []
        for name, lag in lags.items():
            lag = lag if isinstance(lag, Mapping) else {"value": lag}
            err = lag.get("error")
            err_html = f'<span class="err">{_fmt_value(err)}</span>' if err is not None else ""
            rows.append([_esc(name), *(_fmt_value(lag.get(k)) for k in known[:3]), err_html, _extra(lag, known)])
        parts.append("<h3>Lags</h3>" + _grid_table(["stream", "lag (ms)", "std (ms)", "peak", "error", "other"], rows))
    elif lags is not None:
        used.discard("lags")

    mounts = sync.get("mounts")
    if isinstance(mounts, Mapping) and mounts:
        known = ("rotation_deg", "translation_mm", "rotation_std_deg", "translation_std_mm")
        rows = []
        for actor, by_serial in mounts.items():
            if not isinstance(by_serial, Mapping):
                rows.append([_esc(actor), "", "", "", "", "", _fmt_value(by_serial)])
                continue
            for serial, m in by_serial.items():
                m = m if isinstance(m, Mapping) else {"value": m}
                rows.append([_esc(actor), _esc(serial), *(_fmt_value(m.get(k)) for k in known), _extra(m, known)])
        parts.append(
            "<h3>Tracker mounts</h3>"
            + _grid_table(
                [
                    "actor",
                    "tracker",
                    "rotation (deg)",
                    "translation (mm)",
                    "rotation std (deg)",
                    "translation std (mm)",
                    "other",
                ],
                rows,
            )
        )
    elif mounts is not None:
        used.discard("mounts")

    warnings = sync.get("warnings")
    if isinstance(warnings, (list, tuple)):
        if warnings:
            items = "".join(f"<li>{_fmt_value(w)}</li>" for w in warnings)
            parts.append(f'<h3>Warnings</h3><ul class="warn">{items}</ul>')
        else:
            parts.append('<h3>Warnings</h3><p class="muted">(none)</p>')
    elif warnings is not None:
        used.discard("warnings")

    rest = {k: v for k, v in sync.items() if k not in used}
    if rest:
        parts.append("<h3>Other</h3>" + _kv_table(rest))
    return "".join(parts)


# --------------------------------------------------------------------------------------------------
# PNG summary


def _png(
    path: Path, take: str, fps: float, charts: dict[str, dict[str, np.ndarray]], t_span: float, size: tuple[int, int]
) -> None:
    from PIL import Image, ImageDraw, ImageFont

    w, h = size
    img = Image.new("RGB", (w, h), "white")
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default()

    def text(xy, s, fill="black", anchor="la"):
        try:
            draw.text(xy, s, fill=fill, font=font, anchor=anchor)
        except (UnicodeEncodeError, ValueError):  # the bitmap fallback font is Latin-1 only, no anchors
            draw.text(xy, s.encode("latin-1", "replace").decode("latin-1"), fill=fill, font=font)

    n_frames = max((a.size for lines in charts.values() for a in lines.values()), default=0)
    text((10, 8), f"Fit report: {take}   {n_frames} frames at {fps:g} fps ({n_frames / fps:.1f} s)")
    header, left, right, gap = 28, 110, 14, 34
    plot_w = w - left - right
    if not charts:
        text((10, 40), "no series", fill="#888")
        img.save(path, format="PNG")
        return
    slot = (h - header) / len(charts)
    ticks, minutes = _time_axis(t_span, target=max(2, plot_w // 110))
    for c, (title, lines) in enumerate(charts.items()):
        y0 = header + c * slot
        ph = max(slot - gap, 4.0)
        top, bot = y0 + 16, y0 + 16 + ph
        text((left, y0 + 2), title)
        lx = left + draw.textlength(title, font=font) + 16
        strips = is_validity_chart(title)
        if not strips:
            for i, label in enumerate(lines):
                colour = PALETTE[i % len(PALETTE)]
                draw.line([(lx, y0 + 9), (lx + 14, y0 + 9)], fill=colour, width=3)
                text((lx + 18, y0 + 2), label, fill=colour)
                lx += 30 + draw.textlength(label, font=font)
        draw.rectangle([left, top, left + plot_w, bot], outline="#bbbbbb")
        for t in ticks:
            x = left + t / t_span * plot_w
            draw.line([(x, bot), (x, bot + 3)], fill="#444444")
            text((x, bot + 4), _fmt_time(t, minutes), fill="#444444", anchor="ma")
        if not lines:
            text((left + plot_w / 2, (top + bot) / 2), "no data", fill="#888888", anchor="mm")
            continue
        if strips:
            rh = ph / len(lines)
            for r, (label, arr) in enumerate(lines.items()):
                ry0, ry1 = top + r * rh + 1, top + (r + 1) * rh - 1
                valid = np.nan_to_num(arr, nan=0.0) >= 0.5
                xw = min(arr.size / fps / t_span * plot_w, plot_w)
                draw.rectangle([left, ry0, left + xw, max(ry1, ry0)], fill=VALID_COLOUR)
                for c0, c1 in _pixel_runs(_dropout_runs(valid), plot_w / t_span / fps, plot_w):
                    draw.rectangle([left + c0, ry0, left + c1 - 1, max(ry1, ry0)], fill=DROPOUT_COLOUR)
                if rh >= 8:
                    text((left - 6, (ry0 + ry1) / 2), _truncate(label, 16), anchor="rm")
            continue
        finite = [a[np.isfinite(a)] for a in lines.values()]
        finite = [f for f in finite if f.size]
        y_lo, y_hi, y_ticks, dec = _value_axis(
            min((float(f.min()) for f in finite), default=math.nan),
            max((float(f.max()) for f in finite), default=math.nan),
            target=max(1, int(ph // 30)),
        )
        for v in y_ticks:
            y = bot - (v - y_lo) / (y_hi - y_lo) * ph
            draw.line([(left, y), (left + plot_w, y)], fill="#e8e8e8")
            text((left - 6, y), _fmt_tick(v, dec), fill="#444444", anchor="rm")
        for i, arr in enumerate(lines.values()):
            colour = PALETTE[i % len(PALETTE)]
            idx, starts = decimate_minmax(arr, plot_w)
            if idx.size == 0:
                continue
            xs = left + idx / fps / t_span * plot_w
            ys = bot - (arr[idx] - y_lo) / (y_hi - y_lo) * ph
            bounds = list(starts) + [idx.size]
            for s, e in zip(bounds[:-1], bounds[1:]):
                if e - s == 1:
                    draw.point((float(xs[s]), float(ys[s])), fill=colour)
                else:
                    draw.line(list(zip(xs[s:e].tolist(), ys[s:e].tolist())), fill=colour, width=1)
    img.save(path, format="PNG")


# --------------------------------------------------------------------------------------------------
# the page

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:24px auto;max-width:1000px;color:#222}
h1{font-size:1.5em;margin-bottom:.2em}h2{margin-top:1.6em;border-bottom:1px solid #ddd}h3{margin-bottom:.3em}
.muted{color:#888}.meta{color:#555;margin-top:0}
table{border-collapse:collapse;font-size:13px;margin:.4em 0}
th,td{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}
td{font-variant-numeric:tabular-nums}
thead th{background:#f3f3f3}tr.group th{background:#f7f7f7}
table.kv th{font-weight:normal;color:#444}
table.inner{margin:0;font-size:12px}table.inner th,table.inner td{border:none;padding:0 6px 0 0}
.sw{display:inline-block;width:12px;height:12px;margin-right:6px;vertical-align:-1px;border-radius:2px}
.warn{background:#fff6d6;border:1px solid #e8d48a;padding:.5em 1.8em}.err{color:#b00}
figure{margin:1em 0 1.6em 0}figcaption{font-weight:600;margin-bottom:4px}
svg{display:block;max-width:100%;height:auto}
"""


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_fit_report(
    path_html: Path,
    *,
    take: str,
    fps: float,
    series: dict[str, dict[str, np.ndarray]],
    sync: dict,
    summary: dict,
    png_path: Path | None = None,
    png_size: tuple[int, int] = (1200, 800),
) -> Path:
    """Write the fit report for ``take`` to ``path_html`` (one self-contained HTML file) and return it.

    ``fps`` (Hz) maps frame ``i`` of every series to time ``i / fps`` seconds. ``series``: chart title
    -> ``{line label: per-frame values (T,)}`` (any units, named in the title; ``NaN`` = no value);
    titles whose last word is ``valid`` are drawn as dropout strips (values 0/1 or bool). ``sync`` is
    the sync stage's JSON report (``reference``, ``clocks``, ``lags``, ``mounts``, ``warnings``; any
    key may be missing, extra keys are listed as key/value rows). ``summary`` holds headline numbers
    (flat or nested dict) shown first. With ``png_path``, also writes a ``png_size`` (width, height)
    pixel PNG with the same charts stacked. Parent folders are created; files are replaced
    atomically. Raises ValueError on malformed input, naming the offending chart / line / argument.
    """
    if not isinstance(take, str) or not take:
        raise ValueError(f"take must be a non-empty string, got {take!r}")
    if (
        isinstance(fps, bool)
        or not isinstance(fps, (int, float, np.integer, np.floating))
        or not math.isfinite(float(fps))
        or float(fps) <= 0
    ):
        raise ValueError(f"fps must be a finite number > 0 (frames per second), got {fps!r}")
    fps = float(fps)
    if sync is None:
        sync = {}
    if not isinstance(sync, Mapping):
        raise ValueError(f"sync must be a dict (the sync stage's JSON report), got {type(sync).__name__}")
    if not isinstance(summary, Mapping):
        raise ValueError(f"summary must be a dict of headline numbers, got {type(summary).__name__}")
    charts = _check_series(series)
    path_html = Path(path_html)
    if png_path is not None:
        png_path = Path(png_path)
        if png_path.resolve() == path_html.resolve():
            raise ValueError(f"png_path and path_html are the same file: {png_path}")
        if (
            len(png_size) != 2
            or any(isinstance(s, bool) or not isinstance(s, (int, np.integer)) for s in png_size)
            or png_size[0] < 320
            or png_size[1] < 200
        ):
            raise ValueError(f"png_size must be (width, height) integers of at least (320, 200) px, got {png_size!r}")

    n_frames = max((a.size for lines in charts.values() for a in lines.values()), default=0)
    t_span = max((n_frames - 1) / fps, 1.0 / fps)

    body = [f"<h1>Fit report: {_esc(take)}</h1>"]
    body.append(
        f'<p class="meta">{n_frames} frames at {_esc(f"{fps:g}")} fps ({n_frames / fps:.1f} s), '
        f"{len(charts)} chart(s)</p>"
    )
    body.append("<h2>Summary</h2>" + _kv_table(summary))
    warnings = sync.get("warnings")
    if isinstance(warnings, (list, tuple)) and warnings:
        body.append(f'<p class="warn">{len(warnings)} sync warning(s): see <a href="#sync">Sync</a>.</p>')
    body.append("<h2>Charts</h2>")
    if not charts:
        body.append('<p class="muted">No series.</p>')
    for k, (title, lines) in enumerate(charts.items()):
        strips = is_validity_chart(title)
        svg = (_strip_chart_svg if strips else _line_chart_svg)(title, lines, fps, t_span)
        stats = (_strip_stats(lines, fps) if strips else _line_stats(lines)) if lines else ""
        body.append(f'<figure id="chart-{k + 1}"><figcaption>{_esc(title)}</figcaption>{svg}{stats}</figure>')
    body.append('<h2 id="sync">Sync</h2>' + _sync_html(sync))

    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>Fit report: {_esc(take)}</title><style>{_CSS}</style></head>\n<body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )
    path_html.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path_html, page.encode("utf-8"))
    if png_path is not None:
        png_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = png_path.with_name(f".{png_path.name}.{os.getpid()}.tmp")
        try:
            _png(tmp, take, fps, charts, t_span, (int(png_size[0]), int(png_size[1])))
            os.replace(tmp, png_path)
        finally:
            if tmp.exists():
                tmp.unlink()
    return path_html
