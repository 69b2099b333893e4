"""Typed samples as MCAP messages with their schemas inside the file (ROS 1 message encoding).

Every sample dataclass of :mod:`dualhuman_builder.capture.samples` maps to a ROS 1 message
definition (``ros1msg`` schema, ``ros1`` message encoding) named ``dualhuman/<ClassName>``, built
from its fields — so the ``mcap`` CLI (``mcap cat --json``), Foxglove and the ROS 1 tooling decode
our takes without our code. ROS 1 serialisation is little-endian and packed: fixed-size fields as
they are, strings and arrays with a ``uint32`` length (count) prefix.

Field kinds and their ROS 1 types:

=====================  =========================================================================
``int``                ``int64``
``float``              ``float64``
``bool``               ``bool`` (one byte)
``str``                ``string`` (UTF-8)
``tuple[str, ...]``    ``string[]``
``numpy.ndarray``      ``float64[] NAME`` / ``int64[] NAME`` / ``bool[] NAME`` (flattened, C order)
                       plus ``uint32[] NAME__shape`` (its shape)
=====================  =========================================================================

An array's element type comes from the first sample of a channel (:func:`layout_for`); later
samples are cast to it. Values round-trip exactly (float64, int64), so a sample read back from a
take equals the one that was recorded. A channel's messages are read back as columns by
:func:`decode_channel`, which merges samples whose layout changes (an MVN prop added mid-take) by
name. Every length and count in a message is checked against its bytes before use: a message that
lies raises :class:`FormatError`.
"""

from __future__ import annotations

import dataclasses
import math
import operator
import struct
import typing
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Callable

import numpy as np

from dualhuman_builder.errors import FormatError

SCHEMA_ENCODING = "ros1msg"
MESSAGE_ENCODING = "ros1"
SCHEMA_PREFIX = "dualhuman/"

_ARRAY_TYPES = {"f": ("float64", "<f8"), "i": ("int64", "<i8"), "u": ("int64", "<i8"), "b": ("bool", "u1")}
_DTYPES = {"float64": "<f8", "int64": "<i8", "bool": "u1"}
_U32 = struct.Struct("<I")
_I64 = struct.Struct("<q")
_F64 = struct.Struct("<d")


@dataclass(frozen=True)
class FieldSpec:
    name: str
    kind: str  # int, float, bool, str, strs, array
    ros_type: str  # element type for arrays
    dtype: str | None = None  # numpy dtype of an array's elements on the wire


@dataclass(frozen=True)
class Layout:
    """How one sample class is laid out in a channel: ``schema_name``, ``definition`` (ros1msg
    text) and the fields in order."""

    cls: type
    schema_name: str
    fields: tuple[FieldSpec, ...]

    @property
    def definition(self) -> str:
        lines = []
        for f in self.fields:
            if f.kind == "array":
                lines += [f"{f.ros_type}[] {f.name}", f"uint32[] {f.name}__shape"]
            elif f.kind == "strs":
                lines.append(f"string[] {f.name}")
            else:
                lines.append(f"{f.ros_type} {f.name}")
        return "\n".join(lines) + "\n"


_SCALARS = {int: ("int", "int64"), float: ("float", "float64"), bool: ("bool", "bool"), str: ("str", "string")}


@lru_cache(maxsize=None)
def _field_kinds(cls: type) -> tuple[tuple[str, str, str], ...]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if t in _SCALARS:
            out.append((f.name, *_SCALARS[t]))
        elif t is np.ndarray:
            out.append((f.name, "array", ""))
        elif typing.get_origin(t) is tuple and typing.get_args(t) in ((str, ...),):
            out.append((f.name, "strs", "string"))
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: type {t} cannot be written to a take "
                            f"(use int, float, bool, str, tuple[str, ...] or numpy arrays)")
    return tuple(out)


def layout_for(sample) -> Layout:
    """The layout of ``sample``'s class, array element types taken from ``sample``."""
    cls = type(sample)
    fields = []
    for name, kind, ros in _field_kinds(cls):
        if kind == "array":
            arr = np.asarray(getattr(sample, name))
            ros, dtype = _ARRAY_TYPES.get(arr.dtype.kind, ("float64", "<f8"))
            fields.append(FieldSpec(name, kind, ros, dtype))
        else:
            fields.append(FieldSpec(name, kind, ros))
    return Layout(cls, SCHEMA_PREFIX + cls.__name__, tuple(fields))


_SCALAR_CODES = {"int": "q", "float": "d", "bool": "?"}


def _scalar_packer(run: list[FieldSpec]) -> Callable[[Any], bytes]:
    st = struct.Struct("<" + "".join(_SCALAR_CODES[f.kind] for f in run))
    get = operator.attrgetter(*(f.name for f in run))
    if len(run) == 1:
        return lambda s: st.pack(get(s))
    return lambda s: st.pack(*get(s))


def _field_groups(layout: Layout) -> list[tuple[str, Any]]:
    """The fields in order, runs of fixed-size scalars merged: ``("scalars", packer)`` or
    ``(kind, FieldSpec)`` for strings, string lists and arrays."""
    out: list[tuple[str, Any]] = []
    run: list[FieldSpec] = []
    for f in layout.fields:
        if f.kind in _SCALAR_CODES:
            run.append(f)
            continue
        if run:
            out.append(("scalars", _scalar_packer(run)))
            run = []
        out.append((f.kind, f))
    if run:
        out.append(("scalars", _scalar_packer(run)))
    return out


def make_encoder(layout: Layout) -> Callable[[Any], bytes]:
    """A function ``sample -> bytes`` for ``layout``, compiled once: runs of fixed-size scalar
    fields are packed by one ``struct`` call, arrays are copied only when not already
    little-endian and contiguous in the schema's element type."""
    ops: list[Callable[[Any], Any]] = []
    for kind, x in _field_groups(layout):
        if kind == "scalars":
            ops.append(x)
        elif kind == "str":
            ops.append(lambda s, get=operator.attrgetter(x.name): _str_bytes(get(s)))
        elif kind == "strs":
            ops.append(lambda s, get=operator.attrgetter(x.name): _strs_bytes(get(s)))
        else:
            ops.append(lambda s, get=operator.attrgetter(x.name), dt=np.dtype(x.dtype): _array_bytes(get(s), dt))

    def encode(sample) -> bytes:
        return b"".join([op(sample) for op in ops])

    return encode


def make_shaped_encoder(layout: Layout, example) -> Callable[[Any], bytes]:
    """Like :func:`make_encoder`, specialised to the array shapes and dtypes of ``example`` (a
    channel's first sample): each array's count and shape words are precomputed, so an array costs
    one ``tobytes()``. A sample whose arrays differ from the example is encoded by the general
    encoder — the bytes are the same either way."""
    general = make_encoder(layout)
    spec = {}
    for f in layout.fields:
        if f.kind == "array":
            a = np.asarray(getattr(example, f.name))
            if a.ndim >= 8:
                return general
            spec[f.name] = (a.shape, np.dtype(f.dtype).num, _U32.pack(a.size), _SHAPES[a.ndim].pack(a.ndim, *a.shape))
    if not spec:
        return general
    ops = [(kind, x if kind == "scalars" else x.name, spec.get(getattr(x, "name", None)))
           for kind, x in _field_groups(layout)]  # fmt: skip

    def encode(sample) -> bytes:
        parts = []
        for kind, x, arr in ops:
            if kind == "scalars":
                parts.append(x(sample))
            elif kind == "array":
                a = getattr(sample, x)
                shape, num, head, tail = arr
                if type(a) is not np.ndarray or a.shape != shape or a.dtype.num != num:
                    return general(sample)
                parts += (head, a.tobytes(), tail)
            elif kind == "str":
                parts.append(_str_bytes(getattr(sample, x)))
            else:
                parts.append(_strs_bytes(getattr(sample, x)))
        return b"".join(parts)

    return encode


def _str_bytes(v: str) -> bytes:
    raw = v.encode("utf-8")
    return _U32.pack(len(raw)) + raw


_STRS_CACHE: dict[tuple, bytes] = {}
_SHAPES = [struct.Struct(f"<{n + 1}I") for n in range(8)]


def _strs_bytes(v: tuple) -> bytes:
    # sample streams repeat the same name lists (segment names): encode each list once
    out = _STRS_CACHE.get(v)
    if out is None:
        out = _U32.pack(len(v)) + b"".join(_str_bytes(x) for x in v)
        if len(_STRS_CACHE) < 1024:
            _STRS_CACHE[v] = out
    return out


def _array_bytes(v, dt: np.dtype) -> bytes:
    arr = v if type(v) is np.ndarray else np.asarray(v)
    if arr.dtype.num != dt.num:
        arr = arr.astype(dt)
    shape = arr.shape
    n = len(shape)
    tail = _SHAPES[n].pack(n, *shape) if n < 8 else struct.pack(f"<{n + 1}I", n, *shape)
    return _U32.pack(arr.size) + arr.tobytes() + tail


def encode(layout: Layout, sample) -> bytes:
    """``sample`` serialised per ``layout`` (ROS 1, little-endian); see :func:`make_encoder`."""
    enc = _ENCODERS.get(layout)
    if enc is None:
        enc = _ENCODERS[layout] = make_encoder(layout)
    return enc(sample)


_ENCODERS: dict[Layout, Callable[[Any], bytes]] = {}


def parse_definition(schema_name: str, definition: str, classes: dict[str, type]) -> Layout:
    """The layout of a schema read from a take (the inverse of :attr:`Layout.definition`)."""
    if not schema_name.startswith(SCHEMA_PREFIX):
        raise FormatError(f"schema {schema_name!r} is not one of ours")
    cls = classes.get(schema_name[len(SCHEMA_PREFIX):])
    if cls is None:
        raise FormatError(f"schema {schema_name!r} names no known sample type",
                          fix="read the take with the toolkit version that wrote it")  # fmt: skip
    lines = [ln.split() for ln in definition.splitlines() if ln.strip()]
    fields = []
    for words in lines:
        if len(words) != 2:
            raise FormatError(f"schema {schema_name!r}: a line of {len(words)} words ({' '.join(words)[:60]!r}), "
                              "not TYPE NAME")  # fmt: skip
        typ, name = words
        if name.endswith("__shape"):
            continue
        if typ.endswith("[]"):
            base = typ[:-2]
            if base == "string":
                fields.append(FieldSpec(name, "strs", "string"))
            elif base in _DTYPES:
                fields.append(FieldSpec(name, "array", base, _DTYPES[base]))
            else:
                raise FormatError(f"schema {schema_name!r}: unsupported array type {typ!r}")
        else:
            kind = {"int64": "int", "float64": "float", "bool": "bool", "string": "str"}.get(typ)
            if kind is None:
                raise FormatError(f"schema {schema_name!r}: unsupported field type {typ!r}")
            fields.append(FieldSpec(name, kind, typ))
    names = [f.name for f in fields]
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [n for n in names if n not in known]
    required = [n for n, f in known.items() if n not in names and f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING]  # fmt: skip
    if unknown or required or len(set(names)) != len(names):
        raise FormatError(f"schema {schema_name!r} does not match {cls.__name__}: fields {names}",
                          fix="read the take with the toolkit version that wrote it")  # fmt: skip
    return Layout(cls, schema_name, tuple(fields))


_DIMS = [struct.Struct(f"<{n}I") for n in range(8)]
_NP = {k: np.dtype(k) for k in ("<f8", "<i8", "u1")}


def decode(layout: Layout, data: bytes | memoryview):
    """A sample from its ROS 1 bytes. Lengths are checked against the bytes present before any
    allocation; a short or overlong message raises :class:`FormatError`."""
    mv = memoryview(data)
    n = len(mv)
    pos = 0
    values = {}
    u32 = _U32.unpack_from
    try:
        for f in layout.fields:
            k = f.kind
            if k == "int":
                values[f.name] = _I64.unpack_from(mv, pos)[0]
                pos += 8
            elif k == "float":
                values[f.name] = _F64.unpack_from(mv, pos)[0]
                pos += 8
            elif k == "bool":
                values[f.name] = bool(mv[pos])
                pos += 1
            elif k == "str":
                m = u32(mv, pos)[0]
                pos += 4
                if pos + m > n:
                    raise FormatError(f"{layout.schema_name}.{f.name}: string of {m} bytes past the end")
                values[f.name] = str(mv[pos:pos + m], "utf-8")
                pos += m
            elif k == "strs":
                count = u32(mv, pos)[0]
                pos += 4
                if 4 * count > n - pos:  # each string needs at least its 4-byte length
                    raise FormatError(f"{layout.schema_name}.{f.name}: count {count} exceeds the message")
                out = []
                for _ in range(count):
                    m = u32(mv, pos)[0]
                    pos += 4
                    if pos + m > n:
                        raise FormatError(f"{layout.schema_name}.{f.name}: string of {m} bytes past the end")
                    out.append(str(mv[pos:pos + m], "utf-8"))
                    pos += m
                values[f.name] = tuple(out)
            else:
                dt = _NP[f.dtype]
                size = u32(mv, pos)[0]
                pos += 4
                nbytes = size * dt.itemsize
                if pos + nbytes + 4 > n:
                    raise FormatError(f"{layout.schema_name}.{f.name}: {size} values past the end")
                flat = np.frombuffer(mv, dtype=dt, count=size, offset=pos)
                pos += nbytes
                ndim = u32(mv, pos)[0]
                pos += 4
                if ndim >= 8 or pos + 4 * ndim > n:
                    raise FormatError(f"{layout.schema_name}.{f.name}: bad shape of {ndim} dimensions")
                shape = _DIMS[ndim].unpack_from(mv, pos)
                pos += 4 * ndim
                if math.prod(shape) != size:
                    raise FormatError(f"{layout.schema_name}.{f.name}: shape {shape} does not hold {size} values")
                if f.ros_type == "bool":
                    arr = flat.reshape(shape).astype(bool)
                elif f.ros_type == "int64":
                    arr = flat.reshape(shape).astype(np.int64)
                else:
                    arr = flat.reshape(shape).astype(np.float64)
                values[f.name] = arr
    except (struct.error, IndexError):
        raise FormatError(f"{layout.schema_name} message is truncated ({n} bytes)") from None
    except UnicodeDecodeError as e:
        raise FormatError(f"{layout.schema_name}: a string is not UTF-8 ({e})") from None
    if pos != n:
        raise FormatError(f"{layout.schema_name} message has {n - pos} bytes after its last field")
    try:
        return layout.cls(**values)
    except (TypeError, ValueError) as e:
        raise FormatError(f"{layout.schema_name}: the fields do not make a {layout.cls.__name__} ({e})") from None


def sample_classes() -> dict[str, type]:
    """Every sample dataclass of :mod:`dualhuman_builder.capture.samples`, by class name."""
    from dualhuman_builder.capture import samples

    return {name: obj for name, obj in vars(samples).items()
            if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__module__ == samples.__name__}


# ---------------------------------------------------------------------- columns
def message_dtype(layout: Layout, first: bytes | memoryview) -> np.dtype:
    """A structured dtype matching ``first`` byte for byte (strings and array headers included),
    for reading a channel whose messages all have the same length in one ``frombuffer``. Field
    ``NAME`` holds the value (arrays with their shape as a subarray), ``NAME__head`` / ``NAME__tail``
    the length and shape words, ``NAME__raw`` a string's bytes (compare across rows before use)."""
    mv = memoryview(first)
    pos = 0
    names, formats, offsets = [], [], []

    def put(name, fmt, size):
        nonlocal pos
        names.append(name)
        formats.append(fmt)
        offsets.append(pos)
        pos += size

    for f in layout.fields:
        k = f.kind
        if k in ("int", "float"):
            put(f.name, "<i8" if k == "int" else "<f8", 8)
        elif k == "bool":
            put(f.name, "u1", 1)
        elif k == "str":
            m = _U32.unpack_from(mv, pos)[0]
            put(f.name + "__raw", f"V{4 + m}", 4 + m)
        elif k == "strs":
            start = pos
            count = _U32.unpack_from(mv, pos)[0]
            p2 = pos + 4
            for _ in range(count):
                p2 += 4 + _U32.unpack_from(mv, p2)[0]
            put(f.name + "__raw", f"V{p2 - start}", p2 - start)
        else:
            size = _U32.unpack_from(mv, pos)[0]
            item = np.dtype(f.dtype).itemsize
            ndim = _U32.unpack_from(mv, pos + 4 + size * item)[0]
            shape = tuple(np.frombuffer(mv, "<u4", ndim, pos + 8 + size * item).tolist())
            put(f.name + "__head", "<u4", 4)
            put(f.name, (f.dtype, shape) if shape else f.dtype, size * item)
            put(f.name + "__tail", f"V{4 + 4 * ndim}", 4 + 4 * ndim)
    if pos != len(mv):
        raise FormatError(f"{layout.schema_name}: message of {len(mv)} bytes, fields cover {pos}")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": pos})


def decode_columns(layout: Layout, datas: list) -> dict[str, Any] | None:
    """All messages of one channel at once: ``{field: array (N, ...)}`` (strings: the one value
    every row shares). None when the messages differ in length, shape or strings (then decode them
    one by one)."""
    if not datas:
        return None
    blocks = []
    for d in datas:  # 2-D uint8 arrays (rows of equal-length messages) or single messages
        blocks.append(d if getattr(d, "ndim", 1) == 2 else np.frombuffer(d, dtype=np.uint8)[None, :])
    n0 = blocks[0].shape[1]
    if any(b.shape[1] != n0 for b in blocks):
        return None
    raw = np.ascontiguousarray(np.concatenate(blocks) if len(blocks) > 1 else blocks[0])
    dt = message_dtype(layout, raw[0].tobytes())
    rows = raw.view(dt).ravel()
    out: dict[str, Any] = {}
    for f in layout.fields:
        if f.kind in ("str", "strs"):
            col = rows[f.name + "__raw"]
            if (col == col[0]).all():
                out[f.name] = getattr(decode(layout, raw[0].tobytes()), f.name)
            elif f.kind == "str":  # same length, different text (e.g. time codes): an array of str
                width = col.dtype.itemsize
                as_bytes = np.ascontiguousarray(col).view(np.uint8).reshape(-1, width)
                if not (as_bytes[:, :4] == as_bytes[0, :4]).all():
                    return None
                text = np.ascontiguousarray(as_bytes[:, 4:]).view(f"S{width - 4}").ravel()
                try:
                    out[f.name] = np.char.decode(text, "utf-8")
                except UnicodeDecodeError:
                    return None
            else:
                return None
        elif f.kind == "array":
            head, tail = rows[f.name + "__head"], rows[f.name + "__tail"]
            if not ((head == head[0]).all() and (tail == tail[0]).all()):
                return None
            arr = rows[f.name]
            out[f.name] = arr.astype(bool) if f.ros_type == "bool" else np.ascontiguousarray(arr).astype(
                np.int64 if f.ros_type == "int64" else np.float64, copy=False)
        elif f.kind == "bool":
            out[f.name] = rows[f.name].astype(bool)
        else:
            out[f.name] = np.ascontiguousarray(rows[f.name])
    return out


# ---------------------------------------------------------------------- channels whose layout changes
@dataclass
class ChannelData:
    """The decoded samples of one channel as columns (see :func:`decode_channel`): ``count``
    samples; ``odd`` of them laid out otherwise than the channel's most common layout (another
    segment count, other names); ``skipped`` messages that do not decode, left out."""

    columns: dict[str, Any]
    count: int
    odd: int = 0
    skipped: int = 0


_FILL = {"float64": np.nan, "int64": 0, "bool": False}


def _rows(parts: list):
    """Each message of ``parts`` (2-D uint8 blocks of equal-length messages or single messages)."""
    for p in parts:
        if getattr(p, "ndim", 1) == 2:
            yield from (p[i].tobytes() for i in range(len(p)))
        else:
            yield p


def _stack(layout: Layout, samples: list) -> dict[str, Any]:
    """Columns of ``samples`` that share one layout (array shapes and string lists)."""
    cols: dict[str, Any] = {}
    for f in layout.fields:
        vals = [getattr(s, f.name) for s in samples]
        if f.kind == "array":
            cols[f.name] = np.stack(vals)
        elif f.kind == "strs":
            cols[f.name] = vals[0]
        elif f.kind == "str":
            cols[f.name] = vals[0] if all(v == vals[0] for v in vals) else np.asarray(vals)
        else:
            cols[f.name] = np.asarray(vals, dtype={"int": np.int64, "float": np.float64, "bool": bool}[f.kind])
    return cols


def _sample_signature(layout: Layout, s) -> tuple:
    return tuple(np.shape(getattr(s, f.name)) if f.kind == "array" else getattr(s, f.name)
                 for f in layout.fields if f.kind in ("array", "strs"))  # fmt: skip


def _cols_signature(layout: Layout, cols: dict) -> tuple:
    return tuple(np.shape(cols[f.name])[1:] if f.kind == "array" else cols[f.name]
                 for f in layout.fields if f.kind in ("array", "strs"))  # fmt: skip


def _name_keys(names: tuple) -> list[tuple[str, int]]:
    """``(name, occurrence)`` per entry, so that a name listed twice keeps two places."""
    seen: dict[str, int] = {}
    out = []
    for n in names:
        out.append((n, seen.get(n, 0)))
        seen[n] = seen.get(n, 0) + 1
    return out


def decode_channel(layout: Layout, datas: list) -> ChannelData:
    """Every message of one channel as columns, whatever the layout of each.

    Messages of one layout (the usual case) come back as :func:`decode_columns` gives them:
    ``(N, ...)`` arrays, strings shared by every sample as one value. When the layout changes
    within the channel (an MVN prop added mid-take: 23 segments, then 24; one stray datagram with
    another segment count), the samples are merged so that no value moves to another name:

    * an array whose first axis is indexed by the string list before it (``segment_names`` for
      ``orientations`` and ``positions``) is aligned **by name**: the list becomes the union of
      every sample's names, the channel's most common list first (so a suit's 23 body segments keep
      their places and a prop's segments follow), and ``NAME__present (N, U)`` says which entries
      each sample carried; absent entries are NaN (float), 0 (int) or False (bool);
    * another array whose shape changes is padded to the widest shape the same way, with
      ``FIELD__shape (N, ndim)`` the shape of each sample (-1 for a sample of another rank, whose
      values are all absent);
    * a string list that changes and indexes no array becomes an object array of tuples ``(N,)``.

    Messages that do not decode (a damaged or forged message) are counted in ``skipped`` and left
    out, and so are samples whose layout would make the merged columns more than
    :data:`MERGE_GROWTH` times the channel's bytes (every sample naming other segments); ``odd``
    counts the samples laid out otherwise than the most common layout."""
    groups: dict[int, tuple[list[int], list[int], list]] = {}
    total = 0
    for d in datas:
        n, width = (d.shape[0], d.shape[1]) if getattr(d, "ndim", 1) == 2 else (1, len(d))
        starts, counts, parts = groups.setdefault(width, ([], [], []))
        starts.append(total)
        counts.append(n)
        parts.append(d)
        total += n
    subs: list[tuple[np.ndarray, dict]] = []
    skipped = 0
    for starts, counts, parts in groups.values():
        if len(groups) == 1:
            positions = np.arange(total)
        else:
            c = np.asarray(counts)
            positions = np.repeat(np.asarray(starts) - np.cumsum(c) + c, c) + np.arange(int(c.sum()))
        cols = None
        try:
            decode(layout, next(_rows(parts[:1])))  # the first message's structure, checked before the fast path
            cols = decode_columns(layout, parts)
        except FormatError:
            cols = None
        if cols is not None:
            subs.append((positions, cols))
            continue
        by_sig: dict[tuple, tuple[list[int], list]] = {}
        for p, data in zip(positions.tolist(), _rows(parts)):
            try:
                s = decode(layout, data)
            except FormatError:
                skipped += 1
                continue
            ps, ss = by_sig.setdefault(_sample_signature(layout, s), ([], []))
            ps.append(p)
            ss.append(s)
        subs += [(np.asarray(ps, dtype=np.int64), _stack(layout, ss)) for ps, ss in by_sig.values()]
    if len(subs) > 1:
        nbytes = sum(d.size if getattr(d, "ndim", 1) == 2 else len(d) for d in datas)
        subs, dropped = _admit(layout, subs, MERGE_GROWTH * nbytes + (16 << 20))
        skipped += dropped
    return _merge(layout, subs, skipped)


#: How many times the bytes of its messages the merged columns of a channel whose layout changes may
#: take (padding and aligning by name): a channel whose every sample names other segments would
#: otherwise grow with the square of its length.
MERGE_GROWTH = 4


def _admit(layout: Layout, subs: list[tuple[np.ndarray, dict]], limit: int) -> tuple[list, int]:
    """The groups of samples to merge, the most common layout's first, then in order of appearance,
    each admitted while the merged columns stay under ``limit`` bytes; returns them and the number of
    samples left out."""
    sizes: dict[tuple, int] = {}
    for p, c in subs:
        sig = _cols_signature(layout, c)
        sizes[sig] = sizes.get(sig, 0) + len(p)
    main = max(sizes, key=lambda k: sizes[k])
    order = sorted(range(len(subs)), key=lambda i: (_cols_signature(layout, subs[i][1]) != main, int(subs[i][0].min())))
    names: dict[str, set] = {f.name: set() for f in layout.fields if f.kind == "strs"}
    widest: dict[str, list[int]] = {}
    before = {}
    last = None
    for f in layout.fields:
        before[f.name] = last
        if f.kind == "strs":
            last = f.name
    kept, rows, dropped = [], 0, 0
    for i in order:
        p, c = subs[i]
        new = {k: set(_name_keys(c[k])) - v for k, v in names.items()}
        union = {k: len(v) + len(new[k]) for k, v in names.items()}
        trial_widest = {}
        per_row = sum(union.values())
        for f in layout.fields:
            if f.kind != "array":
                continue
            shape = list(c[f.name].shape[1:])
            w = widest.get(f.name, shape)
            w = [max(a, b) for a, b in zip(w, shape)] + (w[len(shape):] if len(w) > len(shape) else shape[len(w):])
            trial_widest[f.name] = w
            rest = int(np.prod(w[1:], dtype=np.int64)) if len(w) > 1 else 1
            u = union[before[f.name]] if before[f.name] else 0
            per_row += 8 * max(int(np.prod(w, dtype=np.int64)), u * rest)
        if kept and (rows + len(p)) * per_row > limit:
            dropped += len(p)
            continue
        kept.append(subs[i])
        rows += len(p)
        for k, v in new.items():
            names[k] |= v
        widest = trial_widest
    return kept, dropped


def _merge(layout: Layout, subs: list[tuple[np.ndarray, dict]], skipped: int) -> ChannelData:
    """One set of columns from groups of samples that each share a layout (see :func:`decode_channel`)."""
    if not subs:
        return ChannelData({}, 0, 0, skipped)
    order = np.sort(np.concatenate([p for p, _ in subs]))
    N = len(order)
    if len(subs) == 1:
        return ChannelData(subs[0][1], N, 0, skipped)
    ranks = [np.searchsorted(order, p) for p, _ in subs]
    sigs = [_cols_signature(layout, c) for _, c in subs]
    weight: dict[tuple, int] = {}
    first: dict[tuple, int] = {}
    for sig, r in zip(sigs, ranks):
        weight[sig] = weight.get(sig, 0) + len(r)
        first[sig] = min(first.get(sig, N), int(r.min()))
    main_sig = max(weight, key=lambda k: (weight[k], -first[k]))
    # the most common layout first, then the others in order of appearance
    seq = sorted(range(len(subs)), key=lambda i: (sigs[i] != main_sig, int(ranks[i].min())))
    out: dict[str, Any] = {}
    names_before: dict[str, FieldSpec | None] = {}
    last_strs = None
    for f in layout.fields:
        names_before[f.name] = last_strs
        if f.kind == "strs":
            last_strs = f
    aligned: dict[str, tuple] = {}  # strs field -> (union names, {sub: column indices})
    for f in layout.fields:
        if f.kind != "array":
            continue
        nf = names_before[f.name]
        if nf is None or all(subs[i][1][nf.name] == subs[seq[0]][1][nf.name] for i in seq):
            continue
        if not all(subs[i][1][f.name].ndim >= 2 and subs[i][1][f.name].shape[1] == len(subs[i][1][nf.name])
                   for i in seq):  # fmt: skip
            continue
        if nf.name not in aligned:
            index: dict[tuple[str, int], int] = {}
            where = {}
            for i in seq:
                keys = _name_keys(subs[i][1][nf.name])
                for k in keys:
                    index.setdefault(k, len(index))
                where[i] = np.asarray([index[k] for k in keys], dtype=np.int64)
            aligned[nf.name] = (tuple(k[0] for k in index), where)
        aligned.setdefault(f.name, aligned[nf.name])
    for f in layout.fields:
        cols = [subs[i][1][f.name] for i in range(len(subs))]
        if f.kind in ("int", "float", "bool"):
            col = np.empty(N, dtype=cols[seq[0]].dtype)
            for r, c in zip(ranks, cols):
                col[r] = c
            out[f.name] = col
        elif f.kind == "str":
            if all(isinstance(c, str) for c in cols) and len(set(cols)) == 1:
                out[f.name] = cols[0]
            else:
                col = np.empty(N, dtype=object)
                for r, c in zip(ranks, cols):
                    col[r] = c
                out[f.name] = np.asarray(col.tolist(), dtype=str)
        elif f.kind == "strs":
            if f.name in aligned:
                union, where = aligned[f.name]
                present = np.zeros((N, len(union)), dtype=bool)
                for i, r in enumerate(ranks):
                    present[r[:, None], where[i][None, :]] = True
                out[f.name] = union
                out[f.name + "__present"] = present
            elif len(set(cols)) == 1:
                out[f.name] = cols[0]
            else:
                col = np.empty(N, dtype=object)
                for r, c in zip(ranks, cols):
                    for k in r.tolist():
                        col[k] = c
                out[f.name] = col
        else:
            main = cols[seq[0]]
            fill = _FILL[f.ros_type]
            if f.name in aligned:
                union, where = aligned[f.name]
                col = np.full((N, len(union), *main.shape[2:]), fill, dtype=main.dtype)
                for i, (r, c) in enumerate(zip(ranks, cols)):
                    if c.shape[2:] == main.shape[2:]:
                        col[r[:, None], where[i][None, :]] = c
                out[f.name] = col
            elif len({c.shape[1:] for c in cols}) == 1:
                col = np.empty((N, *main.shape[1:]), dtype=main.dtype)
                for r, c in zip(ranks, cols):
                    col[r] = c
                out[f.name] = col
            else:
                same_rank = [c for c in cols if c.ndim == main.ndim]
                widest = tuple(int(max(c.shape[k] for c in same_rank)) for k in range(1, main.ndim))
                col = np.full((N, *widest), fill, dtype=main.dtype)
                shapes = np.full((N, main.ndim - 1), -1, dtype=np.int64)
                for r, c in zip(ranks, cols):
                    if c.ndim == main.ndim:
                        col[(r, *(slice(0, k) for k in c.shape[1:]))] = c
                        shapes[r] = c.shape[1:]
                out[f.name] = col
                out[f.name + "__shape"] = shapes
    return ChannelData(out, N, N - weight[main_sig], skipped)
