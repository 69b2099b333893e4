"""The generated benchmark pages match the committed results files (no figure typed by hand)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_docs_are_generated_from_the_results():
    r = subprocess.run([sys.executable, "benchmarks/make_docs.py", "--check"], cwd=REPO, capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 0, "docs/benchmarks.md or docs/accuracy.md is stale: run benchmarks/make_docs.py\n" + r.stdout


def test_every_results_file_says_where_and_against_what_it_was_measured():
    files = sorted((REPO / "benchmarks" / "results").glob("*.json"))
    assert files, "no committed results"
    for path in files:
        doc = json.loads(path.read_text())
        assert doc["name"] == path.stem
        for key in ("script", "command", "date", "commit", "machine", "figures", "goals"):
            assert key in doc, f"{path.name} lacks {key}"
        assert doc["machine"].get("cpu") and doc["machine"].get("cores"), path.name
        assert (REPO / doc["script"]).is_file(), f"{path.name}: {doc['script']} is not in the repository"
        for goal in doc["goals"]:
            assert goal["op"] in ("<=", ">=") and "met" in goal, (path.name, goal)
