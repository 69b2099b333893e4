"""Regenerate ``docs/benchmarks.md`` and ``docs/accuracy.md`` from ``benchmarks/results/*.json``.

    .venv/bin/python benchmarks/make_docs.py            # write both files
    .venv/bin/python benchmarks/make_docs.py --check    # exit 1 if either differs from what the results give

``docs/benchmarks.md`` has one section per results file (see ``results_file.py`` for the layout):
what the script measures, the command that wrote the file, the machine, date and commit, its tables
of main figures, and its goals, met or NOT met. A results file these docs expect (``EXPECTED``) that
is missing is listed as not measured yet, with the command that measures it. ``docs/accuracy.md``
holds the fit accuracy tables from ``fit_accuracy.json``, ``fit_accuracy_realistic.json`` and
``fit_accuracy_calibrated.json``: one
row per take, the mean and worst over takes, and the goals.

Both files depend on nothing but the results files (and, for a missing one, its script's docstring),
so ``--check`` can run in a test: it prints which file is out of date and exits 1.
"""

from __future__ import annotations

import argparse
import ast
import datetime as _dt
import difflib
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import lookup, summary  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DOCS = ROOT / "docs"
RUN = ".venv/bin/python"

#: Where the reaction prior's experiments read their data from, for ``EXPECTED``'s entries.
RP_DATASET = "the reaction prior's dataset ([models guide](guides/models.md#the-reaction-prior-on-a-synthetic-dataset))"

#: The results files the docs expect, in the order they appear: (name, command that writes it from
#: the repository root, where it must run). Probes are the ``probe_*`` names. A script under
#: ``benchmarks/`` or ``benchmarks/probes/`` that no entry runs is expected too (``expected()``).
EXPECTED: tuple[tuple[str, str, str], ...] = (
    ("body", "benchmarks/bench_body.py", ""),
    ("body_cuda", "benchmarks/bench_body.py --device all", "on a machine with a CUDA GPU"),
    ("scenes", "benchmarks/bench_scenes.py", ""),
    ("scene_seeds", "benchmarks/bench_scene_seeds.py",
     "on an otherwise idle machine (300 scenes at 30 fps: several hours on 2 cores)"),
    ("capture", "benchmarks/bench_capture.py", ""),
    ("decoders", "benchmarks/bench_decoders.py", ""),
    ("mvnx", "benchmarks/bench_mvnx.py", "with the `bench` extra installed (the `mvnx` package)"),
    ("fit", "benchmarks/bench_fit.py --minutes 1 --collision held --runs 1 --workers 1,auto", ""),
    ("fit_cuda", "benchmarks/bench_fit.py --inputs HUG.npz --device cuda --collision held --runs 1",
     "on a machine with a CUDA GPU; HUG.npz from `bench_fit.py --minutes 1 --save-inputs HUG.npz --runs 0`"),
    ("fit_solvers", "benchmarks/bench_fit.py --collision held --solver windows,take:shared,take:runs "
     "--out benchmarks/results/fit_solvers.json",
     ""),
    ("fit_accuracy", "benchmarks/bench_fit_accuracy.py --keep TAKES",
     "with TAKES a folder that keeps the recordings (a later run scores the same ones)"),
    ("fit_accuracy_take", "benchmarks/bench_fit_accuracy.py --keep TAKES --solver take",
     "with TAKES the folder of `fit_accuracy`'s run (the same recordings)"),
    ("fit_accuracy_take_runs", "benchmarks/bench_fit_accuracy.py --keep TAKES --solver take:runs",
     "with TAKES the folder of `fit_accuracy`'s run (the same recordings)"),
    ("fit_accuracy_calibrated", "benchmarks/bench_fit_accuracy.py --keep TAKES --calibration",
     "with TAKES a folder that keeps the recordings (a later run scores the same ones)"),
    ("fit_accuracy_realistic", "benchmarks/bench_fit_accuracy.py --keep TAKES --preset realistic",
     "with TAKES a folder that keeps the recordings (a later run scores the same ones)"),
    ("fit_accuracy_realistic_take", "benchmarks/bench_fit_accuracy.py --keep TAKES --preset realistic --solver take",
     "with TAKES the folder of `fit_accuracy_realistic`'s run (the same recordings)"),
    ("fit_accuracy_realistic_take_runs", "benchmarks/bench_fit_accuracy.py --keep TAKES --preset realistic --solver take:runs",
     "with TAKES the folder of `fit_accuracy_realistic`'s run (the same recordings)"),
    ("fit_accuracy_realistic_no_trackers", "benchmarks/bench_fit_accuracy.py --keep TAKES --preset realistic --no-trackers",
     "with TAKES a folder that keeps the recordings (a later run scores the same ones)"),
    ("long_takes", "benchmarks/bench_long_takes.py --takes 60 600 --keep TAKES",
     "with TAKES a folder that keeps the scenes and takes (the 10-minute scene takes about 10 minutes to make)"),
    ("run", "benchmarks/bench_run.py --takes 24",
     "on an otherwise idle machine (24 takes through the fit with each executor: about an hour on 2 cores)"),
    ("long_takes_realistic", "benchmarks/bench_long_takes.py --takes 60 600 --preset realistic --keep TAKES",
     "with TAKES a folder that keeps the scenes and takes (the 10-minute scene takes about 10 minutes to make)"),
    ("collision", "benchmarks/bench_collision.py", ""),
    ("contacts", "benchmarks/bench_contacts.py", "with the `bench` extra installed (`rtree`, for trimesh)"),
    ("render", "benchmarks/bench_render.py", ""),
    ("render_cuda", "benchmarks/bench_render.py --variant cuda_ad_rgb --views 8 --frames 16 --repeats 5",
     "on a machine with a CUDA GPU"),
    ("export", "benchmarks/bench_export.py", ""),
    ("fuzz", "benchmarks/fuzz.py", "on an otherwise idle machine (100,000 inputs per target: about 15 to 20 minutes on 2 cores)"),
    ("probe_mcap_writer", "benchmarks/probes/probe_mcap_writer.py --repeats 9", ""),
    ("probe_skin_at", "benchmarks/probes/probe_skin_at.py", ""),
    ("probe_collision_band", "benchmarks/probes/probe_collision_band.py", ""),
    ("probe_tracker_offsets", "benchmarks/probes/probe_tracker_offsets.py --keep TAKES",
     "with TAKES a folder that keeps the tuning seeds' recordings"),
    ("probe_fit_spread", "benchmarks/probes/probe_fit_spread.py --keep TAKES",
     "with TAKES the folder of `fit_accuracy_realistic`'s run (its recording is the first of five)"),
    ("probe_fit_spread_take_step", "benchmarks/probes/probe_fit_spread.py --keep TAKES --solver take:shared,take:runs,windows "
     "--out benchmarks/results/probe_fit_spread_take_step.json", "with TAKES the folder of `probe_fit_spread`'s run (the same five recordings)"),
    ("probe_fit_rules", "benchmarks/probes/probe_fit_rules.py --inputs HUG.npz --runs 2",
     "on an otherwise idle machine (12 fits of half a minute: about 20 minutes on 2 cores); HUG.npz from "
     "`bench_fit.py --minutes 1 --save-inputs HUG.npz --runs 0`"),
    ("probe_prior_code", "benchmarks/probes/probe_prior_code.py --export RP/export-r64 --work RP/codes --jobs 2 "
     "--vae 64x2,64x2t4,64x2t8,128x2,64x2@6000",
     f"with RP/export-r64 {RP_DATASET}; "
     "about an hour on 2 cores"),
    ("reaction_prior", "benchmarks/bench_reaction_prior.py --export RP/export --seeds 3 --jobs 2 --work RP/runs "
     "--choose-lambda 0.01,0.1,1,10,100,1000 --set inn_steps=5400 --vae-set vae_steps=2000 "
     "--variants full,no_vae,mlp,no_noise,features",
     f"with RP/export {RP_DATASET}; "
     "several hours on 2 cores"),
    ("reaction_prior_vae6000", "benchmarks/bench_reaction_prior.py --export RP/export --seeds 3 --jobs 2 --work RP/v6 "
     "--choose-lambda 0.01,0.1,1,10,100,1000 --set inn_steps=5400 --vae-set vae_steps=6000 "
     "--variants full,no_vae,mlp,no_noise --out benchmarks/results/reaction_prior_vae6000.json",
     f"with RP/export {RP_DATASET}; "
     "about two hours on 2 cores"),
    ("probe_interchange_upstream",
     "benchmarks/probes/probe_interchange_upstream.py --humanml3d HUMANML3D --intergen INTERGEN",
     "with checkouts of EricGuo5513/HumanML3D and tr3e/InterGen"),
)

ACCURACY = (("fit_accuracy", "Ideal devices, without a calibration take"),
            ("fit_accuracy_take", "Ideal devices, the take solver (`fit --solver take`), on the first table's recordings"),
            ("fit_accuracy_take_runs", "Ideal devices, the take solver with a step per run of frames (`--take-step runs`), on the first table's recordings"),
            ("fit_accuracy_realistic", "Realistic devices (every error drawn per take), without a calibration take"),
            ("fit_accuracy_realistic_take", "Realistic devices, the take solver, on the table above's recordings"),
            ("fit_accuracy_realistic_take_runs", "Realistic devices, the take solver with a step per run of frames, on the same recordings"),
            ("fit_accuracy_realistic_no_trackers", "Realistic devices, the fit without trackers (what they buy)"),
            ("fit_accuracy_calibrated", "Ideal devices, with the studio day's calibration take"))  # fmt: skip

INTRO = (
    "Each script under `benchmarks/` writes its latest figures to `benchmarks/results/<name>.json`, with the machine, "
    "date and commit they were measured on and the goal each figure is held against; `benchmarks/make_docs.py` "
    "generates this page and [fit accuracy](accuracy.md) from those files. Speed figures hold for the machine named in "
    "each section; ratios to a baseline are measured in the same run. Probes (`benchmarks/probes/`) each measure one "
    "design question."
)
ACCURACY_INTRO = (
    "Takes are recorded in real time from the simulated studio over loopback transports, one per scene type and "
    "seed, and scored against the scene's ground truth. The seeds were chosen once and the fit is never tuned on "
    "them (it is tuned on seeds 1 and 2). `ideal` devices have the simulators' default errors; `realistic` ones draw "
    "every error per take within published ranges ([presets](guides/simulation-presets.md)). Contact F1 compares "
    "the fitted pair's per-vertex contacts with the ground truth's at the contact threshold. With the calibration take, each device seed's calibration "
    "take carries its tracker mounts and lags into every take of that seed; the mount columns are then the "
    "calibration take's. The table without trackers fits the same realistic takes with the suits alone (collision term "
    "kept): what the trackers buy. What limits the realistic figures: [presets](guides/simulation-presets.md#what-limits-the-fit-under-realistic). "
    "Speed figures: [benchmarks](benchmarks.md)."
)
ACCURACY_LEGEND = (
    'Bold: a take over its goal. "free": fitted without trackers or the collision term; "off": the penetration the '
    "fit's windows leave before the collision passes. Goals hold for the worst take:"
)

GENERATED = ("<!-- Generated by benchmarks/make_docs.py from benchmarks/results/*.json: do not edit by hand. "
             "Re-run the benchmark, then `.venv/bin/python benchmarks/make_docs.py`. -->")  # fmt: skip


def expected(root: Path = ROOT) -> list[tuple[str, str, str]]:
    """``EXPECTED``, then one entry per other ``bench_<name>.py`` (results ``<name>``) and
    ``probes/probe_<name>.py`` (results ``probe_<name>``), by file name."""
    covered = {command.split()[0] for _, command, _ in EXPECTED}
    out = list(EXPECTED)
    scripts = sorted((root / "benchmarks").glob("bench_*.py")) + sorted((root / "benchmarks" / "probes").glob("probe_*.py"))
    for p in scripts:
        script = p.relative_to(root).as_posix()
        if script not in covered:
            out.append((p.stem.removeprefix("bench_"), script, ""))
    return out


# ============================================================================ formatting
def fmt(value: Any) -> str:
    """A figure as table text: None as a dash, booleans as yes/no, numbers to ~3 significant digits
    (thousands separated), lists joined, ``{"mean", "std"}`` as "mean ± std"."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        if math.isnan(value) or math.isinf(value):
            return "—"
        a = abs(value)
        if a == 0:
            return "0"
        if a >= 100:
            return f"{value:,.0f}"
        if a >= 10:
            return f"{value:.1f}"
        if a >= 1:
            return f"{value:.2f}"
        if a >= 1e-3:
            return f"{value:.3g}"
        return f"{value:.1e}"
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v) for v in value)
    if isinstance(value, dict) and set(value) == {"mean", "std"}:  # over seeds
        return f"{fmt(value['mean'])} ± {fmt(value['std'])}"
    if isinstance(value, dict):
        return ", ".join(f"{k} {fmt(v)}" for k, v in value.items())
    return str(value).replace("|", "\\|")


def md_table(header: list[str], rows: list[list[str]], align: list[str] | None = None) -> list[str]:
    align = align or ["---"] + ["---:"] * (len(header) - 1)
    out = ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def when(doc: dict) -> str:
    try:
        t = _dt.datetime.fromisoformat(doc["date"]).astimezone(_dt.UTC)
        date = t.strftime("%Y-%m-%d %H:%M UTC")
    except (KeyError, ValueError):
        date = str(doc.get("date", "?"))
    sha = str(doc.get("commit", "unknown"))
    dirty = sha.endswith("-dirty")
    sha = sha.removesuffix("-dirty")
    commit = f"`{sha[:10]}`" + (" with uncommitted changes" if dirty else "") if sha != "unknown" else "unknown"
    return f"{date}, commit {commit}"


def machine_line(m: dict) -> str:
    parts = [m.get("cpu") or "unknown CPU"]
    if m.get("cores"):
        parts.append(f"{m['cores']} cores")
    if m.get("memory_gib"):
        parts.append(f"{m['memory_gib']:g} GiB memory")
    parts.append(f"GPU: {m['gpu']}" if m.get("gpu") else "no GPU")
    versions = [f"Python {m['python']}"] if m.get("python") else []
    if m.get("torch"):
        versions.append(f"torch {m['torch']}")
    return ", ".join(parts) + ("; " + ", ".join(versions) if versions else "")


def command_line(doc: dict) -> str:
    words = str(doc.get("command", "")).split()
    script = str(doc.get("script", ""))
    if words and script.endswith(words[0]):
        words[0] = script
    return f"{RUN} " + " ".join(words)


def goal_rows(goals: list[dict]) -> list[list[str]]:
    rows = []
    for g in goals:
        value, unit = g.get("value"), g.get("unit") or ""
        if isinstance(value, bool) or (value is None and g.get("op") == ">=" and g.get("bound") == 1 and not unit):
            bound = "holds"
        else:
            bound = f"{'≤' if g['op'] == '<=' else '≥'} {g['bound']:g}" + (f" {unit}" if unit else "")
        measured = fmt(value) + (f" {unit}" if unit and value is not None and not isinstance(value, bool) else "")
        met = {True: "met", False: "**NOT met**", None: "not measured"}[g.get("met")]
        rows.append([g.get("label") or f"`{g['figure']}`", bound, measured, met])
    return rows


def goals_tally(goals: list[dict]) -> str:
    if not goals:
        return "no goals"
    met = sum(1 for g in goals if g.get("met") is True)
    missed = sum(1 for g in goals if g.get("met") is False)
    text = f"{met} of {len(goals)} goals met"
    return text + (f", **{missed} NOT met**" if missed else "")


# ============================================================================ inputs
def load_results(folder: Path) -> dict[str, dict]:
    """``{name: document}`` of every ``*.json`` in ``folder`` (a file that is not a results file is
    reported and skipped)."""
    out = {}
    for p in sorted(folder.glob("*.json")):
        try:
            doc = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as e:
            print(f"make_docs: skipping {p}: {e}", file=sys.stderr)
            continue
        if not isinstance(doc, dict) or "figures" not in doc:
            print(f"make_docs: skipping {p}: not a results file (no 'figures')", file=sys.stderr)
            continue
        out[p.stem] = doc
    return out


def plain(text: str) -> str:
    """reStructuredText inline markup of a docstring as Markdown: ````x```` -> ```x```, roles dropped."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def script_summary(command: str) -> str:
    """The first paragraph of the docstring of the script a command runs ("" if unreadable)."""
    path = ROOT / command.split()[0]
    try:
        return plain(summary(ast.get_docstring(ast.parse(path.read_text()))))
    except (OSError, SyntaxError):
        return ""


# ============================================================================ docs/benchmarks.md
def section(name: str, doc: dict | None, command: str, where: str) -> list[str]:
    script = (doc or {}).get("script") or command.split()[0]
    out = [f"### {name}", ""]
    if doc is None:
        text = script_summary(command)
        out += ([text, ""] if text else [])
        out += [f"**Not measured yet.** Run{' ' + where if where else ''}:", "", "```bash",
                f"{RUN} {command}", "```", ""]  # fmt: skip
        return out
    text = plain(doc.get("description") or "") or script_summary(command)
    out += ([text, ""] if text else [])
    out += [f"- Script: `{script}`", f"- Command: `{command_line(doc)}`",
            f"- Machine: {machine_line(doc.get('machine') or {})}", f"- Measured: {when(doc)}"]  # fmt: skip
    if name in dict(ACCURACY):
        out.append("- Per take: [fit accuracy](accuracy.md)")
    out.append("")
    figures = doc.get("figures") or {}
    for t in doc.get("tables") or []:
        rows = [[str(r[0])] + [fmt(lookup(figures, c)) if c else "" for c in r[1:]] for r in t["rows"]]
        out += [f"{t['title']}:", ""] + md_table(list(t["columns"]), rows) + [""]
    goals = doc.get("goals") or []
    if goals:
        out += ["Goals:", ""] + md_table(["figure", "goal", "measured", ""], goal_rows(goals),
                                         ["---", "---", "---:", "---"]) + [""]  # fmt: skip
    else:
        out += ["No goals: the figures are for comparison.", ""]
    if doc.get("notes"):
        out += [str(doc["notes"]), ""]
    return out


def benchmarks_md(results: dict[str, dict]) -> str:
    known = expected()
    names = [n for n, _, _ in known] + sorted(n for n in results if n not in {e[0] for e in known})
    spec = {n: (c, w) for n, c, w in known}
    out = [GENERATED, "", "# Benchmarks", "", INTRO, "",
           "| results file | script | measured | goals |", "| --- | --- | --- | --- |"]  # fmt: skip
    for n in names:
        doc = results.get(n)
        command = spec.get(n, ((doc or {}).get("script", "?"), ""))[0]
        script = (doc or {}).get("script") or command.split()[0]
        status = when(doc).split(",")[0] if doc else "not measured yet"
        out.append(f"| [{n}](#{n}) | `{script}` | {status} | {goals_tally(doc.get('goals') or []) if doc else ''} |")
    out.append("")
    groups = (("Benchmarks", [n for n in names if not n.startswith("probe_")]),
              ("Probes", [n for n in names if n.startswith("probe_")]))  # fmt: skip
    for title, group in groups:
        if not group:
            continue
        out += [f"## {title}", ""]
        for n in group:
            doc = results.get(n)
            command, where = spec.get(n, ((doc or {}).get("script", "?"), ""))
            out += section(n, doc, command, where)
    return "\n".join(out).rstrip() + "\n"


# ============================================================================ docs/accuracy.md
#: (header, column, the column shown beside it in the same cell or None, digits)
ACC_COLUMNS = (
    ("MPJPE mm", "mpjpe_mm", None, 2),
    ("PA-MPJPE mm", "pa_mpjpe_mm", None, 2),
    ("root mm", "root_mm", None, 2),
    ("MPJPE / root free mm", "mpjpe_free_mm", "root_free_mm", 1),
    ("max pen. mm (off)", "max_penetration_mm", "max_penetration_off_mm", 2),
    ("pen. share % (off)", "penetrating_share_pct", "penetrating_share_off_pct", 3),
    ("clock ms", "clock_offset_error_ms", None, 2),
    ("mount °", "mount_rotation_error_deg", None, 2),
    ("mount offset mm", "mount_offset_error_mm", None, 1),
    ("slide mm", "foot_slide_mm", None, 2),
    ("contact F1", "contact_f1", None, 3),
    ("fit s", "fit_s", None, 1),
    ("fit s exact", "fit_s_exact", None, 1),
    ("MPJPE exact mm", "mpjpe_exact_mm", None, 2),
)


def num(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and (math.isnan(value) or math.isinf(value))):
        return "—"
    return f"{value:.{digits}f}"


def take_name(row: dict) -> str:
    return f"{str(row.get('type', '?')).replace('_', ' ')} {row.get('seed', '')}".strip()


def accuracy_section(title: str, name: str, doc: dict | None) -> list[str]:
    out = [f"## {title}", ""]
    if doc is None:
        command, where = {n: (c, w) for n, c, w in EXPECTED}[name]
        return out + [f"`benchmarks/results/{name}.json`: **not measured yet.** Run{' ' + where if where else ''}:",
                      "", "```bash",
                      f"{RUN} {command}", "```", ""]  # fmt: skip
    figures, params = doc.get("figures") or {}, doc.get("params") or {}
    rows, summ = figures.get("rows") or [], figures.get("summary") or {}
    bounds = {g["figure"].split(".")[1]: g for g in doc.get("goals") or [] if g["figure"].startswith("summary.")}
    cols = [c for c in ACC_COLUMNS if any(c[1] in r for r in rows)]
    out += [f"- Results file: `benchmarks/results/{name}.json`", f"- Command: `{command_line(doc)}`",
            f"- Machine: {machine_line(doc.get('machine') or {})}", f"- Measured: {when(doc)}"]  # fmt: skip
    setting = [f"{params['fps']:g} fps" if isinstance(params.get("fps"), (int, float)) else None,
               f"recorded at {params['speed']:g}x real time" if isinstance(params.get("speed"), (int, float)) else None,
               f"{len(rows)} take{'' if len(rows) == 1 else 's'}"]  # fmt: skip
    out += ["- Takes: " + ", ".join(s for s in setting if s), ""]

    def cell(r: dict, c: tuple) -> str:
        header, key, off, digits = c
        text = num(r.get(key), digits)
        g = bounds.get(key)
        value = r.get(key)
        over = g and isinstance(value, (int, float)) and not math.isnan(value) and (
            value > g["bound"] if g["op"] == "<=" else value < g["bound"])
        if over:
            text = f"**{text}**"
        if off:
            other = num(r.get(off), digits)
            text = f"{text} / {other}" if header.startswith("MPJPE /") else f"{text} ({other})"
        return text

    body = [[take_name(r)] + [cell(r, c) for c in cols] for r in rows]
    for stat in ("mean", "worst"):
        body.append([f"*{stat}*"] + [cell({k: (summ.get(k) or {}).get(stat) for k in (c[1], c[2]) if k}, c)
                                     for c in cols])  # fmt: skip
    goal_cells = []
    for c in cols:
        g = bounds.get(c[1])
        goal_cells.append(f"{'≤' if g['op'] == '<=' else '≥'} {g['bound']:g}" if g else "")
    body.append(["goal"] + goal_cells)
    out += md_table(["take"] + [c[0] for c in cols], body) + [""]
    out += [ACCURACY_LEGEND, ""]
    out += md_table(["figure", "goal", "measured", ""], goal_rows(doc.get("goals") or []),
                    ["---", "---", "---:", "---"]) + [""]  # fmt: skip
    cal = figures.get("calibration_takes") or {}
    if cal:
        out += ["Calibration takes (their own tracker mounts against the simulated ones):", ""]
        out += md_table(["calibration take", "mount ° worst", "offset mm mean", "offset mm RMS", "offset mm worst"],
                        [[f"seed {s}", num(v.get("rotation_deg_worst"), 2), num(v.get("offset_mm_mean"), 1),
                          num(v.get("offset_mm_rms"), 1), num(v.get("offset_mm_worst"), 1)] for s, v in cal.items()]) + [""]  # fmt: skip
    totals = figures.get("totals") or {}
    if totals.get("fit_s_exact"):
        out += [(f"Fit seconds over all takes: {totals['fit_s']:.1f} with held contacts, {totals['fit_s_exact']:.1f} "
                 f"located at every evaluation ({totals['exact_over_held']:.2f}x)."), ""]  # fmt: skip
    if doc.get("notes"):
        out += [str(doc["notes"]), ""]
    return out


def accuracy_md(results: dict[str, dict]) -> str:
    desc = plain(next((results[n].get("description") for n, _ in ACCURACY if n in results and results[n].get("description")),
                     "")) or script_summary("benchmarks/bench_fit_accuracy.py")  # fmt: skip
    out = [GENERATED, "", "# Fit accuracy", "", desc, "", ACCURACY_INTRO, ""]
    for name, title in ACCURACY:
        out += accuracy_section(title, name, results.get(name))
    for name in sorted(n for n in results if n.startswith("fit_accuracy") and n not in dict(ACCURACY)):
        params = results[name].get("params") or {}
        seeds = ", ".join(str(x) for x in params.get("seeds") or [])
        title = (f"`{name}`: {'with' if params.get('calibration') else 'without'} a calibration take"
                 + (f", device seeds {seeds}" if seeds else ""))  # fmt: skip
        out += accuracy_section(title, name, results[name])
    return "\n".join(out).rstrip() + "\n"


# ============================================================================ main
def render(results_dir: Path) -> dict[str, str]:
    """``{file name: text}`` of both generated docs."""
    results = load_results(results_dir)
    return {"benchmarks.md": benchmarks_md(results), "accuracy.md": accuracy_md(results)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a generated file is out of date")
    ap.add_argument("--results", type=Path, default=RESULTS, help="folder of results files (default benchmarks/results)")
    ap.add_argument("--docs", type=Path, default=DOCS, help="folder the docs go to (default docs)")
    args = ap.parse_args(argv)
    stale = []
    for name, text in render(args.results).items():
        path = args.docs / name
        old = path.read_text() if path.is_file() else None
        if old == text:
            continue
        if args.check:
            stale.append(name)
            diff = difflib.unified_diff((old or "").splitlines(), text.splitlines(), f"{path} (on disk)",
                                        f"{path} (from the results)", n=1, lineterm="")  # fmt: skip
            print("\n".join(list(diff)[:40]))
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print(f"out of date: {', '.join(stale)}; run {RUN} benchmarks/make_docs.py", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
