"""Property tests of the file readers (MVNX, BVH): small valid files built here, mutated, and arbitrary
bytes never raise anything but a :class:`DualhumanError`, and reading a few KB stays within a few tens
of MB (``tracemalloc`` peak), whatever counts, entities, nesting or numbers the file claims."""

from __future__ import annotations

import math
import re
import tracemalloc

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation  # noqa: F401  (imported here: its import is not the reader's memory)

from dualhuman_builder.capture.importers.bvh import read_bvh
from dualhuman_builder.capture.importers.mvnx import read_mvnx
from dualhuman_builder.errors import DualhumanError

#: Peak traced memory allowed while reading an input of a few KB.
MEMORY_LIMIT = 32 << 20


# --------------------------------------------------------------------------------------------- generators
def mvnx_text(segments: int = 2, frames: int = 3, sensors: int = 1, joints: int = 1, ergo: int = 1,
              calibration: tuple[str, ...] = ("identity", "tpose"), namespace: bool = True) -> str:  # fmt: skip
    """A small valid MVNX file: ``segments`` segments with one point each, ``sensors`` sensors,
    ``joints`` joints, ``ergo`` ergonomic joints, the ``calibration`` frames, then ``frames`` normal
    frames holding one element of each kind (segment, sensor, joint, ergonomic joint, free width)."""
    ns = ' xmlns="http://www.xsens.com/mvn/mvnx"' if namespace else ""
    seg = [f's{i}' for i in range(segments)]
    out = ['<?xml version="1.0" encoding="UTF-8"?>', f'<mvnx version="4"{ns}>', '<mvn version="2023.0" build="t"/>',
           "<comment>c</comment>", f'<subject label="alice" frameRate="60" segmentCount="{segments}">',
           "<segments>"]  # fmt: skip
    for i, s in enumerate(seg):
        out.append(f'<segment label="{s}" id="{i + 1}"><points><point label="p{i}"><pos_b>0 0.1 0</pos_b></point>'
                   "</points></segment>")  # fmt: skip
    out.append("</segments><sensors>" + "".join(f'<sensor label="{s}"/>' for s in seg[:sensors]) + "</sensors>")
    out.append("<joints>" + "".join(f'<joint label="j{k}"><connector1>s0/p0</connector1><connector2>s1/p1</connector2>'
                                    "</joint>" for k in range(joints)) + "</joints>")  # fmt: skip
    out.append("<ergonomicJointAngles>" + "".join(f'<ergonomicJointAngle label="e{k}"/>' for k in range(ergo))
               + "</ergonomicJointAngles>")  # fmt: skip
    out.append('<footContactDefinition><contactDefinition label="LeftFoot_Heel"/></footContactDefinition>')
    out.append(f'<frames segmentCount="{segments}" sensorCount="{sensors}" jointCount="{joints}">')

    def values(n: int, k: int, phase: float) -> str:
        return " ".join(f"{math.sin(phase + 0.37 * i):.4f}" for i in range(n * k))

    unit = " ".join(["0.5 0.5 0.5 0.5"] * segments)
    for kind in calibration:
        out.append(f'<frame time="0" index="" tc="" ms="" type="{kind}"><orientation>{unit}</orientation>'
                   f"<position>{values(segments, 3, 0.0)}</position></frame>")  # fmt: skip
    for f in range(frames):
        q = " ".join(f"{math.cos(0.1 * f + s):.6f} 0 0 {math.sin(0.1 * f + s):.6f}" for s in range(segments))
        out.append(f'<frame time="{17 * f}" index="{f}" tc="00:00:00:{f:02d}" ms="{1700000000000 + 17 * f}" '
                   f'type="normal"><orientation>{q}</orientation><position>{values(segments, 3, f)}</position>'
                   f"<velocity>{values(segments, 3, f + 1)}</velocity>"
                   f"<footContacts>1 0</footContacts>"
                   f"<sensorOrientation>{' '.join(['1 0 0 0'] * sensors)}</sensorOrientation>"
                   f"<jointAngle>{values(joints, 3, f + 2)}</jointAngle>"
                   f"<jointAngleErgo>{values(ergo, 3, f + 3)}</jointAngleErgo>"
                   f"<centerOfMass>{values(1, 9, f)}</centerOfMass></frame>")  # fmt: skip
    out += ["</frames>", "</subject>", '<securityCode code=""/>', "</mvnx>", ""]
    return "\n".join(out)


def bvh_text(joints: int = 3, frames: int = 3, end_site: bool = True) -> str:
    """A small valid BVH file: a root with position and rotation channels, then a chain of ``joints - 1``
    joints with rotation channels (the last one with an End Site), ``frames`` frames at 25 fps."""
    lines = ["HIERARCHY", "ROOT Hips", "{", "  OFFSET 0 90 0",
             "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]  # fmt: skip
    for k in range(1, joints):
        lines += [f"JOINT J{k}", "{", "  OFFSET 0 10 0", "  CHANNELS 3 Zrotation Xrotation Yrotation"]
    if end_site:
        lines += ["End Site", "{", "  OFFSET 0 5 0", "}"]
    lines += ["}"] * joints
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: 0.04"]
    C = 6 + 3 * (joints - 1)
    for f in range(frames):
        lines.append(" ".join(f"{10 * math.sin(0.3 * f + c):.4f}" for c in range(C)))
    return "\n".join(lines) + "\n"


VALID_MVNX = mvnx_text()
VALID_BVH = bvh_text()

MVNX_TOKENS = ("<frame>", "</frame>", '<frame time="5" type="normal">', '<frame type="tpose">', "<orientation>",
               "</orientation>", "<position>", "</position>", "<segments>", "</segments>", '<segment label="x" id="9">',
               "<frames>", '<frames segmentCount="2" sensorCount="99999999" jointCount="1">', "</frames>",
               "<sensors>", "</sensors>", '<sensor label="s9"/>', "<subject>", "</subject>", "nan", "inf", "-inf",
               "1e309", "-1", "99999999999999999999999", "0x1f", " ", "\n", "\x00", '"', "&amp;", "&lt;", "&x;",
               '<!DOCTYPE mvnx [<!ENTITY x "xxxxxxxxxx">]>', "<![CDATA[1 2 3]]>", "<!-- c -->", "<?pi x?>",
               "<a><a><a><a><a><a><a><a>", "</a>", "é", "\u2028")  # fmt: skip
BVH_TOKENS = ("{", "}", "ROOT R", "JOINT J", "End Site", "OFFSET 0 0 0", "OFFSET 1e308 1e308 1e308",
              "CHANNELS 3 Zrotation Xrotation Yrotation", ("CHANNELS 6 Xposition Yposition Zposition Xrotation "
              "Yrotation Zrotation"), "CHANNELS 2 Xrotation Xrotation", "CHANNELS 99999999999999999999",
              "CHANNELS \u00b2", "MOTION", "Frames: 99999999999", "Frames: \u00b2", "Frame Time: 1e-320",
              "Frame Time: 1e300", "Frame Time: nan", "nan", "inf", "-inf", "1e309", "-1e308", "\n", "\r", "\t",
              "\x00", "\ufeff", "\u2028", "\x0c", "é", "0" * 5000)  # fmt: skip
NUMBER = re.compile(r"-?\d+(\.\d+)?")
numbers = st.one_of(st.integers(-(2**70), 2**70).map(str), st.floats().map(repr),
                    st.sampled_from(["", "nan", "inf", "-inf", "1e309", "1e-320", "0x10", "\u0661\u0662", "1_0",
                                     "9" * 5000]),
                    st.text(max_size=6))  # fmt: skip


@st.composite
def mutated(draw, base: str, tokens: tuple[str, ...]) -> bytes:
    """``base`` with one to five edits: a span deleted, a token or short text inserted, a span repeated
    (up to 50 times), a number replaced by another (huge, negative, not finite, not a number), or a
    whole line deleted, repeated or moved (the structure kept, its order and counts changed)."""
    text = base
    for _ in range(draw(st.integers(1, 5))):
        i = draw(st.integers(0, len(text)))
        j = min(len(text), i + draw(st.integers(0, 80)))
        op = draw(st.sampled_from(("delete", "insert", "repeat", "number", "number", "line", "line")))
        if op == "delete":
            text = text[:i] + text[j:]
        elif op == "insert":
            text = text[:i] + draw(st.one_of(st.sampled_from(tokens), st.text(max_size=8))) + text[i:]
        elif op == "repeat":
            text = text[:j] + text[i:j] * draw(st.integers(1, 50)) + text[j:]
        elif op == "number":
            m = NUMBER.search(text, i)
            if m is not None:
                text = text[: m.start()] + draw(numbers) + text[m.end() :]
        else:
            lines = text.split("\n")
            k = draw(st.integers(0, len(lines) - 1))
            line = lines.pop(k)
            at = draw(st.integers(0, len(lines)))
            lines[at:at] = [line] * draw(st.integers(0, 3))
            text = "\n".join(lines)
    return text.encode("utf-8", "surrogatepass")


binary = st.one_of(st.binary(max_size=4096), st.text(max_size=2000).map(lambda t: t.encode("utf-8", "surrogatepass")))


def read_bounded(reader, data: bytes, path) -> object | None:
    """``reader(path)`` of ``data``: the result, or None when it raised a DualhumanError (anything else
    propagates); fails when the traced peak exceeds :data:`MEMORY_LIMIT`."""
    path.write_bytes(data)
    tracemalloc.start()
    try:
        try:
            result = reader(path)
        except DualhumanError:
            result = None
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < MEMORY_LIMIT, f"{peak / 2**20:.1f} MiB traced reading {len(data)} bytes"
    return result


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("props")


def read_bvh_or_mvnx(folder, name: str, text: str):
    path = folder / name
    path.write_text(text)
    return read_mvnx(path) if name.endswith(".mvnx") else read_bvh(path)


def test_the_generated_files_are_valid(folder):
    mf = read_bvh_or_mvnx(folder, "x.mvnx", VALID_MVNX)
    assert mf.num_frames == 3 and list(mf.calibration) == ["identity", "tpose"]
    assert mf.arrays["sensorOrientation"].shape == (3, 1, 4) and mf.arrays["jointAngleErgo"].shape == (3, 1, 3)
    assert mf.track.orientation_valid.all() and mf.track.position_valid.all()
    tr = read_bvh_or_mvnx(folder, "x.bvh", VALID_BVH)
    assert tr.num_frames == 3 and tr.segment_names == ("Hips", "J1", "J2") and tr.fps == 25.0


# --------------------------------------------------------------------------------------------- MVNX
@given(segments=st.integers(1, 4), sensors=st.integers(0, 4), joints=st.integers(0, 3), ergo=st.integers(0, 2),
       frames=st.integers(1, 4), namespace=st.booleans())  # fmt: skip
def test_mvnx_valid_files_of_any_size_read_back(folder, segments, sensors, joints, ergo, frames, namespace):
    """The count checks refuse no honest file: every count agrees with the values, whatever the sizes."""
    sensors = min(sensors, segments)
    text = mvnx_text(segments, frames, sensors, joints, ergo, namespace=namespace)
    mf = read_bounded(read_mvnx, text.encode(), folder / "v.mvnx")
    assert mf is not None and mf.num_frames == frames and len(mf.segments) == segments
    assert mf.arrays["sensorOrientation"].shape == (frames, sensors, 4)
    assert mf.arrays["jointAngle"].shape == (frames, joints, 3)
    assert mf.arrays["jointAngleErgo"].shape == ((frames, ergo, 3) if ergo else (frames, 0))
    assert mf.track.orientation_valid.all() and mf.track.position_valid.all()


@given(data=mutated(VALID_MVNX, MVNX_TOKENS))
def test_mvnx_mutated_files_raise_only_dualhuman_errors_in_bounded_memory(folder, data):
    read_bounded(read_mvnx, data, folder / "m.mvnx")


@given(data=binary)
@example(data=b"")
@example(data=b"<mvnx/>")
@example(data=b"<mvnx>" + b"<a>" * 3000)
def test_mvnx_arbitrary_bytes_raise_only_dualhuman_errors(folder, data):
    read_bounded(read_mvnx, data, folder / "a.mvnx")


ATTRIBUTES = ('segmentCount="2" sensorCount', 'sensorCount="1" jointCount', 'jointCount="1">', 'frameRate="60"',
              'time="17"', 'index="1"', 'ms="1700000000017"', 'id="2"', 'segmentCount="2">')  # fmt: skip


@given(attribute=st.sampled_from(ATTRIBUTES), value=numbers)
def test_mvnx_any_attribute_value_raises_only_dualhuman_errors(folder, attribute, value):
    assert VALID_MVNX.count(attribute) == 1
    edited = VALID_MVNX.replace(attribute, re.sub(r'"[^"]*"', f'"{value}"', attribute, count=1))
    read_bounded(read_mvnx, edited.encode("utf-8", "surrogatepass"), folder / "c.mvnx")


# --------------------------------------------------------------------------------------------- BVH
@given(data=mutated(VALID_BVH, BVH_TOKENS))
def test_bvh_mutated_files_raise_only_dualhuman_errors_in_bounded_memory(folder, data):
    read_bounded(read_bvh, data, folder / "m.bvh")


@given(data=binary)
@example(data=b"")
@example(data=b"HIERARCHY\nROOT r {\nOFFSET 0 0 0\n}\nMOTION\nFrames: \xc2\xb2\nFrame Time: 1\n")
def test_bvh_arbitrary_bytes_raise_only_dualhuman_errors(folder, data):
    read_bounded(read_bvh, data, folder / "a.bvh")


@given(frames=numbers, frame_time=numbers, channels=numbers)
def test_bvh_any_header_value_raises_only_dualhuman_errors(folder, frames, frame_time, channels):
    text = (VALID_BVH.replace("Frames: 3", f"Frames: {frames}").replace("Frame Time: 0.04", f"Frame Time: {frame_time}")
            .replace("CHANNELS 3 Zrotation Xrotation Yrotation\nJOINT J2", f"CHANNELS {channels} Zrotation Xrotation "
                     "Yrotation\nJOINT J2"))  # fmt: skip
    read_bounded(read_bvh, text.encode("utf-8", "surrogatepass"), folder / "h.bvh")


@given(frame=st.integers(0, 2), channel=st.integers(0, 11), value=numbers)
@example(frame=1, channel=3, value="nan")  # the root's first rotation channel
def test_bvh_any_motion_value_is_read_or_refused_and_counted(folder, frame, channel, value):
    """A motion value of any kind: a number (non-finite ones counted, their joints marked invalid) or a
    FormatError; what is marked valid is finite, and ``meta`` counts what is not."""
    lines = VALID_BVH.splitlines()
    k = len(lines) - 3 + frame
    values = lines[k].split()
    values[channel] = value
    lines[k] = " ".join(values)
    tr = read_bounded(read_bvh, ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass"), folder / "v.bvh")
    if tr is not None:
        assert tr.meta["invalid_orientations"] == np.count_nonzero(~tr.orientation_valid)
        assert tr.meta["invalid_positions"] == np.count_nonzero(~tr.position_valid)
        assert np.isfinite(tr.orientations[tr.orientation_valid]).all()
        assert np.isfinite(tr.positions[tr.position_valid]).all()
