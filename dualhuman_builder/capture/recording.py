"""Recording a take from Python or the CLI: which sources, who wears what, where the take goes.

:func:`plan_capture` turns a rig file or ad-hoc ``--source`` / ``--actor`` arguments into the
sources to open and the actor bindings; :func:`capture_take` opens them, records a take
(:class:`~dualhuman_builder.capture.recorder.Recorder`) and registers it in a workspace catalog
with its checksum. A URL that stands for a whole studio (``sim://``,
:attr:`~dualhuman_builder.capture.sources.Source.PLAYS_STUDIO`) is recorded through real loopback
transports (its source's :meth:`~dualhuman_builder.capture.sources.Source.loopback_studio`).

Ad-hoc arguments:

* ``--source [NAME=]URL`` (repeatable); NAME defaults to the scheme's kind and a number
  (``mvn1``). A UDP URL with no host listens on 127.0.0.1 only.
* ``--actor NAME=SOURCE#CHARACTER`` binds an actor to an MVN character of a source (NAME of
  the source, or its URL).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence
from urllib.parse import urlsplit

from dualhuman_builder.capture.recorder import LiveStatus, Recorder, TakeResult
from dualhuman_builder.capture.sources import Source, SourceError, open_source, registered_sources, source_class
from dualhuman_builder.rig import RigActor, load_rig


@dataclass
class CapturePlan:
    """``sources``: ``[(name, url)]``; ``actors``: bindings; ``rig_name`` / ``rig_text`` / ``rig_path``
    when from a rig file; ``simulated``: the one URL of a studio to play (``sim://``), if that is
    what is recorded."""

    sources: list[tuple[str, str]]
    actors: list[RigActor] = field(default_factory=list)
    rig_name: str | None = None
    rig_text: str | None = None
    rig_path: Path | None = None
    simulated: str | None = None


_KIND = {"mvn+udp": "mvn", "vive+udp": "vive", "xbus": "xbus", "mti+can": "can", "vive+usb": "viveusb"}


def _plays_studio(url: str) -> bool:
    return source_class(url).PLAYS_STUDIO


def plan_capture(rig: str | Path | None = None, sources: Sequence[str] = (), actors: Sequence[str] = ()) -> CapturePlan:
    """What to open: the rig's sources and actors, or the ad-hoc ones (not both)."""
    if rig is not None:
        if sources or actors:
            raise SourceError("give either --rig or --source/--actor, not both",
                              fix="put ad-hoc sources in a rig file, or drop --rig")  # fmt: skip
        r = load_rig(rig)
        sims = [s.url for s in r.sources if _plays_studio(s.url)]
        return CapturePlan([(s.name, s.url) for s in r.sources], list(r.actors), r.name, r.text, Path(rig),
                           sims[0] if sims else None)  # fmt: skip
    if not sources:
        raise SourceError("nothing to record", fix="give --rig RIG.toml or --source URL (e.g. --source 'sim://handshake?seed=3')")
    named: list[tuple[str, str]] = []
    counts: dict[str, int] = {}
    for text in sources:
        name, eq, url = text.partition("=")
        if not eq or "://" in name:
            name, url = "", text
        scheme = urlsplit(url).scheme
        known = registered_sources()
        if scheme not in known:
            raise SourceError(f"unknown source scheme in {text!r}", fix=f"use one of {', '.join(s + '://' for s in known)}")
        if not name:
            counts[scheme] = counts.get(scheme, 0) + 1
            name = f"{_KIND.get(scheme, scheme)}{counts[scheme]}"
        if any(n == name for n, _ in named):
            raise SourceError(f"source name {name!r} is used twice", fix="name sources NAME=URL")
        named.append((name, url))
    sims = [u for _, u in named if _plays_studio(u)]
    if sims and len(named) > 1:
        raise SourceError(f"{sims[0]} plays a whole simulated studio and cannot be mixed with other sources",
                          fix="record it on its own")  # fmt: skip
    bound = []
    for text in actors:
        m = re.fullmatch(r"([^=]+)=(.+)#(\d+)", text)
        if not m:
            raise SourceError(f"--actor {text!r} is not NAME=SOURCE#CHARACTER", fix="e.g. --actor alice=mvn1#0")
        actor, src, char = m.group(1), m.group(2), int(m.group(3))
        match = [n for n, u in named if src in (n, u)]
        if not match:
            raise SourceError(f"--actor {text!r}: no source named {src!r}", fix=f"use one of {[n for n, _ in named]}")
        bound.append(RigActor(actor, match[0], char, {}))
    return CapturePlan(named, bound, simulated=sims[0] if sims else None)


def default_take_path(workspace: str | Path, take: str) -> Path:
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        return ws.take_dir(take) / f"{take}.mcap"


def capture_take(plan: CapturePlan, out: str | Path, *, take: str, duration: float | None = None,
                 workspace: str | Path | None = None, on_status: Callable[[LiveStatus], None] | None = None,
                 progress: Callable[[str], None] | None = None, sim_speed: float = 1.0, sim_faults=None,
                 foxglove_hz: float = 60.0) -> TakeResult:  # fmt: skip
    """Open the plan's sources, record until ``duration`` (a simulated studio: until it has played),
    close, and register the take in ``workspace`` when given. Returns the :class:`TakeResult`;
    a failure mid-take (device lost, disk full) is in ``result.error`` with the file kept."""
    studio = None
    opened: list[tuple[str, Source]] = []
    try:
        if plan.simulated is not None:
            studio = source_class(plan.simulated).loopback_studio(plan.simulated, speed=sim_speed, faults=sim_faults,
                                                                    progress=progress)  # fmt: skip
            opened, actors, rig_text = studio.sources, studio.actors, studio.rig_text
            until = studio.finished
        else:
            for name, url in plan.sources:
                if progress:
                    progress(f"opening {name}: {url}")
                opened.append((name, open_source(url)))
            actors, rig_text, until = plan.actors, plan.rig_text, None
        recorder = Recorder(out, take=take, sources=opened, actors=actors, rig_text=rig_text, foxglove_hz=foxglove_hz,
                            extra_meta={"rig_name": plan.rig_name or "", "simulated": plan.simulated or ""})  # fmt: skip
        result = recorder.run(duration, until=until, on_status=on_status)
    finally:
        if studio is not None:
            studio.close()
        else:
            for _, src in opened:
                src.close()
    if workspace is not None:
        from dualhuman_builder.errors import DualhumanError

        try:
            register_take(workspace, result, plan, actors)
        except DualhumanError as e:
            raise DualhumanError(f"the take was recorded to {result.path} but could not be registered: {e.message}",
                                 fix=e.fix) from e  # fmt: skip
    return result


def register_take(workspace: str | Path, result: TakeResult, plan: CapturePlan, actors: Sequence[RigActor]) -> None:
    """Add the take to the catalog: its file with SHA-256, rig (registered if new), the actors the
    workspace knows (others are listed in the take's meta), sample counts, how it ended."""
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        rig_name = None
        if plan.rig_path is not None:
            known = dict(ws.rigs())
            rig_name = plan.rig_name if plan.rig_name in known else ws.add_rig(plan.rig_path)
        names = [a.name for a in actors]
        registered = {a.name for a in ws.actors()}
        ws.add_take(result.take, rig=rig_name, actors=[n for n in names if n in registered], files=[result.path],
                    start_time=result.start_utc, duration_s=result.duration_s,
                    sample_counts=dict(result.samples_per_topic),
                    meta={"reason": result.reason, "error": result.error, "simulated": plan.simulated,
                          "actors": names, "unregistered_actors": [n for n in names if n not in registered],
                          "sources": {n: s for n, s in result.source_stats.items()}})  # fmt: skip
