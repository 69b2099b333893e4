"""warp's kernel cache for the toolkit's kernels: build it once per machine, and check it.

warp compiles a module's kernels (C++ through its bundled Clang) the first time one of them runs
and keeps the object code in its kernel cache (``$WARP_CACHE_PATH/<warp version>``, by default
``~/.cache/warp/<warp version>``); later runs load it from there. :func:`build_kernel_cache` runs
every warp module the pipeline uses once, on the CPU, on tiny inputs: anny's skinning, the contact
kernels, the scenes' signed distances, and the fit's collision and skinning kernels. It then
records what it built in ``dualhuman-kernels.json`` in that folder, together with a fingerprint of
the sources of those kernels, so that :func:`kernel_cache_status` can tell without compiling
anything whether the cache still matches this code.

Which modules hold warp code is read from the package's sources (``@wp.kernel``, ``@wp.func``,
``@wp.struct``); a module that holds some but that the build did not load is reported in
``missing``.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import importlib.util
import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: The record :func:`build_kernel_cache` leaves in warp's kernel cache folder.
RECORD_NAME = "dualhuman-kernels.json"

#: anny's warp module (its linear blend skinning), compiled by the body model's first forward pass.
ANNY_WARP_MODULE = "anny.skinning.warp_skinning"

#: Modules with warp code that the pipeline does not run: ``doctor`` compiles its own probe kernel
#: each time (it reports that time), and this module only names warp's decorators.
_NOT_PIPELINE = ("dualhuman_builder.doctor", "dualhuman_builder.kernel_cache")

_WARP_CODE = re.compile(r"^\s*@wp\.(kernel|func|struct)\b|\bwp\.kernel\(", re.MULTILINE)


def toolkit_warp_modules() -> dict[str, Path]:
    """``{module name: source file}`` of every module of the package that defines warp kernels,
    functions or structs (found in the sources, nothing imported), the pipeline's only."""
    package = Path(__file__).resolve().parent
    found = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if name not in _NOT_PIPELINE and _WARP_CODE.search(path.read_text(encoding="utf-8")):
            found[name] = path
    return found


def kernel_cache_dir() -> Path:
    """warp's kernel cache folder as this process's warp uses it (starts warp)."""
    from dualhuman_builder.warp_runtime import init_warp

    return Path(init_warp().config.kernel_cache_dir)


def _fingerprint() -> str:
    """SHA-256 over the warp and anny versions and the sources of every module whose kernels the
    build compiles: a change to any of them means the cache may lack the new kernels."""
    wp = _warp()
    h = hashlib.sha256(f"warp {wp.config.version}\nanny {importlib.metadata.version('anny')}\n".encode())
    sources = dict(toolkit_warp_modules())
    spec = importlib.util.find_spec(ANNY_WARP_MODULE)
    if spec is not None and spec.origin:
        sources[ANNY_WARP_MODULE] = Path(spec.origin)
    for name, path in sorted(sources.items()):
        h.update(f"{name}\n".encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _warp():
    from dualhuman_builder.warp_runtime import init_warp

    return init_warp()


def kernel_cache_status() -> dict[str, Any]:
    """Whether the kernel cache holds every kernel the pipeline runs, compiled from this code;
    compiles nothing.

    Returns ``{"built": bool, "cache_dir": str, "detail": str}``; ``detail`` says what is missing
    or out of date when ``built`` is False.
    """
    cache = kernel_cache_dir()
    record_path = cache / RECORD_NAME
    try:
        record = json.loads(record_path.read_text())
    except (OSError, ValueError):
        return {"built": False, "cache_dir": str(cache), "detail": f"no record of a build ({record_path.name} missing)"}
    if record.get("fingerprint") != _fingerprint():
        return {"built": False, "cache_dir": str(cache),
                "detail": "out of date: the kernels' sources, warp or anny changed since it was built"}  # fmt: skip
    lost = [i for idents in record.get("modules", {}).values() for i in idents if not any((cache / i).glob("*.o"))]
    if lost:
        return {"built": False, "cache_dir": str(cache), "detail": f"{len(lost)} module(s) gone: {', '.join(lost)}"}
    return {"built": True, "cache_dir": str(cache), "detail": f"{len(record['modules'])} modules"}


def build_kernel_cache(log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run every warp kernel the pipeline uses once on tiny inputs on the CPU, so that warp
    compiles them into its kernel cache now (or loads them from it), and record the build.

    Returns ``{"built": bool, "seconds": float, "cache_dir": str, "modules": {name: [cache folders]},
    "missing": [names]}``: ``built`` is False when the cache already held everything
    (:func:`kernel_cache_status`); ``missing`` names the package's modules with warp code that
    were not loaded (none, unless a new module's kernels are only defined when a function runs).
    """
    import numpy as np

    say = log or (lambda _msg: None)
    was_built = kernel_cache_status()["built"]
    wp = _warp()
    t0 = time.perf_counter()

    from dualhuman_builder.body.model import get_body_model

    say("anny's skinning")
    model = get_body_model()
    rest = model.rest().vertices[0].detach().cpu().numpy().astype(np.float32)
    # two bodies side by side, arms overlapping: every stage of the contact queries has work
    a, b = rest[None], (rest + np.array([0.3, 0.0, 0.0], np.float32))[None]

    from dualhuman_builder.contacts.compute import contacts_from_vertices
    from dualhuman_builder.contacts.topology import default_topology

    say("contacts")
    contacts_from_vertices(a, b, default_topology(), workers=1)

    from dualhuman_builder.geometry.distance import get_pair_distance

    say("signed distances")
    get_pair_distance("cpu")(a[0], b[0], band=0.05)

    modules = {}
    missing = []
    for name in [ANNY_WARP_MODULE, *toolkit_warp_modules()]:
        say(name)
        try:
            importlib.import_module(name)
            wp.load_module(name, device="cpu")
        except RuntimeError:  # no warp code registered at import: kernels defined only when a function runs
            missing.append(name)
            continue
        module = wp.get_module(name)
        # the CPU's variants (context None), one per block size launched
        modules[name] = sorted({module.get_module_identifier(dim) for ctx, dim in list(module.execs) if ctx is None})
    seconds = time.perf_counter() - t0
    cache = kernel_cache_dir()
    record = {"fingerprint": _fingerprint(), "warp": wp.config.version, "modules": modules, "missing": missing}
    (cache / RECORD_NAME).write_text(json.dumps(record, indent=1) + "\n")
    return {"built": not was_built, "seconds": seconds, "cache_dir": str(cache), "modules": modules, "missing": missing}
