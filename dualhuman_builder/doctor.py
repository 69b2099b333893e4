"""``dualhuman doctor``: what works on this machine, tried for real, and how to fix what does not.

Each :class:`Check` runs the thing it reports on (a Mitsuba render per variant, a libigl signed
distance query with a known answer, a warp BVH query, an SQLite WAL database, the capture
transports' round trips) rather than only importing it. A failing check with ``required=True``
means the pipeline cannot run here (:func:`exit_code` is then 1); other failures are warnings
about optional speed-ups or hardware paths.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.metadata
import json
import os
import platform
import shutil
import sqlite3
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

#: Allowed values of :attr:`Check.status`.
STATUSES = ("ok", "warn", "fail", "skip")

SETUP_FIX = "scripts/setup.sh"

#: Distributions reported, and whether the pipeline needs them (``dualhuman-builder`` itself may
#: be imported from a source tree without being installed).
PACKAGES: tuple[tuple[str, bool], ...] = (
    ("dualhuman-builder", False),
    ("numpy", True),
    ("scipy", True),
    ("torch", True),
    ("anny", True),
    ("mitsuba", True),
    ("drjit", True),
    ("libigl", True),
    ("warp-lang", True),
    ("trimesh", True),
    ("mcap", True),
    ("python-can", True),
    ("pyserial", True),
    ("pyusb", True),
    ("OpenEXR", True),
    ("click", True),
    ("rich", True),
)

#: Free disk space (bytes) under which the storage check warns.
MIN_FREE_BYTES = 5 * 1024**3


@dataclass
class Check:
    """One line of the report.

    ``status``: one of :data:`STATUSES`; ``fix``: what to run or change (None when ok);
    ``required``: a ``"fail"`` here makes :func:`exit_code` 1.
    """

    group: str
    name: str
    status: str
    detail: str
    fix: str | None = None
    required: bool = False

    def __post_init__(self):
        if self.status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, got {self.status!r}")


def _error(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}"


@contextlib.contextmanager
def _quiet_warp():
    """Silence warp's init banner and module-load messages (they would break a CLI spinner)."""
    try:
        import warp
    except Exception:  # warp missing or broken: reported by its own check
        yield
        return
    level = warp.config.log_level
    warp.config.log_level = max(level, 30)  # warp.LOG_WARNING
    try:
        yield
    finally:
        warp.config.log_level = level


# ----------------------------------------------------------------------------------------- python, packages
def check_python() -> Check:
    """Python >= 3.11 (required)."""
    ok = sys.version_info >= (3, 11)
    return Check(
        "python", "python", "ok" if ok else "fail", f"{platform.python_version()} at {sys.executable}",
        None if ok else "use Python 3.11 or newer (scripts/setup.sh creates .venv with python3)", required=True,
    )


def _requirements() -> dict[str, str]:
    """``{canonical name: specifier}`` of this package's dependencies (installed metadata or pyproject)."""
    try:
        from packaging.requirements import Requirement
        from packaging.utils import canonicalize_name
    except ImportError:
        return {}
    try:
        lines = importlib.metadata.requires("dualhuman-builder") or []
    except importlib.metadata.PackageNotFoundError:
        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        if not pyproject.is_file():
            return {}
        import tomllib

        lines = tomllib.loads(pyproject.read_text()).get("project", {}).get("dependencies", [])
    wanted = {}
    for line in lines:
        req = Requirement(line)
        if req.marker is None or req.marker.evaluate({"extra": ""}):
            wanted[canonicalize_name(req.name)] = str(req.specifier)
    return wanted


def check_packages() -> list[Check]:
    """Installed version of each of :data:`PACKAGES`, against this package's pins where known."""
    wanted = _requirements()
    try:
        from packaging.utils import canonicalize_name
        from packaging.version import InvalidVersion, Version
    except ImportError:
        canonicalize_name = str.lower  # noqa: N806
        Version = None  # noqa: N806
    checks = []
    for dist, required in PACKAGES:
        try:
            version = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            if dist == "dualhuman-builder":
                where = Path(__file__).resolve().parents[1]
                checks.append(Check("packages", dist, "warn", f"not installed; imported from the source tree {where}",
                                    f"{SETUP_FIX} (installs it editable, with the `dualhuman` command)"))
            else:
                checks.append(Check("packages", dist, "fail" if required else "warn", "not installed",
                                    SETUP_FIX, required))
            continue
        spec = wanted.get(canonicalize_name(dist))
        if spec and Version is not None:
            from packaging.specifiers import SpecifierSet

            try:
                fits = SpecifierSet(spec).contains(Version(version), prereleases=True)
            except InvalidVersion:
                fits = True
            if not fits:
                checks.append(Check("packages", dist, "fail" if required else "warn",
                                    f"{version} installed, dualhuman-builder needs {spec}", SETUP_FIX, required))
                continue
        checks.append(Check("packages", dist, "ok", version + (f" (needs {spec})" if spec else ""), None, required))
    return checks


# ----------------------------------------------------------------------------------------- torch
def check_torch() -> list[Check]:
    """torch imports; CUDA devices (absent: skip; a GPU with a CPU-only torch: warn)."""
    try:
        import torch
    except Exception as e:
        return [Check("torch", "torch", "fail", f"cannot import torch ({_error(e)})", SETUP_FIX, True)]
    checks = [Check("torch", "torch", "ok", f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads",
                    required=True)]
    if torch.cuda.is_available():
        n = torch.cuda.device_count()
        names = sorted({torch.cuda.get_device_name(i) for i in range(n)})
        checks.append(Check("torch", "cuda", "ok", f"{n} device(s): {', '.join(names)}; CUDA {torch.version.cuda}"))
        return checks
    from dualhuman_builder.render.mitsuba_env import nvidia_gpus

    gpus, why = nvidia_gpus()
    if gpus and torch.version.cuda is None:
        checks.append(Check("torch", "cuda", "warn", f"{why}, but torch {torch.__version__} is a CPU-only build",
                            "install a CUDA build of torch (https://pytorch.org/get-started/locally/)"))
    elif gpus:
        checks.append(Check("torch", "cuda", "warn", f"{why}, but torch (CUDA {torch.version.cuda}) sees none",
                            "update the NVIDIA driver to one that supports this torch's CUDA version"))
    else:
        checks.append(Check("torch", "cuda", "skip", f"no CUDA device: {why}; torch runs on the CPU"))
    return checks


# ----------------------------------------------------------------------------------------- body model
def _tree_bytes(root: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, f)).st_size
    return total


def check_body_model() -> list[Check]:
    """The anny cache is built (required) and the model loads: seconds, vertex and face counts."""
    from dualhuman_builder.body.model import anny_cache_dir, anny_cache_is_warm, anny_version, get_body_model

    root = anny_cache_dir()
    fix = "dualhuman body warm (builds it, a few minutes once per machine)"
    if not anny_cache_is_warm():
        return [
            Check("body model", "anny cache", "fail", f"not built under {root}", fix, True),
            Check("body model", "anny model", "skip", "not loaded: its cache is not built", None, True),
        ]
    size_mb = _tree_bytes(root) / 1e6
    checks = [Check("body model", "anny cache", "ok", f"{root} ({size_mb:.0f} MB)", required=True)]
    t0 = time.perf_counter()
    try:
        with _quiet_warp():
            model = get_body_model()
    except Exception as e:
        checks.append(Check("body model", "anny model", "fail", f"cannot build the model ({_error(e)})",
                            getattr(e, "fix", None) or f"rm -rf {root} && {fix}", True))
        return checks
    seconds = time.perf_counter() - t0
    checks.append(Check(
        "body model", "anny model", "ok",
        f"anny {anny_version()} loaded in {seconds:.2f} s: {model.num_vertices} vertices, "
        f"{int(model.faces.shape[0])} faces, {model.num_bones} bones",
        required=True,
    ))
    return checks


# ----------------------------------------------------------------------------------------- mitsuba
def check_mitsuba_variant(variant: str, render: bool = True) -> Check:
    """Render the probe scene with ``variant`` (see :func:`~dualhuman_builder.render.mitsuba_env.probe_variant`).

    ``scalar_rgb`` is required; ``llvm_ad_rgb`` warns on failure; ``cuda_ad_rgb`` is skipped where
    there is no NVIDIA driver or GPU and warns on failure otherwise.
    """
    from dualhuman_builder.render.mitsuba_env import (
        LLVM_ENV,
        find_llvm,
        llvm_path_from_user,
        nvidia_gpus,
        probe_variant,
    )

    required = variant == "scalar_rgb"
    if variant.startswith("cuda_"):
        gpus, why = nvidia_gpus()
        if gpus == 0:
            return Check("mitsuba", variant, "skip", why)
    if not render:
        return Check("mitsuba", variant, "skip", "not probed (render checks off)", None, required)
    probe = probe_variant(variant)
    detail = probe.detail
    if probe.llvm_path:
        if probe.llvm_path not in detail:
            detail += f"; libLLVM {probe.llvm_path}"
        if llvm_path_from_user():
            detail += f" (set by your {LLVM_ENV})"
    if probe.ok:
        return Check("mitsuba", variant, "ok", detail, None, required)
    if required:
        return Check("mitsuba", variant, "fail", detail, f"{SETUP_FIX} (reinstalls mitsuba and drjit)", True)
    if variant.startswith("llvm_"):
        if llvm_path_from_user():
            good = find_llvm() or "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
            fix = (f"point {LLVM_ENV} at a libLLVM newer than 15 (e.g. {good}; `apt-get install libllvm19`) "
                   f"or unset it")
        else:
            fix = "apt-get install libllvm19 (its /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 is then found)"
        return Check("mitsuba", variant, "warn", detail, fix)
    return Check("mitsuba", variant, "warn", detail, "use an NVIDIA driver >= 535 (`nvidia-smi` shows its version)")


# ----------------------------------------------------------------------------------------- geometry
def _unit_cube():
    import numpy as np

    v = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]  # outward
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    return v, f


def check_libigl() -> Check:
    """``igl.signed_distance`` on a unit cube against known distances (required)."""
    import numpy as np

    try:
        import igl

        v, f = _unit_cube()
        points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.25, 0.1, 0.0], [0.0, 0.8, 0.0]])
        expected = np.array([-0.5, 0.5, -0.25, 0.3])
        t0 = time.perf_counter()
        s, *_ = igl.signed_distance(points, v, f)
        ms = (time.perf_counter() - t0) * 1e3
    except Exception as e:
        return Check("geometry", "libigl", "fail", f"signed_distance failed ({_error(e)})", SETUP_FIX, True)
    err = float(np.max(np.abs(np.asarray(s) - expected)))
    version = importlib.metadata.version("libigl")
    if not err < 1e-9:
        return Check("geometry", "libigl", "fail",
                     f"libigl {version}: signed distances {np.round(s, 4).tolist()}, expected {expected.tolist()}",
                     SETUP_FIX, True)
    return Check("geometry", "libigl", "ok",
                 f"libigl {version}: signed distance to a unit cube exact at 4 points ({ms:.1f} ms)", None, True)


def check_warp() -> Check:
    """warp started as the toolkit starts it and a signed point query on a CPU ``wp.Mesh`` (BVH) of a
    tetrahedron; without an NVIDIA driver, the detail says why warp has no CUDA device."""
    fix = f"{SETUP_FIX} (warp-lang); without warp, anny falls back to slower dense skinning"
    try:
        import numpy as np

        from dualhuman_builder.warp_runtime import cuda_driver_problem, init_warp

        with _quiet_warp():
            wp = init_warp()

            @wp.kernel(module="unique")
            def signed_distance(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
                i = wp.tid()
                q = wp.mesh_query_point_sign_normal(mesh, points[i], 1.0e6)
                if q.result:
                    out[i] = q.sign * wp.length(points[i] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))

            verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
            tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int32).ravel()
            points = np.array([[0.1, 0.1, 0.1], [-1.0, 0.0, 0.0], [0.2, 0.2, -0.5]], dtype=np.float32)
            expected = np.array([-0.1, 1.0, 0.5])
            t0 = time.perf_counter()
            mesh = wp.Mesh(points=wp.array(verts, dtype=wp.vec3, device="cpu"),
                           indices=wp.array(tris, dtype=wp.int32, device="cpu"))
            out = wp.full(len(points), 1e9, dtype=float, device="cpu")
            wp.launch(signed_distance, dim=len(points), inputs=[mesh.id, wp.array(points, dtype=wp.vec3, device="cpu"),
                                                                 out], device="cpu")
            got = out.numpy()
            seconds = time.perf_counter() - t0
    except Exception as e:
        return Check("geometry", "warp", "warn", f"warp mesh query failed ({_error(e)})", fix)
    err = float(np.max(np.abs(got - expected)))
    if not err < 1e-5:
        return Check("geometry", "warp", "warn", f"warp {wp.__version__}: mesh query gave {got.tolist()}, "
                                                 f"expected {expected.tolist()}", fix)
    devices = ", ".join(str(d) for d in wp.get_devices())
    no_cuda = cuda_driver_problem()
    return Check("geometry", "warp", "ok", f"warp {wp.__version__}: CPU mesh query exact in {seconds * 1e3:.1f} ms "
                 f"incl. kernel load; devices: {devices}" + (f" (no CUDA: {no_cuda})" if no_cuda else ""))


def check_kernel_cache() -> Check:
    """warp's kernel cache holds the pipeline's kernels compiled from this code (else each stage
    compiles its kernels on its first run on this machine: a warning)."""
    from dualhuman_builder.kernel_cache import kernel_cache_status

    status = kernel_cache_status()
    if status["built"]:
        return Check("geometry", "warp kernel cache", "ok", f"{status['cache_dir']}: {status['detail']}")
    return Check("geometry", "warp kernel cache", "warn", f"not built in {status['cache_dir']}: {status['detail']}; "
                 "each stage compiles its warp kernels on its first run", "dualhuman body warm")


# ----------------------------------------------------------------------------------------- storage
def check_sqlite() -> Check:
    """SQLite version and a WAL-mode database on a temporary file (the catalog needs WAL; required)."""
    try:
        with tempfile.TemporaryDirectory(prefix="dualhuman-doctor-") as tmp:
            path = Path(tmp) / "catalog.sqlite"
            con = sqlite3.connect(path)
            try:
                mode = con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
                con.execute("CREATE TABLE t (id INTEGER PRIMARY KEY, name TEXT)")
                with con:
                    con.execute("INSERT INTO t (name) VALUES (?)", ("take-0001",))
                rows = con.execute("SELECT name FROM t").fetchall()
            finally:
                con.close()
    except sqlite3.Error as e:
        return Check("storage", "sqlite", "fail", f"SQLite {sqlite3.sqlite_version}: {_error(e)}",
                     "use a local file system for workspaces (WAL does not work on some network mounts)", True)
    if mode.lower() != "wal" or rows != [("take-0001",)]:
        return Check("storage", "sqlite", "fail", f"SQLite {sqlite3.sqlite_version}: journal mode {mode!r}, "
                     f"rows {rows}", "use a local file system for workspaces", True)
    return Check("storage", "sqlite", "ok", f"SQLite {sqlite3.sqlite_version}, WAL journal works in {tempfile.gettempdir()}",
                 None, True)


def check_disk() -> Check:
    """Free space where workspaces (current folder) and the anny cache live."""
    from dualhuman_builder.body.model import anny_cache_dir

    places = {"current folder": Path.cwd(), "anny cache": anny_cache_dir()}
    parts, low = [], []
    for label, place in places.items():
        while not place.exists() and place != place.parent:
            place = place.parent
        free = shutil.disk_usage(place).free
        parts.append(f"{label} {free / 1024**3:.1f} GiB free")
        if free < MIN_FREE_BYTES:
            low.append(label)
    if low:
        return Check("storage", "disk space", "warn", "; ".join(parts),
                     f"free space for {', '.join(low)} (renders and take logs need several GiB)")
    return Check("storage", "disk space", "ok", "; ".join(parts))


# ----------------------------------------------------------------------------------------- capture
def _capture_check(probe: Callable) -> Check:
    result = probe()
    return Check("capture", result.name, "ok" if result.ok else "warn", result.detail,
                 None if result.ok else result.fix)


# ----------------------------------------------------------------------------------------- run, report
def _plan(render: bool) -> list[tuple[str, str, bool, Callable[[], Check | list[Check]]]]:
    from dualhuman_builder.capture.backends import CAPTURE_PROBES

    plan = [
        ("python", "python", True, check_python),
        ("packages", "package versions", True, check_packages),
        ("torch", "torch", True, check_torch),
        ("body model", "anny", True, check_body_model),
    ]
    for variant in ("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb"):
        plan.append(("mitsuba", variant, variant == "scalar_rgb",
                     lambda v=variant: check_mitsuba_variant(v, render=render)))
    plan += [
        ("geometry", "libigl", True, check_libigl),
        ("geometry", "warp", False, check_warp),
        ("geometry", "warp kernel cache", False, check_kernel_cache),
        ("storage", "sqlite", True, check_sqlite),
        ("storage", "disk space", False, check_disk),
    ]
    for name, probe in CAPTURE_PROBES:
        plan.append(("capture", name, False, lambda p=probe: _capture_check(p)))
    return plan


def run_checks(render: bool = True, progress: Callable[[str], None] | None = None) -> list[Check]:
    """Run every check, in report order. ``render=False`` skips the Mitsuba renders (seconds each).

    ``progress(name)`` is called before each check runs (e.g. to label a spinner). A check that
    raises unexpectedly is reported as ``fail`` (required) or ``warn`` with the exception.
    """
    checks: list[Check] = []
    for group, name, required, run in _plan(render):
        if progress is not None:
            progress(f"{group}: {name}")
        try:
            result = run()
        except Exception as e:
            result = Check(group, name, "fail" if required else "warn", f"check raised {_error(e)}", None, required)
        checks.extend(result if isinstance(result, list) else [result])
    return checks


def exit_code(checks: Iterable[Check]) -> int:
    """1 if any required check failed, else 0."""
    return int(any(c.required and c.status == "fail" for c in checks))


def checks_to_json(checks: Iterable[Check]) -> str:
    """The checks as a JSON list of objects with the fields of :class:`Check`."""
    return json.dumps([dataclasses.asdict(c) for c in checks], indent=2)


_SYMBOLS = {"ok": ("✓", "green"), "warn": ("!", "yellow"), "fail": ("✗", "bold red"), "skip": ("-", "dim")}


def summary_line(checks: list[Check]) -> str:
    """``"N ok, N warnings, N failed, N skipped: <verdict>"``."""
    count = {s: sum(c.status == s for c in checks) for s in STATUSES}
    required_failed = [c for c in checks if c.required and c.status == "fail"]
    text = f"{count['ok']} ok, {count['warn']} warnings, {count['fail']} failed, {count['skip']} skipped: "
    if required_failed:
        names = ", ".join(f"{c.group}/{c.name}" for c in required_failed)
        return text + f"not ready, {len(required_failed)} required check(s) failed ({names})"
    return text + "ready" + (" (see the warnings for optional parts)" if count["warn"] else "")


def print_report(checks: list[Check], console) -> None:
    """Print the checks as a table (status, group, check, detail, fix) and a one-line summary.

    ``console`` is a :class:`rich.console.Console`. Cells are plain text: no rich markup is read
    from details or fixes.
    """
    from rich.table import Table
    from rich.text import Text

    table = Table(show_header=True, header_style="bold", show_lines=False, pad_edge=False)
    table.add_column("", no_wrap=True)
    table.add_column("group", no_wrap=True)
    table.add_column("check", no_wrap=True)
    table.add_column("detail", overflow="fold")
    table.add_column("fix", overflow="fold")
    for c in checks:
        symbol, style = _SYMBOLS[c.status]
        table.add_row(Text(symbol, style=style), Text(c.group), Text(c.name, style=style if c.status != "ok" else ""),
                      Text(c.detail), Text(c.fix or "", style="cyan"))
    console.print(table)
    style = "bold red" if exit_code(checks) else "bold green"
    console.print(Text(summary_line(checks), style=style))
