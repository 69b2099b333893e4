"""The review page of a workspace: one static HTML file to triage its takes in a browser.

One row per take: its stages' states, its quality flags (:mod:`.gates`) and key figures, and
relative links to its fit report (``report.html``), contact sheet (the ``sheet`` stage's
``contact_sheet.png``), renders and sync report where they exist. Everything is in the one file
(inline CSS and JavaScript, no server, nothing fetched from the network), so the page opens from
disk, and from a copy of the workspace folder. The table sorts by any column (click its header)
and filters by verdict, by gate and by text. Read-only on the workspace: it reads the catalog only.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path
from typing import Any
from urllib.parse import quote

from dualhuman_builder.errors import WorkspaceError

#: The page's default file name, in the workspace folder.
REVIEW_NAME = "review.html"

_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.2em;color:#222}
h1{font-size:1.3em;margin:0 0 .3em}
.summary span{margin-right:1.2em}
.controls{margin:.8em 0}.controls>*{margin-right:.8em}
table{border-collapse:collapse;width:100%}
th,td{border:1px solid #ccc;padding:.25em .4em;vertical-align:top;text-align:left}
th{background:#f0f0f0;cursor:pointer;user-select:none;position:sticky;top:0}
th.sorted-asc::after{content:" \\25B2"}th.sorted-desc::after{content:" \\25BC"}
td.st{text-align:center;font-family:monospace}
.done{color:#070}.stale{color:#a60}.failed,.interrupted{color:#c00}.running{color:#06c}.none{color:#aaa}
tr.flagged td.verdict{background:#fde0dc}tr.clean td.verdict{background:#e3f5e1}tr.unchecked td.verdict{background:#eee}
ul.flags{margin:0;padding-left:1.1em}.outdated{color:#a60}
td.num{text-align:right;font-variant-numeric:tabular-nums}
"""

_JS = """
(function(){
  var table=document.getElementById('takes'), body=table.tBodies[0];
  var verdict=document.getElementById('verdict'), gate=document.getElementById('gate'), text=document.getElementById('text');
  function apply(){
    var v=verdict.value, g=gate.value, q=text.value.toLowerCase(), shown=0;
    Array.prototype.forEach.call(body.rows,function(r){
      var ok=(v==='all'||r.dataset.verdict===v)&&(g===''||(' '+r.dataset.gates+' ').indexOf(' '+g+' ')>=0)
             &&(q===''||r.textContent.toLowerCase().indexOf(q)>=0);
      r.style.display=ok?'':'none'; if(ok)shown++;
    });
    document.getElementById('shown').textContent=shown;
  }
  [verdict,gate].forEach(function(e){e.addEventListener('change',apply)}); text.addEventListener('input',apply);
  Array.prototype.forEach.call(table.tHead.rows[0].cells,function(th,i){
    th.addEventListener('click',function(){
      var asc=!th.classList.contains('sorted-asc');
      Array.prototype.forEach.call(table.tHead.rows[0].cells,function(c){c.classList.remove('sorted-asc','sorted-desc')});
      th.classList.add(asc?'sorted-asc':'sorted-desc');
      var rows=Array.prototype.slice.call(body.rows);
      rows.sort(function(a,b){
        var x=a.cells[i].dataset.sort, y=b.cells[i].dataset.sort;
        if(x===undefined)x=a.cells[i].textContent; if(y===undefined)y=b.cells[i].textContent;
        var nx=Number(x), ny=Number(y), c;
        if(x!==''&&y!==''&&!isNaN(nx)&&!isNaN(ny))c=nx-ny; else c=x.localeCompare(y);
        return asc?c:-c;
      });
      rows.forEach(function(r){body.appendChild(r)});
    });
  });
  apply();
})();
"""

#: The mark of each stage state in the table (the same as ``dualhuman status``).
MARKS = {"done": "\u2713", "stale": "~", "failed": "\u2717", "running": "\u25b6", "interrupted": "!", None: "\u00b7"}


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


def _href(page_dir: Path, target: Path) -> str:
    """A relative URL from the page's folder to ``target`` (percent-encoded, '/'-separated)."""
    rel = os.path.relpath(target.resolve(), page_dir.resolve())
    return quote(Path(rel).as_posix(), safe="/")


def _number(value, fmt: str) -> tuple[str, str]:
    """(text, sort key) of a figure; ("", "") when there is none."""
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)):
        return "", ""
    return format(value, fmt), repr(float(value))


def take_rows(ws) -> list[dict[str, Any]]:
    """One dict per take: ``take``, ``stages`` (stage -> state, or for the per-sequence stages
    "k/n" done), ``verdict`` (``flagged``, ``clean`` or ``unchecked``), ``flags``, ``outdated``,
    ``figures`` and ``links`` (name -> path of an artifact that exists)."""
    from dualhuman_builder.pipeline import STAGES
    from dualhuman_builder.workspace.catalog import take_flags

    verdicts = take_flags(ws.conn)
    status = ws.status_rows()
    out = []
    for row in (r for r in status if r["sequence"] is None):
        take = row["take"]
        seqs = [r for r in status if r["take"] == take and r["sequence"] is not None]
        stages: dict[str, str | None] = {}
        for s in STAGES:
            if s.per == "sequence":
                done = sum(1 for r in seqs if (r["stages"].get(s.name) or {}).get("state") == "done")
                stages[s.name] = f"{done}/{len(seqs)}" if seqs else None
            else:
                stages[s.name] = (row["stages"].get(s.name) or {}).get("state")
        v = verdicts.get(take)
        verdict = "unchecked" if v is None else "flagged" if v["flags"] else "clean"
        figures: dict[str, Any] = {}
        links: dict[str, Path] = {}
        for name in ("sync", "fit", "contacts", "render", "sheet"):
            rec = ws.stage_record(name, take)
            if rec is None or rec["status"] not in ("done", "stale"):
                continue
            summ, arts = rec["summary"], rec["artifacts"]
            if name == "fit":
                for key in ("frames", "max_penetration_after_mm", "penetrating_share_after"):
                    figures[key] = summ.get(key)
            elif name == "contacts":
                figures["contact_frames"] = summ.get("contact_frames")
                figures["contact_events"] = summ.get("events")
            elif name == "render":
                figures["render_frames"] = summ.get("frames")
            for label, art in (("fit report", "report.html"), ("contact sheet", "contact_sheet.png"),
                               ("sync report", "sync.json"), ("renders", "render.json")):  # fmt: skip
                if art in arts and (ws.root / arts[art]["path"]).is_file():
                    links[label] = (ws.root / arts[art]["path"]).parent / "views" if label == "renders" else \
                        ws.root / arts[art]["path"]  # fmt: skip
        out.append({"take": take, "stages": stages, "verdict": verdict, "flags": (v or {}).get("flags", []),
                    "outdated": (v or {}).get("outdated", []), "checked_at": (v or {}).get("checked_at"),
                    "figures": figures, "links": links})  # fmt: skip
    return out


def render_page(ws, page_dir: Path, rows: list[dict[str, Any]] | None = None, title: str | None = None) -> str:
    """The review page's HTML for workspace ``ws``, its links relative to ``page_dir``."""
    from dualhuman_builder.pipeline import STAGES
    from dualhuman_builder.quality.gates import GATE_NAMES
    from dualhuman_builder.workspace.catalog import now_iso

    rows = take_rows(ws) if rows is None else rows
    title = title or f"Review of {ws.root.name}"
    n = {k: sum(r["verdict"] == k for r in rows) for k in ("flagged", "clean", "unchecked")}
    by_gate: dict[str, int] = {}
    for r in rows:
        for g in sorted({f["gate"] for f in r["flags"]}):
            by_gate[g] = by_gate.get(g, 0) + 1
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           '<meta name="viewport" content="width=device-width, initial-scale=1">',
           f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
           f"<h1>{_e(title)}</h1>",
           (f'<p class="meta">Workspace <code>{_e(ws.root)}</code>, written {_e(now_iso())} by <code>dualhuman review</code>. '
            "Flags come from <code>dualhuman gates</code> (thresholds: <code>dualhuman_builder/quality/gates.toml</code>).</p>"),
           (f'<p class="summary"><span id="count-takes">{len(rows)} takes</span><span id="count-flagged">{n["flagged"]} flagged</span>'
            f'<span id="count-clean">{n["clean"]} clean</span><span id="count-unchecked">{n["unchecked"]} not checked</span>'
            '<span>shown: <b id="shown"></b></span></p>'),  # the script counts them
           '<p class="summary">' + "".join(f"<span>{_e(g)}: {c}</span>" for g, c in sorted(by_gate.items())) + "</p>",
           ('<div class="controls"><label>verdict <select id="verdict"><option value="all">all</option>'
            '<option value="flagged">flagged</option><option value="clean">clean</option>'
            '<option value="unchecked">not checked</option></select></label>'
            '<label>gate <select id="gate"><option value="">any</option>')
           + "".join(f'<option value="{_e(g)}">{_e(g)}</option>' for g in GATE_NAMES)
           + ('</select></label><label>text <input id="text" type="search" placeholder="take, flag..."></label>'
              "</div>"),
           '<table id="takes"><thead><tr><th>take</th><th>verdict</th>'
           + "".join(f"<th>{_e(s.name)}</th>" for s in STAGES)
           + ("<th>flags</th><th>frames</th><th>max penetration (mm)</th><th>penetrating (%)</th>"
              "<th>contact frames</th><th>links</th></tr></thead><tbody>")]  # fmt: skip
    for r in rows:
        gates = " ".join(sorted({f["gate"] for f in r["flags"]}))
        cells = [f'<td class="take">{_e(r["take"])}</td>']
        label = {"flagged": f"flagged ({len(r['flags'])})", "clean": "clean", "unchecked": "not checked"}[r["verdict"]]
        order = {"flagged": 0, "unchecked": 1, "clean": 2}[r["verdict"]]
        cells.append(f'<td class="verdict" data-sort="{order}">{_e(label)}'
                     + (f'<br><span class="outdated">outdated: {_e(", ".join(r["outdated"]))} ran again since</span>'
                        if r["outdated"] else "") + "</td>")  # fmt: skip
        for s in STAGES:
            state = r["stages"].get(s.name)
            if state is not None and "/" in str(state):
                cells.append(f'<td class="st">{_e(state)}</td>')
            else:
                cells.append(f'<td class="st {_e(state or "none")}" title="{_e(state or "not run")}">{MARKS.get(state, "?")}</td>')
        items = "".join(f'<li data-gate="{_e(f["gate"])}"><b>{_e(f["gate"])}</b> ({_e(f["stage"])}): {_e(f["message"])}</li>'
                        for f in r["flags"])  # fmt: skip
        cells.append(f'<td class="flags" data-sort="{len(r["flags"])}">' + (f'<ul class="flags">{items}</ul>' if items else "")
                     + "</td>")  # fmt: skip
        fig = r["figures"]
        share = fig.get("penetrating_share_after")
        for value, fmt in ((fig.get("frames"), "d"), (fig.get("max_penetration_after_mm"), ".2f"),
                           (None if share is None else 100 * share, ".3f"), (fig.get("contact_frames"), "d")):  # fmt: skip
            try:
                text, key = _number(value, fmt)
            except (TypeError, ValueError):
                text, key = _number(value, "g")
            cells.append(f'<td class="num" data-sort="{_e(key or "-1")}">{_e(text)}</td>')
        links = " ".join(f'<a href="{_e(_href(page_dir, p))}" data-kind="{_e(name)}">{_e(name)}</a>'
                         for name, p in r["links"].items())  # fmt: skip
        cells.append(f'<td class="links">{links}</td>')
        out.append(f'<tr class="{r["verdict"]}" data-verdict="{r["verdict"]}" data-gates="{_e(gates)}" '
                   f'data-take="{_e(r["take"])}">' + "".join(cells) + "</tr>")  # fmt: skip
    out += ["</tbody></table>", f"<script>{_JS}</script>", "</body></html>"]
    return "\n".join(out)


def write_review(ws, out: str | Path | None = None) -> Path:
    """Write the review page of ``ws`` to ``out`` (default ``WS/review.html``) atomically; returns its path."""
    from dualhuman_builder.fileio import atomic_open

    path = Path(out) if out is not None else ws.root / REVIEW_NAME
    if path.is_dir():
        path = path / REVIEW_NAME
    if not path.parent.is_dir():
        raise WorkspaceError("the review page's folder does not exist", path=path.parent,
                             fix=f"create it (mkdir -p {path.parent}) or give another --out")  # fmt: skip
    page = render_page(ws, path.parent)
    with atomic_open(path, "wb") as f:
        f.write(page.encode("utf-8"))
    return path


def page_json(rows: list[dict[str, Any]]) -> str:
    """The rows as JSON (paths as strings), for scripts that triage without a browser."""
    return json.dumps([{**r, "links": {k: str(v) for k, v in r["links"].items()}} for r in rows], indent=1)
