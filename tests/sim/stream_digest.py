"""A short digest of a simulated stream's arrays that is the same on any CPU, for the simulator tests
that pin a stream recorded once (:func:`stream_digest`)."""

from __future__ import annotations

import hashlib

import numpy as np


def machine_stable(name: str, a: np.ndarray) -> np.ndarray:
    """``a`` without the last bits that differ between CPUs (the exact-bit digests recorded on one machine
    failed on another with the same numpy and scipy): floats rounded to 1e-6, ``*_ns`` times to
    microseconds. Any change to what a simulator does moves them by far more."""
    if np.issubdtype(a.dtype, np.floating):
        return np.round(a.astype(np.float64), 6) + 0.0
    return a // 1000 if name.endswith("_ns") else a


def stream_digest(obj, names) -> str:
    """16 hex digits of SHA-256 over ``obj``'s arrays ``names`` (each name, dtype and
    :func:`machine_stable` values, in that order)."""
    h = hashlib.sha256()
    for name in names:
        a = np.ascontiguousarray(getattr(obj, name))
        h.update(name.encode()), h.update(str(a.dtype).encode()), h.update(machine_stable(name, a).tobytes())
    return h.hexdigest()[:16]
