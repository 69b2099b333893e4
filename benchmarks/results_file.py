"""One results file per benchmark: ``benchmarks/results/<name>.json``, committed with the code.

Every benchmark script ends with :func:`write_results`, which records where and when the figures
were measured (machine, CPU and GPU model, date, commit, command line) beside the figures and the
goal each one is held against, so that the tables in ``docs/`` are generated from data
(``benchmarks/make_docs.py``) rather than typed by hand.

File layout::

    {"name": "...", "script": "benchmarks/bench_x.py", "command": "bench_x.py --flag ...",
     "description": "...",                 # what the script measures: its docstring's first paragraph
     "date": "2026-11-27T15:00:00+00:00", "commit": "<sha>[-dirty]",
     "machine": {"cpu": "...", "cores": 2, "memory_gib": 23.4, "gpu": null, "python": "3.11.7",
                 "torch": "2.13.0", "platform": "Linux-..."},
     "params": {...},                      # what the run was asked to do
     "figures": {...},                     # any JSON: the measurements
     "goals": [{"figure": "summary.mpjpe_mm.worst", "op": "<=", "bound": 15.0, "value": 9.6,
                "unit": "mm", "label": "MPJPE, worst take", "met": true}],
     "tables": [{"title": "...", "columns": ["batch", "bodies/s"],
                 "rows": [["1", "cpu.1.forward.bodies_per_s"]]}],
     "notes": "..."}

``met`` is null where the figure was not measured (missing, NaN or not a number). A table's rows
are a label followed by dotted paths into ``figures`` (``""``: an empty cell); ``make_docs.py``
looks them up, so each figure is written once.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"


@dataclass(frozen=True)
class Goal:
    """A bound a figure is measured against: ``figure`` is a dotted path into ``figures``
    (``"summary.mpjpe_mm.worst"``; list items by index), ``op`` one of ``<=``, ``>=`` (a boolean
    figure that must hold: ``>= 1``), ``label`` what the figure is, in words."""

    figure: str
    op: str
    bound: float
    unit: str = ""
    label: str = ""

    def __post_init__(self) -> None:
        if self.op not in ("<=", ">="):
            raise ValueError(f"Goal op must be '<=' or '>=', not {self.op!r}")

    def check(self, figures: Mapping[str, Any]) -> dict[str, Any]:
        value = lookup(figures, self.figure)
        ok = None
        if isinstance(value, (int, float)) and not (isinstance(value, float) and math.isnan(value)):
            ok = bool(value <= self.bound if self.op == "<=" else value >= self.bound)
        return {"figure": self.figure, "op": self.op, "bound": self.bound, "value": value, "unit": self.unit,
                "label": self.label, "met": ok}  # fmt: skip


@dataclass(frozen=True)
class Table:
    """A table of main figures for the generated docs: ``columns`` heads it; each row is a label
    followed by one dotted path into ``figures`` per further column (``""``: an empty cell)."""

    title: str
    columns: Sequence[str]
    rows: Sequence[Sequence[str]]

    def as_dict(self) -> dict[str, Any]:
        for row in self.rows:
            if len(row) != len(self.columns):
                raise ValueError(f"table {self.title!r}: row {list(row)} has {len(row)} cells, not {len(self.columns)}")
        return {"title": self.title, "columns": list(self.columns), "rows": [list(r) for r in self.rows]}


def lookup(figures: Mapping[str, Any], dotted: str) -> Any:
    """``figures["a"]["b"]`` for ``"a.b"``; None where a key is missing."""
    cur: Any = figures
    for key in dotted.split("."):
        if isinstance(cur, Mapping) and key in cur:
            cur = cur[key]
        elif isinstance(cur, list) and key.isdigit() and int(key) < len(cur):
            cur = cur[int(key)]
        else:
            return None
    return cur


def machine() -> dict[str, Any]:
    """CPU model, cores, memory, GPU (CUDA device name, if torch sees one), versions."""
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem = round(int(line.split()[1]) / 2**20, 1)
                break
    except OSError:
        pass
    gpu = torch_version = None
    if "torch" in sys.modules or _importable("torch"):
        import torch

        torch_version = torch.__version__
        if torch.cuda.is_available():
            gpu = torch.cuda.get_device_name(0)
    return {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": mem, "gpu": gpu,
            "python": platform.python_version(), "torch": torch_version, "platform": platform.platform()}  # fmt: skip


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


def commit() -> str:
    """The checkout's commit, with ``-dirty`` when tracked files differ from it."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()  # fmt: skip
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _plain(o: Any) -> Any:
    """JSON for numpy scalars and arrays, NaN as null."""
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    return str(o)


def _no_nan(o: Any) -> Any:
    if isinstance(o, float) and (math.isnan(o) or math.isinf(o)):
        return None
    if isinstance(o, Mapping):
        return {str(k): _no_nan(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_no_nan(v) for v in o]
    return o


def summary(doc: str | None) -> str:
    """The first paragraph of a docstring, on one line."""
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def write_results(name: str, figures: Mapping[str, Any], *, params: Mapping[str, Any] | None = None,
                  goals: Iterable[Goal] = (), tables: Iterable[Table] = (), notes: str = "",
                  description: str | None = None, out: Path | None = None) -> Path:  # fmt: skip
    """Write ``benchmarks/results/<name>.json`` (or ``out``) and return its path. ``figures`` and
    ``params`` may hold numpy values and paths; NaN and infinity are written as null.
    ``description`` (what the benchmark measures) defaults to the first paragraph of the running
    script's docstring."""
    figures = json.loads(json.dumps(figures, default=_plain))
    if description is None:
        description = summary(getattr(sys.modules.get("__main__"), "__doc__", None))
    script = Path(sys.argv[0]).resolve()
    doc = {
        "name": name,
        "script": script.relative_to(ROOT).as_posix() if script.is_relative_to(ROOT) else sys.argv[0],
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "description": description,
        "date": _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat(),
        "commit": commit(),
        "machine": machine(),
        "params": json.loads(json.dumps(dict(params or {}), default=_plain)),
        "figures": figures,
        "goals": [g.check(figures) for g in goals],
        "tables": [t.as_dict() for t in tables],
        "notes": notes,
    }
    path = out or RESULTS_DIR / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_no_nan(doc), indent=1, allow_nan=False) + "\n")
    return path
