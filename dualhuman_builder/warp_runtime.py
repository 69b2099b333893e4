"""Starting warp (NVIDIA's kernel compiler) the same way everywhere in the toolkit.

warp's native library writes ``Warp CUDA warning: Could not find or load the NVIDIA CUDA driver.
GPU execution will not be available.`` to the process's standard error (file descriptor 2, from C,
so no Python setting reaches it) each time it starts on a machine without an NVIDIA driver, and
warp's Python side logs a start-up banner. :func:`init_warp` starts warp with the banner off and,
only where no NVIDIA driver library loads, without that one line; anything else warp writes while
starting still reaches standard error. Call it before anything imports anny, whose skinning
module starts warp as it is imported.

Imports nothing of the toolkit: the body model, the geometry kernels and the stages all use it.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys
import tempfile
import threading
from collections.abc import Iterator

#: The line warp's native library prints when it finds no NVIDIA driver (``native/cuda_util.cpp``).
CUDA_DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"

_lock = threading.Lock()
_started = False


@functools.lru_cache(maxsize=1)
def cuda_driver_problem() -> str | None:
    """Why warp can reach no NVIDIA driver on this machine, e.g. ``"no NVIDIA driver
    (libcuda.so.1 not found)"``; None where the driver library loads (warp then reports
    its devices, or its own errors, as usual)."""
    if sys.platform.startswith("linux"):
        names = ("libcuda.so", "libcuda.so.1")
    elif sys.platform == "win32":
        names = ("nvcuda.dll",)
    else:
        return "warp has no CUDA support on this platform"
    for name in names:
        try:
            ctypes.CDLL(name)
            return None
        except OSError:
            continue
    return f"no NVIDIA driver ({names[-1]} not found)"


def init_warp():
    """Start warp once per process and return the ``warp`` module; later calls return at once.

    Sets ``warp.config.log_level`` to at least warnings (no banner, no per-module load lines).
    On a machine without an NVIDIA driver, the native CUDA-driver warning is dropped; every other
    line warp prints while starting is passed on to standard error, and errors are raised as usual.
    """
    global _started
    import warp as wp

    with _lock:
        if not _started:
            wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
            if cuda_driver_problem() is None:
                wp.init()
            else:
                with stderr_without(CUDA_DRIVER_WARNING):
                    wp.init()
            _started = True
    return wp


@contextlib.contextmanager
def stderr_without(text: str) -> Iterator[None]:
    """Hold back what is written to file descriptor 2 (by Python or by C) inside the block, then
    write it out without the lines that contain ``text``. Does nothing where fd 2 is closed."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        finally:
            with contextlib.suppress(Exception):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            kept = [line for line in held.read().splitlines(keepends=True) if text.encode() not in line]
            out = b"".join(kept)
            while out:
                out = out[os.write(2, out):]
