"""Child processes of the toolkit (``python -m dualhuman_builder...`` workers): their environment,
and a scratch folder that goes away with them.

Workers are fresh interpreters started with :mod:`subprocess` rather than :mod:`multiprocessing`:
no fork of a process holding torch's and warp's threads, and no re-import of the caller's
``__main__``, so scripts without a ``__main__`` guard work.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Iterator



#: The folder that holds the ``dualhuman_builder`` package imported now (a checkout, or site-packages).
PACKAGE_PARENT = Path(__file__).resolve().parents[1]


def cpu_count() -> int:
    """The CPUs this process may run on (its affinity mask on Linux)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def available_memory() -> int | None:
    """``MemAvailable`` of /proc/meminfo in bytes: what new processes may use without swapping (None where
    there is no such file)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment for a ``python -m dualhuman_builder...`` child, with the folder of
    the package imported now first on ``PYTHONPATH`` (so the child imports the same code), plus ``extra``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(PACKAGE_PARENT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra or {})
    return env


@contextlib.contextmanager
def scratch_with_children(prefix: str) -> Iterator[tuple[Path, list[subprocess.Popen]]]:
    """A temporary folder and a list to put the started children in: on leaving (also on failure),
    every child still running is killed and the folder removed."""
    tmp = Path(tempfile.mkdtemp(prefix=prefix))
    procs: list[subprocess.Popen] = []
    try:
        yield tmp, procs
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        shutil.rmtree(tmp, ignore_errors=True)
