"""`dualhuman run`: every pending stage of every take of a workspace, on local processes or Ray."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main

#: How each outcome shows in the summary table: (word, colour).
OUTCOME_STYLE = {"done": ("done", "dim green"), "ran": ("ran", "green"), "failed": ("failed", "bold red"),
                 "skipped": ("skipped", "yellow"), "pending": ("not reached", "magenta")}  # fmt: skip


def _stage_list(ctx, param, value: str | None):
    if not value:
        return None
    return tuple(s.strip() for s in value.split(",") if s.strip())


@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--take", "takes", multiple=True, metavar="TAKE", help="Only this take (repeat for more; default: every take).")
@click.option("--until", default=None, metavar="STAGE", help="Stop after this stage (e.g. fuse, fit).")
@click.option("--stages", default=None, callback=_stage_list, metavar="A,B", help="Only these stages, e.g. sync,fuse.")
@click.option("--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True,
              help="local: worker processes on this machine; ray: tasks on a Ray cluster (pip install "
                   "'dualhuman-builder[ray]').")
@click.option("--address", default=None, metavar="HOST:PORT",
              help="With --executor ray: the cluster's head (`ray start --head` prints it; 'auto' on a node of it). "
                   "Default: a Ray cluster started on this machine for the run.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Tasks at once. Default: local, one per CPU within the available memory at 2 GiB each; ray, the "
                   "cluster's CPUs.")
@click.option("--retries", type=click.IntRange(min=0, max=10), default=1, show_default=True,
              help="Tries after the first for a stage that fails or whose worker dies.")
@click.option("--fps", type=click.FloatRange(min=1.0, max=1000.0), default=None,
              help="Frame rate of the common timeline for sync, fuse and fit (default: the stages' 30).")
@click.option("--mounts-from", "mounts_from", default=None, metavar="TAKE",
              help="The studio day's calibration take: synced first, its tracker mounts and lags used by the others.")
def run(workspace: Path, takes: tuple[str, ...], until: str | None, stages: tuple[str, ...] | None, executor: str,
        address: str | None, workers: int | None, retries: int, fps: float | None, mounts_from: str | None):  # fmt: skip
    """Run every pending stage of every take, in pipeline order, skipping what is done.

    Stages use their defaults (their own commands take more options). A stage that fails is tried
    again (--retries), then recorded failed with its error and the take's later stages skipped; the
    other takes go on. Stop it with Ctrl-C and run it again to resume: only results the catalog
    records done are skipped. One run per workspace at a time (a second one refuses). Exits 1 when
    a stage failed.

    \b
    Examples:
      dualhuman run WS
      dualhuman run WS --until fit --take T001 --take T002
      dualhuman run WS --executor ray --address 10.0.0.5:6379
    """
    from dualhuman_builder.batch import RunOptions, run_workspace

    if address is not None and executor != "ray":
        raise click.BadParameter("--address is for --executor ray", param_hint="--address")
    options = RunOptions(takes=takes or None, until=until, stages=stages, fps=fps, mounts_from=mounts_from,
                         retries=retries, workers=workers)  # fmt: skip
    display = _Display()
    try:
        with display:
            summary = run_workspace(workspace, options, executor=executor, address=address, on_event=display.event)
    except KeyboardInterrupt as e:
        summary = getattr(e, "summary", None)
        if summary is not None:
            _print_summary(summary)
        console.print("[magenta]interrupted[/]: run the same command again to resume", highlight=False)
        sys.exit(130)
    _print_summary(summary)
    if summary.failed:
        sys.exit(1)


class _Display:
    """One progress display across takes and stages: a rich bar and the running tasks' latest lines
    on a terminal, one plain line per started and finished stage otherwise."""

    def __init__(self):
        self.live = console.is_terminal
        self.progress = None
        self.bar = None
        self.total = 0
        self.finished = 0
        self.lines: dict[tuple[str, str], str] = {}

    def __enter__(self):
        if self.live:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), console=console, transient=True)  # fmt: skip
            self.progress.__enter__()
        return self

    def __exit__(self, *exc):
        if self.progress is not None:
            self.progress.__exit__(*exc)

    def _say(self, text: str) -> None:
        from rich.markup import escape

        if self.progress is not None:
            self.progress.console.print(escape(text), highlight=False, soft_wrap=True)
        else:
            console.print(escape(text), highlight=False, soft_wrap=True)

    def _refresh(self) -> None:
        if self.progress is None or self.bar is None:
            return
        running = ", ".join(f"{t} {s}" for t, s in list(self.lines)[:4]) or "waiting"
        self.progress.update(self.bar, completed=self.finished, description=f"stages ({running})")

    def event(self, kind: str, take, stage, info) -> None:
        from dualhuman_builder.workspace.workspace import printable

        where = f"{printable(take)} {stage}" if take else ""
        if kind == "plan":
            self.total = len(info.tasks)
            self._say(f"{self.total} stages to run over {len(info.takes)} takes ({len(info.done)} done already)")
            if self.progress is not None:
                self.bar = self.progress.add_task("stages", total=self.total)
        elif kind == "start":
            self.lines[(take, stage)] = ""
            if not self.live:
                self._say(f"{where}: started" + (f" (try {info})" if info > 1 else ""))
        elif kind == "retry":
            self.lines.pop((take, stage), None)
            self._say(f"{where}: failed, trying again: {printable(str(info))}")
        elif kind == "end":
            self.lines.pop((take, stage), None)
            self.finished += 1
            word = {"ran": "done", "failed": "FAILED", "skipped": "skipped"}.get(info.state, info.state)
            why = f": {printable(info.error)}" if info.error else ""
            secs = f" ({info.seconds:.1f} s)" if info.state == "ran" else ""
            self._say(f"[{self.finished}/{self.total}] {where}: {word}{secs}{why}")
        self._refresh()


def _print_summary(summary) -> None:
    """The table take x stage (done before / ran / failed / skipped), then the errors and reasons."""
    from rich.table import Table

    from dualhuman_builder.workspace.workspace import printable

    table = Table(title=f"run: {summary.executor} executor, {summary.workers} workers, {summary.seconds:.0f} s",
                  title_justify="left")  # fmt: skip
    table.add_column("take")
    stages = [s for s in summary.stages if any(k[1] == s for k in summary.outcomes)]
    for s in stages:
        table.add_column(s)
    notes = []
    for take in summary.takes:
        cells = []
        for s in stages:
            out = summary.outcomes.get((take, s))
            if out is None:
                cells.append("")
                continue
            word, style = OUTCOME_STYLE[out.state]
            tries = f" ×{out.tries}" if out.tries > 1 else ""
            cells.append(f"[{style}]{word}{tries}[/]")
            if out.state in ("failed", "skipped") and out.error:
                notes.append((out.state, f"{take} {s}", out.error))
        table.add_row(printable(take), *cells)
    console.print(table)
    from rich.markup import escape

    for state, where, why in notes:
        if state == "failed" or "failed" in why:
            colour = "red" if state == "failed" else "yellow"
            console.print(f"[{colour}]{state}[/] {escape(printable(where))}: {escape(printable(why))}", highlight=False,
                          soft_wrap=True)  # fmt: skip
    counts = {s: summary.count(s) for s in OUTCOME_STYLE}
    console.print(f"ran {counts['ran']}, done before {counts['done']}, failed {counts['failed']}, "
                  f"skipped {counts['skipped']}" + (f", not reached {counts['pending']}" if counts["pending"] else ""),
                  highlight=False)  # fmt: skip
