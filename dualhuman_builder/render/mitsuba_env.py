"""Which Mitsuba 3 variant renders on this machine, found by rendering, not by guessing.

Variants the toolkit uses, fastest first: ``cuda_ad_rgb`` (NVIDIA GPU and driver), ``llvm_ad_rgb``
(CPU JIT through a system ``libLLVM``), ``scalar_rgb`` (no JIT, slow, always works).

``llvm_ad_rgb`` needs a libLLVM **newer than 15**. Dr.Jit loads it at run time from
``DRJIT_LIBLLVM_PATH`` (or its own search); LLVM 15 (Debian 12's default) *aborts the process*
("LLVM ERROR: Cannot select ... fminimum") instead of raising. So:

- :func:`configure_llvm` points ``DRJIT_LIBLLVM_PATH`` at a good libLLVM; call it before the
  first ``import drjit`` / ``import mitsuba`` of the process.
- :func:`probe_variant` renders a tiny scene in a child process
  (``python -m dualhuman_builder.render.mitsuba_env --probe VARIANT``), so an abort kills the
  child and is reported, never the caller.
- :func:`pick_variant` returns the first preferred variant whose probe renders, once per process.

This module imports neither drjit nor mitsuba at import time.
"""

from __future__ import annotations

import ctypes
import json
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from dualhuman_builder.errors import DualhumanError

#: Environment variable Dr.Jit reads to find libLLVM.
LLVM_ENV = "DRJIT_LIBLLVM_PATH"


def _llvm_candidates() -> tuple[str, ...]:
    versions = (19, 20, 18, 17, 16)  # Debian 12's libllvm19 first: the tested one
    machine = platform.machine().lower()
    arches = ["x86_64", "aarch64"] if machine not in ("aarch64", "arm64") else ["aarch64", "x86_64"]
    paths: list[str] = []
    for v in versions:
        for arch in arches:  # Debian / Ubuntu multiarch layout (libllvmN packages)
            d = f"/usr/lib/{arch}-linux-gnu"
            paths += [f"{d}/libLLVM.so.{v}.1", f"{d}/libLLVM-{v}.so", f"{d}/libLLVM-{v}.so.1"]
        paths += [f"/usr/lib/llvm-{v}/lib/libLLVM.so.{v}.1", f"/usr/lib/llvm-{v}/lib/libLLVM-{v}.so"]
        paths += [f"/usr/lib64/libLLVM.so.{v}.1", f"/usr/lib64/libLLVM-{v}.so"]  # Fedora / RHEL
    return tuple(paths)


#: libLLVM shared libraries newer than LLVM 15 to try, best first (native architecture first).
LLVM_CANDIDATES: tuple[str, ...] = _llvm_candidates()

#: Variants tried by :func:`pick_variant`, fastest first.
PREFERRED_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")

#: Size (pixels) and samples per pixel of the probe render.
PROBE_RESOLUTION = 32
PROBE_SPP = 4


def find_llvm() -> str | None:
    """Path of the first existing :data:`LLVM_CANDIDATES` entry, or None."""
    for path in LLVM_CANDIDATES:
        if os.path.exists(path):
            return path
    return None


def configure_llvm() -> str | None:
    """Make Dr.Jit load a libLLVM newer than 15; returns the path it will use (None: none found).

    A ``DRJIT_LIBLLVM_PATH`` already set by the user is kept as is. Otherwise it is set to the
    first existing :data:`LLVM_CANDIDATES` entry. Takes effect only when called **before** drjit
    or mitsuba is first imported in this process (Dr.Jit reads the variable when its LLVM backend
    starts); in a process that already imported them, it only affects child processes.
    """
    global _llvm_set_here
    current = os.environ.get(LLVM_ENV)
    if current:
        return current
    path = find_llvm()
    if path is not None:
        os.environ[LLVM_ENV] = path
        _llvm_set_here = path
    return path


_llvm_set_here: str | None = None


def llvm_path_from_user() -> bool:
    """True when ``DRJIT_LIBLLVM_PATH`` was set by the user, not by :func:`configure_llvm`."""
    value = os.environ.get(LLVM_ENV)
    return bool(value) and value != _llvm_set_here


def nvidia_gpus() -> tuple[int, str]:
    """``(number of CUDA devices, detail)`` from the NVIDIA driver itself (``libcuda.so.1``).

    Zero with the reason when there is no driver library or no device; imports no framework.
    """
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return 0, "no NVIDIA driver (libcuda.so.1 not found)"
    rc = cuda.cuInit(0)
    if rc != 0:
        reason = {100: "no CUDA-capable device", 999: "unknown error", 3: "not initialized"}.get(rc, "")
        return 0, f"NVIDIA driver present but cuInit failed with error {rc} {reason}".rstrip()
    count = ctypes.c_int(0)
    version = ctypes.c_int(0)
    cuda.cuDeviceGetCount(ctypes.byref(count))
    cuda.cuDriverGetVersion(ctypes.byref(version))
    v = version.value
    return count.value, f"{count.value} CUDA device(s), driver CUDA API {v // 1000}.{v % 1000 // 10}"


@dataclass
class VariantProbe:
    """Outcome of rendering the probe scene with one variant.

    ``seconds``: time to select the variant, load and render the scene in the child process
    (JIT compilation included), or the child's wall time when it failed. ``llvm_path``: the
    libLLVM the child was given (LLVM variants only).
    """

    variant: str
    ok: bool
    seconds: float
    detail: str
    llvm_path: str | None = None


def _probe_scene(mi) -> dict:
    """A diffuse unit sphere under a constant emitter seen by a 32x32 pinhole camera."""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {
            "type": "perspective",
            "fov": 45.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {
                "type": "hdrfilm",
                "width": PROBE_RESOLUTION,
                "height": PROBE_RESOLUTION,
                "rfilter": {"type": "box"},
            },
            "sampler": {"type": "independent", "sample_count": PROBE_SPP},
        },
        "sphere": {"type": "sphere", "bsdf": {"type": "diffuse"}},
        "light": {"type": "constant"},
    }


def _probe_in_this_process(variant: str) -> dict:
    """Render the probe scene here; returns the JSON-able result. May abort the process (LLVM)."""
    t0 = time.perf_counter()
    import mitsuba as mi
    import numpy as np

    if variant not in mi.variants():
        return {
            "ok": False,
            "detail": f"variant {variant} is not compiled into this mitsuba {mi.__version__} wheel "
            f"(it has: {', '.join(mi.variants())})",
        }
    try:
        mi.set_variant(variant)
        image = np.asarray(mi.render(mi.load_dict(_probe_scene(mi)), seed=0), dtype=np.float64)
    except Exception as e:  # Dr.Jit reports backend problems as ImportError/RuntimeError
        return {"ok": False, "detail": _explain(variant, f"{type(e).__name__}: {e}")}
    seconds = time.perf_counter() - t0
    n = PROBE_RESOLUTION
    if image.shape[:2] != (n, n):
        return {"ok": False, "seconds": seconds, "detail": f"rendered image has shape {image.shape}, expected ({n}, {n}, 3)"}
    if not np.isfinite(image).all():
        bad = int((~np.isfinite(image)).sum())
        return {"ok": False, "seconds": seconds, "detail": f"rendered image has {bad} non-finite values"}
    if not (image > 0).any():
        return {"ok": False, "seconds": seconds, "detail": "rendered image is all zero"}
    return {
        "ok": True,
        "seconds": seconds,
        "detail": f"{n}x{n} at {PROBE_SPP} spp in {seconds:.2f} s incl. import and JIT (mean {image.mean():.3f})",
    }


def _explain(variant: str, message: str) -> str:
    text = " ".join(message.split())
    if "CUDA" in text and ("initialized" in text or "driver" in text.lower()):
        return f"no usable CUDA driver/GPU for {variant} ({text})"
    return text


def _child_env(llvm_path: str | None) -> dict[str, str]:
    from dualhuman_builder.children import child_env

    return child_env({LLVM_ENV: llvm_path} if llvm_path is not None else None)


def _tail(text: str, lines: int = 3) -> str:
    kept = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return " | ".join(kept[-lines:])


def _stderr_reason(stderr: str, limit: int = 160) -> str:
    """The telling line of a child's stderr: an ``LLVM ERROR`` or Dr.Jit's load error, else the tail."""
    for marker in ("LLVM ERROR", "jit_find_library()", "Critical Dr.Jit compiler failure"):
        for line in stderr.splitlines():
            if marker in line:
                line = " ".join(line.split())
                return line if len(line) <= limit else line[: limit - 3] + "..."
    return _tail(stderr)


def _llvm_failure(llvm_path: str, stderr: str) -> str:
    missing = "" if os.path.exists(llvm_path) else " (no such file)"
    return f"libLLVM could not be loaded from {llvm_path}{missing}: {_stderr_reason(stderr)}"


def probe_variant(variant: str, timeout: float = 180) -> VariantProbe:
    """Render a 32x32, 4 spp sphere with ``variant`` in a child process and check the image.

    ``ok`` only when the image is finite and not all zero. On failure ``detail`` says why: the
    variant is not compiled into the wheel, no CUDA driver/GPU, libLLVM missing, the child was
    killed by a signal (with its last stderr lines, e.g. LLVM 15's "Cannot select"), or the
    ``timeout`` (seconds) ran out. The child gets ``DRJIT_LIBLLVM_PATH`` as :func:`configure_llvm`
    would choose it; this process's environment is left unchanged.
    """
    is_llvm = variant.startswith("llvm_")
    llvm_path = (os.environ.get(LLVM_ENV) or find_llvm()) if is_llvm else None
    if variant.startswith("cuda_"):
        count, why = nvidia_gpus()
        if count == 0:
            return VariantProbe(variant, False, 0.0, why)
    if is_llvm and llvm_path is None:
        return VariantProbe(
            variant, False, 0.0, f"no libLLVM newer than 15 found (looked for {LLVM_CANDIDATES[0]} and others)"
        )
    cmd = [sys.executable, "-m", "dualhuman_builder.render.mitsuba_env", "--probe", variant]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            cmd, env=_child_env(llvm_path), capture_output=True, text=True, timeout=timeout, check=False
        )
    except subprocess.TimeoutExpired:
        return VariantProbe(variant, False, time.perf_counter() - t0, f"probe timed out after {timeout:g} s", llvm_path)
    wall = time.perf_counter() - t0
    result = None
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("{"):
            try:
                result = json.loads(line)
            except json.JSONDecodeError:
                continue
            break
    if result is not None:
        detail = result["detail"]
        if not result["ok"] and is_llvm and "LLVM backend is inactive" in detail:
            detail = _llvm_failure(llvm_path, proc.stderr)
        return VariantProbe(variant, bool(result["ok"]), float(result.get("seconds", wall)), detail, llvm_path)
    if proc.returncode < 0:
        try:
            sig = signal.Signals(-proc.returncode).name
        except ValueError:
            sig = f"signal {-proc.returncode}"
        detail = f"probe process killed by {sig}"
    else:
        detail = f"probe process exited with status {proc.returncode} without a result"
    if is_llvm:
        detail += f" with libLLVM {llvm_path} (LLVM 15 or older aborts Dr.Jit)"
    reason = _stderr_reason(proc.stderr)
    if reason:
        detail += f": {reason}"
    return VariantProbe(variant, False, wall, detail, llvm_path)


_picked: dict[tuple[str, ...], str] = {}
_pick_lock = threading.Lock()


def pick_variant(preferred: tuple[str, ...] | list[str] = PREFERRED_VARIANTS) -> str:
    """The first of ``preferred`` whose probe renders; probed once per process and cached.

    Also calls :func:`configure_llvm`, so an in-process ``mi.set_variant`` of the returned
    variant uses the libLLVM the probe used. Raises :class:`DualhumanError` listing each
    variant's failure when none renders.
    """
    key = tuple(preferred)
    with _pick_lock:
        if key in _picked:
            return _picked[key]
        configure_llvm()
        failures = []
        for variant in key:
            probe = probe_variant(variant)
            if probe.ok:
                _picked[key] = variant
                return variant
            failures.append(f"{variant}: {probe.detail}")
        raise DualhumanError(
            "no Mitsuba variant renders on this machine (" + "; ".join(failures) + ")",
            fix="run `dualhuman doctor`; scripts/setup.sh installs mitsuba and libllvm19",
        )


def _main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] != "--probe":
        print("usage: python -m dualhuman_builder.render.mitsuba_env --probe VARIANT", file=sys.stderr)
        return 2
    result = _probe_in_this_process(argv[1])
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
