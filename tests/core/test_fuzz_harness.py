"""The fuzz harness (``benchmarks/fuzz.py``) keeps working: its inputs repeat from the seed, what escapes an
operation (a hang included) is counted with where it was raised and saved for ``--replay``, decoder streams run
through the real decoders, and a short run of every target writes a results file with its goals."""

from __future__ import annotations

import importlib.util
import json
import random
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "benchmarks" / "fuzz.py"


@pytest.fixture(scope="module")
def fuzz():
    spec = importlib.util.spec_from_file_location("fuzz_harness", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _packets():
    """Real encoders' packets of two decoders: VIVE USB IMU reports and Xbus frames."""
    from dualhuman_builder.capture.wire.vive_hid import HidImuSample, encode_imu_report
    from dualhuman_builder.capture.wire.xbus import MID, encode_message

    slots = [HidImuSample((k, -k, 4096), (1, 2, 3), (48_000 * k) % 2**32, k & 0xFF) for k in range(60)]
    usb = [(1_000_000 * k, encode_imu_report(slots[max(k - 2, 0):k + 1] if k >= 2 else [slots[0]] * 3)) for k in range(60)]
    xbus = [(1_000_000 * k, encode_message(MID.ERROR, b"\x04")) for k in range(10)]
    return {"vive-usb": usb, "xbus": xbus}


def test_mutations_repeat_from_the_seed_and_fixups_make_frames_pass_the_checks(fuzz):
    data = bytes(range(64))
    a = [fuzz.mutate_bytes(random.Random(f"0:t:{i}"), data, fields=[(4, 4, True)]) for i in range(50)]
    b = [fuzz.mutate_bytes(random.Random(f"0:t:{i}"), data, fields=[(4, 4, True)]) for i in range(50)]
    assert a == b and len(set(a)) > 40 and data not in a
    c = [fuzz.mutate_bytes(random.Random(f"1:t:{i}"), data, fields=[(4, 4, True)]) for i in range(50)]
    assert c != a
    xbus = fuzz.PROTOCOLS["xbus"]
    for i in range(30):
        frame = xbus.fixup(random.Random(i), fuzz.mutate_bytes(random.Random(i), bytes.fromhex("faff3604010203049f")))
        if len(frame) >= 4:
            assert sum(frame[1:]) & 0xFF == 0  # the Xbus checksum holds, so the decoder reads further
    mvn = fuzz.PROTOCOLS["mvn"].fixup(random.Random(0), b"MXTP02" + bytes(18) + bytes(40))
    assert struct.unpack_from(">H", mvn, 22)[0] == 40


def test_decoder_streams_are_reproducible_and_run_through_the_real_decoder(fuzz):
    packets = _packets()
    one, two = fuzz.DecoderTarget("vive-usb", packets), fuzz.DecoderTarget("vive-usb", packets)
    one.stop = 50
    streams = [one.make_input(random.Random(f"0:vive-usb:{i}"), i) for i in range(50)]
    assert streams == [two.make_input(random.Random(f"0:vive-usb:{i}"), i) for i in range(50)]
    assert all(isinstance(t, int) and isinstance(d, bytes) for s in streams for t, d in s)
    escapes = [e for i, s in enumerate(streams) for e in one.run(i, s)]
    assert escapes == [] and one.decoder is None  # the last input ended the session with finish()


def test_an_escape_names_its_operation_and_place_and_a_hang_is_one(fuzz, tmp_path):
    class JsonTarget(fuzz.FileTarget):
        name, suffix = "json", ".json"

        def ops(self, path):
            return [("loads", lambda p: json.loads(p.read_bytes()), (path,))]

    t = JsonTarget(tmp_path)
    assert t.run(0, b'{"a": 1}') == []
    (esc,) = t.run(1, b'{"a": ')
    assert esc.type == "JSONDecodeError" and esc.key.startswith("loads: JSONDecodeError at ") and esc.trace
    paths, doc = t.save(b'{"a": ', esc, tmp_path / "finding")
    assert paths[0].read_bytes() == b'{"a": ' and doc["file"] == "finding.json"
    t.timeout = 0.05
    fuzz.signal.signal(fuzz.signal.SIGALRM, fuzz._alarm)
    start = time.monotonic()
    hang = t.guarded("sleep", time.sleep, 5)
    assert hang.type == "hang" and time.monotonic() - start < 2


def test_replay_runs_a_saved_decoder_finding_again(tmp_path):
    from dualhuman_builder.capture.wire.xbus import encode_message

    finding = tmp_path / "f.json"
    finding.write_text(json.dumps({"target": "xbus", "url": "xbus://loop", "key": "feed: X at y:1",
                                   "packets": [[1, encode_message(0x36, b"").hex()], [2, "faff"]]}))  # fmt: skip
    r = subprocess.run([sys.executable, str(SCRIPT), "--replay", str(finding)], cwd=REPO, capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 0 and "nothing escaped" in r.stdout, r.stdout + r.stderr


@pytest.mark.slow
def test_a_short_run_of_every_target_writes_its_results(tmp_path):
    """50 inputs per target (the corpus is made first when benchmarks/cache/fuzz/ lacks it)."""
    out = tmp_path / "fuzz.json"
    r = subprocess.run([sys.executable, str(SCRIPT), "--inputs", "50", "--out", str(out), "--findings",
                        str(tmp_path / "findings")], cwd=REPO, capture_output=True, text=True, timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    doc = json.loads(out.read_text())
    targets = doc["figures"]["targets"]
    assert list(targets) == ["mvn", "vive", "xbus", "mti-can", "vive-usb", "take", "mvnx", "bvh", "export", "annotate"]
    for name, t in targets.items():
        assert t["inputs"] == 50 and t["peak_mib"] > 0 and isinstance(t["escaped"], int), (name, t)
        assert (t["caught"] is not None) == (t["kind"] == "decoder"), name
    assert len(doc["goals"]) == 3 * len(targets)
    assert {g["figure"].split(".")[-1] for g in doc["goals"]} == {"escaped", "inputs", "peak_mib"}
    assert doc["params"]["corpus"] and doc["tables"][0]["rows"][0][0] == "mvn"
