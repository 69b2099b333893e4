"""The ``capture`` workspace stage: record a sequence's sources into the workspace as an artifact
(idempotent, crash-safe: see :mod:`dualhuman_builder.workspace.runner`).

``dualhuman capture -w WS --take T`` records a live studio and registers the file with the take;
this stage is the same recording made reproducible as a stage of a sequence: the sources (any
source URL, typically a simulated studio played on loopback transports, ``sim://SCENE.npz``) are
recorded with :func:`~dualhuman_builder.capture.recording.capture_take`, the file is checked
(:func:`~dualhuman_builder.capture.log.reader.check_take`) and its raw packets re-decoded to prove
they give the recorded samples bit for bit (:func:`~dualhuman_builder.capture.replay.verify_replay`).

Artifacts (under ``WS/artifacts/TAKE/SEQUENCE/capture/``): ``take.mcap`` and ``capture.json``
(samples per topic, losses per source, events, the check and the replay verdict).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Sequence

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.workspace.runner import Stage

TAKE_FILE, REPORT_FILE = "take.mcap", "capture.json"
CAPTURE = Stage("capture", per="sequence", artifacts=(TAKE_FILE, REPORT_FILE),
                command="dualhuman sim take {ws} --take {take}")  # fmt: skip


def record_take(url: str, take_path: Path, *, take: str, speed: float = 1.0, log: Callable[[str], None] = print) -> dict:
    """Record the source ``url`` into ``take_path`` (a studio URL such as ``sim://`` plays at
    ``speed`` times real time), check the file, and check that re-decoding its raw packets gives
    the recorded samples bit for bit. Returns the summary written to ``capture.json``; raises
    :class:`~dualhuman_builder.errors.DualhumanError` when the recording failed."""
    from dualhuman_builder.capture.log.reader import check_take
    from dualhuman_builder.capture.replay import verify_replay
    from dualhuman_builder.capture.recording import capture_take, plan_capture

    log(f"recording {url} ({speed:g}x real time)...")
    res = capture_take(plan_capture(sources=[url]), take_path, take=take, sim_speed=speed, progress=log)
    if res.error:
        raise DualhumanError(f"the capture of {take} failed: {res.error}")
    check = check_take(take_path)
    replay = verify_replay(take_path)
    lost = {name: int(sum(st.get(k, 0) for k in ("lost", "kernel_drops", "incomplete")))
            for name, st in res.source_stats.items()}  # fmt: skip
    log(f"take: {sum(res.samples_per_topic.values())} samples, {check.messages} messages, lost {lost}, "
        f"replay {'bit-identical' if replay.identical else 'DIFFERS'}")  # fmt: skip
    return {"samples": sum(res.samples_per_topic.values()), "per_topic": dict(res.samples_per_topic), "lost": lost,
            "sources": res.source_stats, "events": res.events, "messages": check.messages, "complete": check.ok,
            "replay_identical": replay.identical, "seconds": round(res.duration_s, 2)}  # fmt: skip


def run_capture(ws, take: str, sequence: str, url: str, *, speed: float = 1.0, params: dict | None = None,
                depends_on: Sequence[tuple[str, str | None]] = (), force: bool = False,
                log: Callable[[str], None] = print):  # fmt: skip
    """The ``capture`` stage of ``take``/``sequence``: :func:`record_take` of ``url`` into the
    stage's ``take.mcap``. ``params`` (default: the URL and speed) and ``depends_on`` (e.g. the
    ``scene`` stage a ``sim://`` URL plays) decide when it is stale. Returns the StageResult."""

    def compute(out):
        summary = record_take(url, out.path(TAKE_FILE), take=take, speed=speed, log=log)
        out.path(REPORT_FILE).write_text(json.dumps(summary, indent=2))
        return {k: summary[k] for k in ("samples", "lost", "replay_identical")}

    return ws.run_stage("capture", compute, take=take, sequence=sequence,
                        params=params if params is not None else {"url": url, "speed": speed},
                        depends_on=depends_on, force=force)  # fmt: skip
