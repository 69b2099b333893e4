"""The fit stage's report: one self-contained HTML page (charts and tables) and an optional PNG summary.

matplotlib draws the charts: it is the field's plotting library, and it leaves less drawing code of our own.

* ``series`` maps a chart title to ``{line label: per-frame values (T,)}`` (any units, named in the
  title; each line may have its own T). Frame ``i`` is drawn at time ``i / fps`` seconds; ``NaN``
  means "no value" and breaks the line there (a value with ``NaN`` on both sides is drawn as a dot).
  Every chart shares one time axis, 0 s to the longest series' last frame, with the same width and
  margins, so charts line up vertically on the page; takes of 120 s or more label it ``m:ss``.
* A chart whose title's last word is ``valid`` (e.g. ``"Tracker valid"``) is drawn as dropout strips:
  one row per label, values >= 0.5 are valid (light green), anything else (0, ``NaN``) is a dropout
  drawn in red, at least one pixel column wide so a one-frame dropout stays visible.
* Long series are decimated before plotting (:func:`decimate_minmax`): each pixel column keeps the
  frames holding its smallest and largest value, so a one-frame spike in an 18,000-frame take is still
  drawn, and a chart's size does not grow with T; lines still break wherever the original has a ``NaN``.
* The HTML page holds each chart as inline SVG (vector, text drawn as glyph outlines, no scripts, no
  external URLs), a statistics table under each chart, the ``summary`` numbers and the ``sync`` report's
  tables; the PNG stacks the same charts in one ``png_size`` (width, height) pixel image.
* Figures are built on their own Agg canvas (:class:`matplotlib.figure.Figure`, never pyplot, never
  changing rcParams), so reports can be written from worker threads and no window ever opens.
"""

from __future__ import annotations

import html
import io
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MultipleLocator

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

# HTML chart layout, inches at _DPI pixels per inch. Every chart has the same width and side margins,
# so their time axes line up.
_DPI = 100
_FIG_W = 9.6
_LEFT = 1.5
_RIGHT = 0.2
_PLOT_PX = round((_FIG_W - _LEFT - _RIGHT) * _DPI)  # pixel columns of a plot: the decimation width
_TOP = 0.12
_LINE_H = 2.2
_AXIS_H = 0.5  # tick labels and the time label under a plot
_STRIP_ROW = 0.2
_LEGEND_ROW = 0.2
_CHAR_W = 0.075  # rough width of one 9 pt character, inches, to choose the legend's columns

_VALID_TITLE = re.compile(r"(^|[^a-z0-9])valid\s*$", re.IGNORECASE)
_TIME_STEPS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200)
_NO_SVG_METADATA = {"Creator": None, "Date": None, "Format": None, "Type": None}  # no dates, no URLs


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
# decimation


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
# charts (matplotlib)


def _truncate(s: str, n: int) -> str:
    return s if len(s) <= n else s[: max(n - 1, 1)] + "…"


def _plain(s: str) -> str:
    """``s`` for a matplotlib text, drawn literally (a ``$`` would otherwise start math text)."""
    return s.replace("$", r"\$")


def _figure(width_in: float, height_in: float) -> Figure:
    fig = Figure(figsize=(width_in, height_in), dpi=_DPI)
    FigureCanvasAgg(fig)  # this figure's own Agg canvas: no pyplot, no window
    return fig


def _time_axis(ax, t_span: float, target: int = 8) -> None:
    """Time axis of ``ax``: 0 to ``t_span`` seconds, about ``target`` round ticks, ``m:ss`` from 120 s."""
    step = next((s for s in _TIME_STEPS if s >= t_span / target), _TIME_STEPS[-1])
    minutes = t_span >= 120
    ax.set_xlim(0.0, t_span)
    ax.xaxis.set_major_locator(MultipleLocator(step))
    if minutes:
        ax.xaxis.set_major_formatter(FuncFormatter(lambda t, _: "{}:{:02d}".format(*divmod(round(t), 60))))
    else:
        ax.xaxis.set_major_formatter(FuncFormatter(lambda t, _: f"{t:g}"))
    ax.set_xlabel("time (min:s)" if minutes else "time (s)", fontsize=9)


def _no_data(ax) -> None:
    ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center", color="#888888")


def _draw_lines(ax, lines: dict[str, np.ndarray], fps: float, n_px: int, gid: str, lw: float) -> list:
    """One line per label, decimated to ``n_px`` columns; returns the legend handles."""
    handles = []
    for i, arr in enumerate(lines.values()):
        colour = PALETTE[i % len(PALETTE)]
        idx, starts = decimate_minmax(arr, n_px)
        x, y = idx / fps, arr[idx]
        (line,) = ax.plot(
            np.insert(x, starts[1:], np.nan),  # a NaN before each new piece breaks the line there
            np.insert(y, starts[1:], np.nan),
            color=colour,
            lw=lw,
            solid_joinstyle="round",
            gid=f"{gid}-line-{i + 1}",
        )
        handles.append(line)
        lone = starts[np.diff(np.append(starts, idx.size)) == 1]  # one-frame pieces: no segment to draw
        if lone.size:
            ax.plot(x[lone], y[lone], ls="none", marker="o", ms=2.2 * lw, color=colour, gid=f"{gid}-dots-{i + 1}")
    if not any(np.isfinite(a).any() for a in lines.values()):
        _no_data(ax)
    ax.grid(axis="y", color="#e4e4e4", lw=0.8)
    ax.set_axisbelow(True)
    return handles


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


def _draw_strips(
    ax, lines: dict[str, np.ndarray], fps: float, t_span: float, n_px: int, gid: str, label_chars: int, fontsize: float
) -> None:
    """One strip per label, top to bottom: light green where valid, red dropouts >= one pixel column."""
    s_per_px = t_span / n_px
    for r, arr in enumerate(lines.values()):
        valid = np.nan_to_num(arr, nan=0.0) >= 0.5
        ax.broken_barh([(0.0, arr.size / fps)], (r - 0.4, 0.8), facecolors=VALID_COLOUR, gid=f"{gid}-valid-{r + 1}")
        cols = _pixel_runs(_dropout_runs(valid), n_px / t_span / fps, n_px)
        if cols:
            ax.broken_barh(
                [(c0 * s_per_px, (c1 - c0) * s_per_px) for c0, c1 in cols],
                (r - 0.4, 0.8),
                facecolors=DROPOUT_COLOUR,
                gid=f"{gid}-dropouts-{r + 1}",
            )
    ax.set_ylim(max(len(lines), 1) - 0.5, -0.5)
    ax.set_yticks(range(len(lines)), [_plain(_truncate(label, label_chars)) for label in lines], fontsize=fontsize)
    ax.tick_params(axis="y", length=0)
    for side in ("left", "right", "top"):
        ax.spines[side].set_visible(False)
    if not lines:
        _no_data(ax)


def _chart_svg(k: int, title: str, lines: dict[str, np.ndarray], fps: float, t_span: float) -> str:
    """Chart ``k`` of the page as an ``<svg>`` element to inline in HTML (ids prefixed ``chart-{k}``)."""
    strips = is_validity_chart(title)
    labels = [_plain(_truncate(label, 40)) for label in lines]
    plot_w = _FIG_W - _LEFT - _RIGHT
    if strips:
        plot_h, legend_h, ncols = max(len(lines), 1) * _STRIP_ROW, 0.0, 1
    else:
        widest = max((len(s) for s in labels), default=0)
        ncols = max(1, min(len(labels), int(plot_w // (0.5 + _CHAR_W * widest))))
        plot_h, legend_h = _LINE_H, math.ceil(len(labels) / ncols) * _LEGEND_ROW + 0.05 if labels else 0.0
    height = _TOP + plot_h + _AXIS_H + legend_h
    fig = _figure(_FIG_W, height)
    ax = fig.add_axes((_LEFT / _FIG_W, 1 - (_TOP + plot_h) / height, plot_w / _FIG_W, plot_h / height))
    if strips:
        _draw_strips(ax, lines, fps, t_span, _PLOT_PX, f"chart-{k}", label_chars=22, fontsize=9)
    else:
        handles = _draw_lines(ax, lines, fps, _PLOT_PX, f"chart-{k}", lw=1.0)
        if handles:
            legend = fig.legend(
                handles,
                labels,
                loc="upper left",
                bbox_to_anchor=(_LEFT / _FIG_W, 1 - (_TOP + plot_h + _AXIS_H) / height),
                ncols=ncols,
                frameon=False,
                fontsize=9,
                borderaxespad=0,
                borderpad=0,
                columnspacing=1.5,
            )
            for h in legend.legend_handles:
                h.set_linewidth(3)
    ax.tick_params(labelsize=9)
    _time_axis(ax, t_span)
    buf = io.StringIO()
    fig.savefig(buf, format="svg", metadata=_NO_SVG_METADATA)
    svg = buf.getvalue()
    svg = svg[svg.index("<svg") :]  # drop the XML declaration and DOCTYPE: the SVG is inlined in HTML
    return svg.replace("<svg ", f'<svg role="img" aria-label="{_esc(title)}" ', 1)


# --------------------------------------------------------------------------------------------------
# chart statistics


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
    w, h = size
    fig = _figure(w / _DPI, h / _DPI)
    n_frames = max((a.size for lines in charts.values() for a in lines.values()), default=0)
    fig.text(
        10 / w,
        1 - 6 / h,
        _plain(f"Fit report: {take}   {n_frames} frames at {fps:g} fps ({n_frames / fps:.1f} s)"),
        va="top",
        fontsize=10,
        weight="bold",
    )
    if not charts:
        fig.text(0.5, 0.5, "no series", ha="center", va="center", color="#888888")
        fig.savefig(path, format="png", dpi=_DPI)
        return
    left, right, top, bottom = 110, 14, 44, 40  # pixels
    n = len(charts)
    avail = h - top - bottom
    gap = min(30.0, 0.4 * avail / n)  # room for each chart's title and legend
    ax_h = (avail - (n - 1) * gap) / n
    axes = fig.subplots(
        n,
        1,
        sharex=True,
        squeeze=False,
        gridspec_kw={
            "left": left / w,
            "right": 1 - right / w,
            "top": 1 - top / h,
            "bottom": bottom / h,
            "hspace": gap / ax_h,
        },
    )[:, 0]
    n_px = w - left - right
    renderer = fig.canvas.get_renderer()  # to measure titles and legends
    for k, (ax, (title, lines)) in enumerate(zip(axes, charts.items()), 1):
        heading = ax.set_title(_plain(title), loc="left", fontsize=9, pad=3)
        ax.tick_params(labelsize=8)
        if is_validity_chart(title):
            _draw_strips(ax, lines, fps, t_span, n_px, f"chart-{k}", label_chars=16, fontsize=8)
            if lines and ax_h / len(lines) < 8:
                ax.set_yticks([])
            continue
        handles = _draw_lines(ax, lines, fps, n_px, f"chart-{k}", lw=0.8)
        if not handles:
            continue
        style = {"fontsize": 8, "borderpad": 0.2, "handlelength": 1.2, "handletextpad": 0.4, "columnspacing": 1.0}
        labels = [_plain(_truncate(label, 24)) for label in lines]
        legend = ax.legend(
            handles, labels, loc="lower right", bbox_to_anchor=(1, 1), ncols=len(handles), frameon=False, **style
        )
        beside_title = n_px - heading.get_window_extent(renderer).width - 20  # pixels right of the title
        width = legend.get_window_extent(renderer).width
        if width > beside_title:  # no room on the title's line: wrap it into the plot's upper right corner
            legend.remove()
            ncols = max(1, int(len(handles) * min(1.0, 0.95 * n_px / width)))
            legend = ax.legend(handles, labels, loc="upper right", ncols=ncols, framealpha=0.85, **style)
        for h in legend.legend_handles:
            h.set_linewidth(2.5)
    _time_axis(axes[-1], t_span, target=max(2, n_px // 110))
    fig.savefig(path, format="png", dpi=_DPI)


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
    flags: Sequence[str] = (),
) -> Path:
    """Write the fit report for ``take`` to ``path_html`` (one self-contained HTML file) and return it.

    ``fps`` (Hz) maps frame ``i`` of every series to time ``i / fps`` seconds. ``series``: chart title
    -> ``{line label: per-frame values (T,)}`` (any units, named in the title; ``NaN`` = no value);
    titles whose last word is ``valid`` are drawn as dropout strips (values 0/1 or bool). ``sync`` is
    the sync stage's JSON report (``reference``, ``clocks``, ``lags``, ``mounts``, ``warnings``; any
    key may be missing, extra keys are listed as key/value rows). ``summary`` holds headline numbers
    (flat or nested dict) shown first. With ``png_path``, also writes a ``png_size`` (width, height)
    pixel PNG with the same charts stacked. ``flags``: sentences on what the data could not give (no
    trackers, segments no sensor measured), listed under "Data limits" before the summary. Parent
    folders are created; files are replaced atomically. Raises ValueError on malformed input, naming
    the offending chart / line / argument.
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
    if isinstance(flags, str) or any(not isinstance(f, str) for f in flags):
        raise ValueError(f"flags must be a list of sentences, got {flags!r}")
    if flags:
        items = "".join(f"<li>{_esc(f)}</li>" for f in flags)
        body.append(f'<h2 id="limits">Data limits</h2><ul class="warn">{items}</ul>')
    body.append("<h2>Summary</h2>" + _kv_table(summary))
    warnings = sync.get("warnings")
    if isinstance(warnings, (list, tuple)) and warnings:
        body.append(f'<p class="warn">{len(warnings)} sync warning(s): see <a href="#sync">Sync</a>.</p>')
    body.append("<h2>Charts</h2>")
    if not charts:
        body.append('<p class="muted">No series.</p>')
    for k, (title, lines) in enumerate(charts.items()):
        svg = _chart_svg(k + 1, title, lines, fps, t_span)
        stats = (_strip_stats(lines, fps) if is_validity_chart(title) else _line_stats(lines)) if lines else ""
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
