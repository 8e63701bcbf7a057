"""PLY files read so that what is read is what the file holds: the header is parsed here and
every element's count checked against the bytes that follow it before anything is
allocated, so a header that claims 10⁹ vertices in a file of 100 is refused at once instead
of allocating for them; a file cut short, or holding more than its header declares, is
refused naming the element and the figures; ASCII numbers that do not parse are refused.
Meshes and clouds in PLY are read here (not through Open3D, which reports such faults only
as a line on stdout and returns what it got).

Data are read vectorised: elements of scalar properties as one structured array; list
properties (a mesh's faces) under the hypothesis that every record holds as many items as the
first, which is verified; other lists (mixed polygons) through `plyfile`, record by record,
up to IRREGULAR_RECORDS records.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scanner.file_checks import MAX_FILE_BYTES, FileRefused, ascii_numbers, read_regular

MAX_HEADER_BYTES = 1 << 20
MAX_ASCII_BYTES = 256 * 1024 ** 2  # ASCII numbers parse to 8 bytes each: 4x the text at worst
IRREGULAR_RECORDS = 2_000_000  # records with lists of varying length are read one by one (plyfile): ~10 s at most
TRAILING_SLACK = 16  # bytes of white space a writer may leave after the data

TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
         "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
         "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class PlyProperty:
    name: str
    type: str  # numpy type code, e.g. "f4"; of the items for a list
    count_type: str | None = None  # a list's count type; None for a scalar


@dataclass(frozen=True)
class PlyElementSpec:
    name: str
    count: int
    properties: tuple[PlyProperty, ...]


@dataclass(frozen=True)
class PlyHeader:
    format: str
    elements: tuple[PlyElementSpec, ...]
    comments: tuple[str, ...]
    data_offset: int  # bytes of header

    def element(self, name: str) -> PlyElementSpec | None:
        return next((e for e in self.elements if e.name == name), None)


@dataclass(frozen=True, eq=False)
class PlyList:
    """A list property: every record's items, flat, and how many each record has."""

    counts: np.ndarray
    values: np.ndarray


Element = dict[str, "np.ndarray | PlyList"]


def _refuse(path: object, problem: str) -> FileRefused:
    return FileRefused(path, f"not a usable PLY file: {problem}")


def parse_header(path: object, data: bytes) -> PlyHeader:
    """The header at the start of `data` (the file's bytes), checked: magic, format, element
    and property lines, counts >= 0, known types, unique names."""
    if not data.startswith(b"ply\n") and not data.startswith(b"ply\r\n"):
        raise _refuse(path, "it does not start with 'ply'")
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise _refuse(path, f"no 'end_header' in its first {MAX_HEADER_BYTES // 1024} kB")
    eol = data.find(b"\n", end)
    if eol < 0:
        raise _refuse(path, "the header's last line has no line end")
    lines = data[:end].decode("latin-1").splitlines()[1:]
    fmt: str | None = None
    elements: list[PlyElementSpec] = []
    props: list[PlyProperty] = []
    comments: list[str] = []

    def close_element() -> None:
        if elements:
            last = elements.pop()
            elements.append(PlyElementSpec(last.name, last.count, tuple(props)))

    for n, line in enumerate(lines, 2):
        words = line.split()
        if not words or words[0] in ("obj_info",):
            continue
        if words[0] == "comment":
            comments.append(line.strip()[8:])
        elif words[0] == "format":
            if len(words) != 3 or words[1] not in FORMATS or words[2] != "1.0":
                raise _refuse(path, f"header line {n}: unknown format {' '.join(words[1:])!r}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise _refuse(path, f"header line {n}: 'element NAME COUNT' expected, got {line.strip()[:60]!r}")
            if any(e.name == words[1] for e in elements):
                raise _refuse(path, f"header line {n}: element '{words[1]}' declared twice")
            close_element()
            props = []
            elements.append(PlyElementSpec(words[1], int(words[2]), ()))
        elif words[0] == "property":
            if not elements:
                raise _refuse(path, f"header line {n}: a property before any element")
            if len(words) == 3 and words[1] in TYPES:
                prop = PlyProperty(words[2], TYPES[words[1]])
            elif len(words) == 5 and words[1] == "list" and words[2] in TYPES and words[3] in TYPES \
                    and TYPES[words[2]][0] in "iu":
                prop = PlyProperty(words[4], TYPES[words[3]], TYPES[words[2]])
            else:
                raise _refuse(path, f"header line {n}: unknown property {line.strip()[:60]!r}")
            if any(p.name == prop.name for p in props):
                raise _refuse(path, f"header line {n}: property '{prop.name}' declared twice")
            props.append(prop)
        else:
            raise _refuse(path, f"header line {n}: unknown keyword {words[0][:20]!r}")
    close_element()
    if fmt is None:
        raise _refuse(path, "no 'format' line in the header")
    return PlyHeader(fmt, tuple(elements), tuple(comments), eol + 1)


def read_header(path: str | Path) -> PlyHeader:
    """The header of a PLY file (only its first MAX_HEADER_BYTES are read)."""
    from scanner.file_checks import regular_size

    regular_size(path)
    with open(path, "rb") as f:
        return parse_header(path, f.read(MAX_HEADER_BYTES))


def read_ply(path: str | Path, *, limit: int = MAX_FILE_BYTES) -> tuple[PlyHeader, dict[str, Element]]:
    """(header, {element name: {property name: array or PlyList}}) of a PLY file, every
    count checked against the bytes the file holds (see the module docstring)."""
    data = read_regular(path, limit=limit)
    header = parse_header(path, data)
    if header.format == "ascii":
        if len(data) > MAX_ASCII_BYTES:
            raise _refuse(path, f"an ASCII PLY of {len(data) / 1e6:.0f} MB; ASCII is read up to "
                                f"{MAX_ASCII_BYTES / 1e6:.0f} MB (write it as binary)")
        return header, _read_ascii(path, header, data)
    return header, _read_binary(path, header, data)


def _min_record_bytes(e: PlyElementSpec, binary: bool) -> int:
    """The fewest bytes one record of `e` can take (an empty list is just its count)."""
    if binary:
        return sum(np.dtype(p.count_type or p.type).itemsize for p in e.properties)
    return 2 * len(e.properties)  # a digit and a separator each


def _check_counts(path: object, header: PlyHeader, available: int) -> None:
    """Refuse counts the remaining bytes cannot hold, before anything is allocated."""
    need = 0
    binary = header.format != "ascii"
    for e in header.elements:
        if e.count and not e.properties:
            raise _refuse(path, f"element '{e.name}' has {e.count} records but no properties")
        need += e.count * _min_record_bytes(e, binary)
        if need > available:
            raise _refuse(path, f"its header declares {e.count} '{e.name}' records, which need at least "
                                f"{need} bytes; the file holds {available} after its header (cut short, or a "
                                f"header that lies)")


def _uniform_dtype(e: PlyElementSpec, lengths: dict[str, int], order: str) -> np.dtype:
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
    for p in e.properties:
        if p.count_type is None:
            fields.append((p.name, order + p.type))
        else:
            fields.append((f"{p.name}#count", order + p.count_type))
            fields.append((p.name, order + p.type, (lengths[p.name],)))
    return np.dtype(fields)


def _read_binary(path: object, header: PlyHeader, data: bytes) -> dict[str, Element]:
    order = FORMATS[header.format]
    body = memoryview(data)[header.data_offset:]
    _check_counts(path, header, len(body))
    at = 0
    out: dict[str, Element] = {}
    for e in header.elements:
        lists = [p for p in e.properties if p.count_type is not None]
        lengths = {}
        if lists and e.count:  # the first record's list lengths, taken as every record's (checked below)
            pos = at
            for p in e.properties:
                if p.count_type is None:
                    pos += np.dtype(p.type).itemsize
                    continue
                size = np.dtype(p.count_type).itemsize
                if pos + size > len(body):
                    raise _refuse(path, f"cut short in the first '{e.name}' record")
                n = int(np.frombuffer(body, order + p.count_type, 1, pos)[0])
                if n < 0:
                    raise _refuse(path, f"the first '{e.name}' record has a list of {n} items")
                lengths[p.name] = n
                pos += size + n * np.dtype(p.type).itemsize
        dtype = _uniform_dtype(e, lengths, order)
        end = at + e.count * dtype.itemsize
        fit = min(e.count, (len(body) - at) // max(dtype.itemsize, 1))  # records the bytes left hold at that size
        rec = np.frombuffer(body, dtype, fit, at)
        uniform = all((rec[f"{p.name}#count"] == lengths[p.name]).all() for p in lists)
        if uniform and fit < e.count and (e.count - fit) * _min_record_bytes(e, True) > len(body) - at - rec.nbytes:
            raise _refuse(path, f"cut short in element '{e.name}': its first {fit} of {e.count} records fill the "
                                f"{len(body) - at} bytes left")
        uniform = uniform and fit == e.count
        if not uniform and lists:
            _irregular_within_bound(path, e)
            element, end = _read_irregular(path, header, e, body, at)
        elif not uniform:
            raise _refuse(path, f"cut short in element '{e.name}': {e.count} records of {dtype.itemsize} bytes "
                                f"need {e.count * dtype.itemsize}, {len(body) - at} bytes are left")
        else:
            element = {p.name: rec[p.name] if p.count_type is None else
                       PlyList(rec[f"{p.name}#count"], rec[p.name].reshape(-1)) for p in e.properties}
        out[e.name] = element
        at = end
    _check_trailing(path, bytes(body[at:at + TRAILING_SLACK + 1]), len(body) - at)
    return out


def _irregular_within_bound(path: object, e: PlyElementSpec) -> None:
    if e.count > IRREGULAR_RECORDS:
        raise _refuse(path, f"element '{e.name}' has lists of varying length in {e.count} records; such lists are "
                            f"read up to {IRREGULAR_RECORDS} records")


def _read_irregular(path: object, header: PlyHeader, e: PlyElementSpec, body: memoryview,
                    at: int) -> tuple[Element, int]:
    """An element whose lists vary in length, through plyfile (record by record; bounded by
    IRREGULAR_RECORDS), from byte `at` of the body; returns it and the byte after it."""
    import io

    from plyfile import PlyData, PlyElementParseError

    fmt = f"format {header.format} 1.0\n"
    props = "".join(f"property list {_ply_type(p.count_type)} {_ply_type(p.type)} {p.name}\n" if p.count_type
                    else f"property {_ply_type(p.type)} {p.name}\n" for p in e.properties)
    stub = f"ply\n{fmt}element {e.name} {e.count}\n{props}end_header\n".encode()
    stream = io.BytesIO(stub + bytes(body[at:]))
    try:
        ply = PlyData.read(stream)
    except (PlyElementParseError, ValueError, IndexError, EOFError) as exc:
        raise _refuse(path, str(exc).splitlines()[0][:160]) from None
    rec = ply[e.name].data
    element: Element = {}
    for p in e.properties:
        if p.count_type is None:
            element[p.name] = np.asarray(rec[p.name])
        else:
            items = list(rec[p.name])
            counts = np.fromiter((len(x) for x in items), np.int64, len(items))
            flat = np.concatenate(items).astype(p.type) if items else np.empty(0, p.type)
            element[p.name] = PlyList(counts, flat)
    return element, stream.tell() - len(stub) + at


def _ply_type(code: str | None) -> str:
    return {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
            "f4": "float", "f8": "double"}[code or ""]


def _check_trailing(path: object, tail: bytes, extra: int) -> None:
    if extra > TRAILING_SLACK or tail.strip(b" \t\r\n\0"):
        raise _refuse(path, f"{extra} bytes follow the last element its header declares (a header that "
                            f"declares fewer records than the file holds)")


def _read_ascii(path: object, header: PlyHeader, data: bytes) -> dict[str, Element]:
    body = data[header.data_offset:]
    _check_counts(path, header, len(body))
    tokens = ascii_numbers(path, body, "PLY file")
    at = 0
    out: dict[str, Element] = {}
    for e in header.elements:
        element, at = _ascii_element(path, e, tokens, at)
        out[e.name] = element
    if at != len(tokens):
        raise _refuse(path, f"{len(tokens) - at} numbers follow the last element its header declares (a header "
                            f"that declares fewer records than the file holds)")
    return out


def _ascii_element(path: object, e: PlyElementSpec, tokens: np.ndarray, at: int) -> tuple[Element, int]:
    """One ASCII element from tokens[at:], records of uniform list lengths (those of the
    first record, checked), else record by record (bounded by IRREGULAR_RECORDS)."""
    widths, pos = [], at
    for p in e.properties:  # the first record's layout
        if p.count_type is None:
            widths.append(1)
            pos += 1
            continue
        if pos >= len(tokens):
            raise _refuse(path, f"cut short in the first '{e.name}' record")
        n = tokens[pos]
        if not (n >= 0 and n == int(n)):
            raise _refuse(path, f"the first '{e.name}' record has a list count of {n}")
        widths.append(1 + int(n))
        pos += 1 + int(n)
    per = sum(widths)
    end = at + e.count * per
    if e.count == 0:
        return {p.name: np.empty(0, p.type) if p.count_type is None else
                PlyList(np.empty(0, np.int64), np.empty(0, p.type)) for p in e.properties}, at
    if end <= len(tokens):
        table = tokens[at:end].reshape(e.count, per)
        starts = np.cumsum([0] + widths[:-1])
        if all(p.count_type is None or (table[:, s] == w - 1).all() for p, s, w in zip(e.properties, starts, widths)):
            element: Element = {}
            for p, s, w in zip(e.properties, starts, widths):
                if p.count_type is None:
                    element[p.name] = _as_type(path, e, p, table[:, s])
                else:
                    element[p.name] = PlyList(table[:, s].astype(np.int64),
                                              _as_type(path, e, p, table[:, s + 1:s + w].reshape(-1)))
            return element, end
    if not any(p.count_type for p in e.properties):
        raise _refuse(path, f"cut short in element '{e.name}': {e.count} records of {per} numbers need "
                            f"{e.count * per}, {len(tokens) - at} are left")
    _irregular_within_bound(path, e)
    return _ascii_irregular(path, e, tokens, at)


def _ascii_irregular(path: object, e: PlyElementSpec, tokens: np.ndarray, at: int) -> tuple[Element, int]:
    columns: dict[str, list] = {p.name: [] for p in e.properties}
    counts: dict[str, list[int]] = {p.name: [] for p in e.properties if p.count_type}
    pos = at
    for _ in range(e.count):  # bounded by IRREGULAR_RECORDS: lists of varying length have no vectorised layout
        for p in e.properties:
            if pos >= len(tokens):
                raise _refuse(path, f"cut short in element '{e.name}'")
            if p.count_type is None:
                columns[p.name].append(tokens[pos])
                pos += 1
                continue
            n = tokens[pos]
            if not (n >= 0 and n == int(n)) or pos + 1 + int(n) > len(tokens):
                raise _refuse(path, f"a '{e.name}' record has a list count of {n} the file cannot hold")
            counts[p.name].append(int(n))
            columns[p.name].append(tokens[pos + 1:pos + 1 + int(n)])
            pos += 1 + int(n)
    element: Element = {}
    for p in e.properties:
        if p.count_type is None:
            element[p.name] = _as_type(path, e, p, np.asarray(columns[p.name]))
        else:
            flat = np.concatenate(columns[p.name]) if columns[p.name] else np.empty(0)
            element[p.name] = PlyList(np.asarray(counts[p.name], np.int64), _as_type(path, e, p, flat))
    return element, pos


def _as_type(path: object, e: PlyElementSpec, p: PlyProperty, values: np.ndarray) -> np.ndarray:
    """ASCII numbers as the property's type: integers must be whole and in range."""
    t = np.dtype(p.type)
    if t.kind == "f":
        return values.astype(t)
    info = np.iinfo(t)
    ok = np.isfinite(values) & (values == np.round(values)) & (values >= info.min) & (values <= info.max)
    if not ok.all():
        bad = values[~ok][0]
        raise _refuse(path, f"'{e.name}' property '{p.name}' is {t}, but holds {bad:g}")
    return values.astype(t)


# ------------------------------------------------------------------------------ clouds and meshes

def vertex_positions(path: object, element: Element) -> np.ndarray:
    """(N, 3) float64 x, y, z of a 'vertex' element, every one finite."""
    missing = [k for k in "xyz" if k not in element or isinstance(element[k], PlyList)]
    if missing:
        raise _refuse(path, f"its 'vertex' element has no scalar {', '.join(missing)}")
    points = np.stack([np.asarray(element[k], np.float64) for k in "xyz"], axis=1)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise _refuse(path, f"vertex {int(np.argmax(bad))} (of {len(points)}; {int(bad.sum())} in all) has a "
                            f"non-finite coordinate")
    return points


def face_triangles(path: object, element: Element, n_vertices: int) -> np.ndarray:
    """(M, 3) int64 vertex indices of a 'face' element's polygons, fanned into triangles;
    every index within 0 .. n_vertices - 1 and every polygon of 3 or more vertices."""
    faces = element.get("vertex_indices", element.get("vertex_index"))
    if not isinstance(faces, PlyList):
        raise _refuse(path, "its 'face' element has no 'vertex_indices' list")
    counts, flat = faces.counts.astype(np.int64), faces.values.astype(np.int64)
    if len(counts) and counts.min() < 3:
        raise _refuse(path, f"face {int(np.argmax(counts < 3))} has {int(counts.min())} vertices (a face needs 3)")
    bad = (flat < 0) | (flat >= n_vertices)
    if bad.any():
        raise _refuse(path, f"a face names vertex {int(flat[bad][0])}, but the file has {n_vertices} vertices "
                            f"(0 .. {n_vertices - 1})")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    fans = counts - 2  # triangles per polygon: (v0, vi, vi+1)
    first = np.repeat(starts, fans)
    step = np.arange(int(fans.sum())) - np.repeat(np.cumsum(fans) - fans, fans)
    return np.stack([flat[first], flat[first + step + 1], flat[first + step + 2]], axis=1)
