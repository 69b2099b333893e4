"""``dualhuman doctor``'s checks, run for real on this machine (Mitsuba renders, libigl, SQLite, capture)."""

from __future__ import annotations

import dataclasses
import io
import json
import os

import pytest
from rich.console import Console

from dualhuman_builder.capture.backends import (
    BackendProbe,
    probe_can_virtual,
    probe_serial_loop,
    probe_serial_pty,
    probe_udp_loopback,
    probe_usb_backend,
    probe_vive_usb,
)
from dualhuman_builder.doctor import Check, checks_to_json, exit_code, print_report, run_checks
from dualhuman_builder.render.mitsuba_env import LLVM_ENV, configure_llvm, find_llvm, nvidia_gpus, probe_variant

LLVM15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"


@pytest.fixture(scope="module")
def checks() -> list[Check]:
    seen: list[str] = []
    result = run_checks(render=True, progress=seen.append)
    assert seen and all(isinstance(s, str) for s in seen)
    return result


def by_name(checks: list[Check], group: str, name: str) -> Check:
    found = [c for c in checks if c.group == group and c.name == name]
    assert len(found) == 1, f"expected one {group}/{name} check, got {found}"
    return found[0]


def test_machine_is_ready(checks):
    assert exit_code(checks) == 0, [c for c in checks if c.required and c.status == "fail"]
    assert by_name(checks, "python", "python").status == "ok"
    for c in checks:
        assert c.status in ("ok", "warn", "fail", "skip")
        if c.status == "ok":
            assert c.fix is None, c


def test_mitsuba_variants_render(checks):
    scalar = by_name(checks, "mitsuba", "scalar_rgb")
    assert scalar.status == "ok" and scalar.required
    llvm = by_name(checks, "mitsuba", "llvm_ad_rgb")
    assert llvm.status == "ok", llvm.detail
    assert not llvm.required
    assert find_llvm() is not None and (os.environ.get(LLVM_ENV) or find_llvm()) in llvm.detail
    cuda = by_name(checks, "mitsuba", "cuda_ad_rgb")
    assert not cuda.required
    if nvidia_gpus()[0] == 0:
        assert cuda.status == "skip", cuda.detail
    else:
        assert cuda.status in ("ok", "warn"), cuda.detail


def test_geometry_storage_and_body_model(checks):
    igl = by_name(checks, "geometry", "libigl")
    assert igl.status == "ok" and igl.required, igl.detail
    assert by_name(checks, "storage", "sqlite").status == "ok"
    model = by_name(checks, "body model", "anny model")
    assert model.status == "ok" and "13718 vertices" in model.detail and "27420 faces" in model.detail
    warp = by_name(checks, "geometry", "warp")
    assert warp.status in ("ok", "warn")
    from dualhuman_builder.kernel_cache import kernel_cache_status
    from dualhuman_builder.warp_runtime import cuda_driver_problem

    kernels = by_name(checks, "geometry", "warp kernel cache")
    assert not kernels.required and kernels.status == ("ok" if kernel_cache_status()["built"] else "warn")
    assert kernels.fix == (None if kernels.status == "ok" else "dualhuman body warm")
    if cuda_driver_problem() is not None:  # CUDA is reported skipped, with the reason
        assert warp.status != "ok" or f"(no CUDA: {cuda_driver_problem()})" in warp.detail
        cuda = by_name(checks, "torch", "cuda")
        assert cuda.status == "skip" and "no NVIDIA driver" in cuda.detail


def test_capture_checks_are_never_required(checks):
    capture = [c for c in checks if c.group == "capture"]
    assert capture and not any(c.required for c in capture)
    assert by_name(checks, "capture", "serial loop://").status == "ok"
    assert by_name(checks, "capture", "can virtual").status == "ok"


def test_json_round_trip(checks):
    data = json.loads(checks_to_json(checks))
    assert data == [dataclasses.asdict(c) for c in checks]
    assert [Check(**d) for d in data] == checks


def test_print_report_ends_with_summary(checks):
    out = io.StringIO()
    print_report(checks, Console(file=out, width=200, color_system=None))
    text = out.getvalue().rstrip().splitlines()
    assert text[-1].endswith("ready") or "ready (see the warnings" in text[-1]
    assert any("llvm_ad_rgb" in line for line in text)


def test_exit_code_counts_only_required_failures():
    ok = Check("python", "python", "ok", "3.11", None, True)
    assert exit_code([ok]) == 0
    assert exit_code([ok, Check("capture", "vive usb", "fail", "permission denied", "udev rule", False)]) == 0
    assert exit_code([ok, Check("storage", "sqlite", "fail", "no WAL", "local disk", True)]) == 1
    assert exit_code([Check("mitsuba", "cuda_ad_rgb", "skip", "no GPU", None, True)]) == 0


def test_check_rejects_unknown_status():
    with pytest.raises(ValueError):
        Check("python", "python", "great", "")


def test_probe_with_missing_libllvm_fails_cleanly(monkeypatch, tmp_path):
    missing = str(tmp_path / "libLLVM-missing.so")
    monkeypatch.setenv(LLVM_ENV, missing)
    probe = probe_variant("llvm_ad_rgb", timeout=120)
    assert not probe.ok
    assert probe.llvm_path == missing
    assert missing in probe.detail and "could not be loaded" in probe.detail, probe.detail
    assert configure_llvm() == missing  # a path the user set is kept


@pytest.mark.skipif(not os.path.exists(LLVM15), reason="needs Debian 12's libLLVM 15")
def test_probe_survives_llvm15_abort(monkeypatch):
    monkeypatch.setenv(LLVM_ENV, LLVM15)
    probe = probe_variant("llvm_ad_rgb", timeout=120)
    assert not probe.ok
    assert "SIGABRT" in probe.detail or "LLVM ERROR" in probe.detail, probe.detail


def test_probe_unknown_variant():
    probe = probe_variant("llvm_ad_nonsense", timeout=120)
    assert not probe.ok and "not compiled" in probe.detail


def test_capture_loopback_paths():
    for probe in (probe_udp_loopback(), probe_serial_loop(), probe_serial_pty(), probe_can_virtual()):
        assert probe.ok, probe


def test_usb_probes_report_instead_of_raising():
    for probe in (probe_usb_backend(), probe_vive_usb()):
        assert isinstance(probe, BackendProbe)
        assert probe.ok or probe.fix, probe
