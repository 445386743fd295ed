"""The PLY container: header parsing, element data as numpy structured arrays, and header writing.

Knows nothing about Gaussian splats; :mod:`.ply` (graphdeco layout) and :mod:`.compressed_ply`
(PlayCanvas layout) interpret the elements. Reading is vectorised (``np.frombuffer`` on the binary
body, one token split for ASCII); errors are :class:`SceneFormatError` naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...util.errors import SceneFormatError, with_path

# PLY scalar type names (both spellings of the spec) -> numpy type code.
PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
# numpy type code -> the name graphdeco / plyfile write.
PLY_TYPE_NAMES = {
    "i1": "char",
    "u1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}

FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_BYTES = 1 << 20
MAX_COUNT_DIGITS = 15  # an element count beyond 10^15 records cannot be in a file


@dataclass
class PlyProperty:
    name: str
    code: str  # numpy type code without byte order, e.g. "f4"
    is_list: bool = False


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list[PlyProperty]

    def property_names(self) -> list[str]:
        return [p.name for p in self.properties]


@dataclass
class PlyHeader:
    format: str  # "ascii", "binary_little_endian" or "binary_big_endian"
    elements: list[PlyElement]
    size: int  # bytes up to and including the end_header line

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def is_ply(data: bytes) -> bool:
    return data[:4] in (b"ply\n", b"ply\r")


def parse_header(path, data: bytes) -> PlyHeader:
    """Parse the header of a PLY file held in ``data``."""
    if not is_ply(data):
        raise SceneFormatError(with_path(path, "not a PLY file (it does not start with 'ply')"))
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise SceneFormatError(with_path(path, "PLY header has no 'end_header' line (truncated or corrupt header)"))
    newline = data.find(b"\n", end)
    if newline < 0:
        raise SceneFormatError(with_path(path, "truncated data: the file ends right after the PLY header"))
    lines = data[:end].decode("ascii", errors="replace").splitlines()[1:]
    fmt = None
    elements: list[PlyElement] = []
    for number, raw in enumerate(lines, start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue

        def bad(problem: str, number=number, raw=raw) -> SceneFormatError:
            line = raw.strip() if len(raw.strip()) <= 80 else raw.strip()[:77] + "..."
            return SceneFormatError(with_path(path, f"bad PLY header line {number} ({line!r}): {problem}"))

        keyword = words[0]
        if keyword == "format":
            if len(words) != 3 or words[1] not in FORMATS:
                raise bad("expected 'format ascii|binary_little_endian|binary_big_endian 1.0'")
            fmt = words[1]
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad("expected 'element NAME COUNT'")
            if len(words[2]) > MAX_COUNT_DIGITS:
                raise bad(f"element count of {len(words[2])} digits is beyond any file")
            if any(e.name == words[1] for e in elements):
                raise bad(f"duplicate element {words[1]!r}")
            elements.append(PlyElement(words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise bad("property before any element")
            if len(words) == 5 and words[1] == "list":
                if words[2] not in PLY_TYPES or words[3] not in PLY_TYPES:
                    raise bad("unknown list type")
                prop = PlyProperty(words[4], PLY_TYPES[words[3]], is_list=True)
            elif len(words) == 3 and words[1] in PLY_TYPES:
                prop = PlyProperty(words[2], PLY_TYPES[words[1]])
            else:
                raise bad("expected 'property TYPE NAME' with a known type")
            if prop.name in elements[-1].property_names():
                raise bad(f"duplicate property {prop.name!r}")
            elements[-1].properties.append(prop)
        else:
            raise bad(f"unknown keyword {keyword!r}")
    if fmt is None:
        raise SceneFormatError(with_path(path, "PLY header has no 'format' line"))
    return PlyHeader(fmt, elements, newline + 1)


def element_dtype(element: PlyElement, byte_order: str) -> np.dtype:
    return np.dtype([(p.name, byte_order + p.code) for p in element.properties])


def read_elements(path, data: bytes, header: PlyHeader, needed: set[str]) -> dict[str, np.ndarray]:
    """Structured arrays of the ``needed`` elements (all their properties), in the file's byte order.

    The data must have exactly the size the header declares. Elements after one with list properties
    (mesh faces) cannot be located; the file is rejected only if one of them is needed.
    """
    if header.format == "ascii":
        return _read_ascii(path, data, header, needed)
    byte_order = FORMATS[header.format]
    out: dict[str, np.ndarray] = {}
    offset = header.size
    for element in header.elements:
        if any(p.is_list for p in element.properties):
            _stop_at_list(path, element, needed - out.keys())
            return out
        dtype = element_dtype(element, byte_order)
        size = dtype.itemsize * element.count
        if offset + size > len(data):
            raise SceneFormatError(
                with_path(
                    path,
                    f"truncated data: the header declares {element.count} {element.name!r} records "
                    f"({size} bytes) but only {max(len(data) - offset, 0)} bytes remain",
                )
            )
        if element.name in needed:
            out[element.name] = np.frombuffer(data, dtype=dtype, count=element.count, offset=offset)
        offset += size
    if offset != len(data):
        raise SceneFormatError(
            with_path(
                path,
                f"header/size mismatch: the header declares {offset - header.size} bytes of data "
                f"but the file holds {len(data) - header.size}",
            )
        )
    return out


def _stop_at_list(path, element: PlyElement, missing: set[str]) -> None:
    """Elements after a list-property element cannot be located; fine only if none of them is needed."""
    if missing:
        raise SceneFormatError(
            with_path(
                path,
                f"PLY element {element.name!r} has list properties, so {', '.join(sorted(missing))} cannot be read",
            )
        )


def _read_ascii(path, data: bytes, header: PlyHeader, needed: set[str]) -> dict[str, np.ndarray]:
    lines = data[header.size :].split(b"\n")
    out: dict[str, np.ndarray] = {}
    start = 0
    for element in header.elements:
        if any(p.is_list for p in element.properties):
            _stop_at_list(path, element, needed - out.keys())
            return out
        block = lines[start : start + element.count]
        start += element.count
        if element.name not in needed:
            continue
        tokens = b" ".join(block).split()
        expected = element.count * len(element.properties)
        if len(block) < element.count or len(tokens) < expected:
            raise SceneFormatError(
                with_path(path, f"truncated data: fewer than {element.count} {element.name!r} lines in the ASCII body")
            )
        if len(tokens) != expected:
            raise SceneFormatError(
                with_path(
                    path,
                    f"header/size mismatch: {element.name!r} lines do not hold {len(element.properties)} values each",
                )
            )
        try:
            values = np.array(tokens, dtype=np.float64).reshape(element.count, len(element.properties))
        except ValueError:
            raise SceneFormatError(with_path(path, f"non-numeric value in the ASCII {element.name!r} data")) from None
        records = np.empty(element.count, dtype=element_dtype(element, "="))
        for j, prop in enumerate(element.properties):
            records[prop.name] = values[:, j]
        out[element.name] = records
    if any(line.strip() for line in lines[start:]):
        raise SceneFormatError(with_path(path, "header/size mismatch: more ASCII data lines than the header declares"))
    return out


def columns(records: np.ndarray, names: list[str], dtype=np.float32) -> np.ndarray:
    """[N, len(names)] array of the named fields of a structured array, in native byte order.

    When every field has the same type the records are viewed as one [N, P] matrix: adjacent names
    (the usual graphdeco case) are then one strided slice, others one gather. Mixed types are
    stacked field by field.
    """
    fields = records.dtype.fields
    all_names = records.dtype.names
    first = fields[all_names[0]][0]
    if (
        all(fields[name][0] == first for name in all_names)
        and records.dtype.itemsize == len(all_names) * first.itemsize
    ):
        matrix = records.view(first).reshape(len(records), len(all_names))
        index = [all_names.index(name) for name in names]
        if index == list(range(index[0], index[0] + len(index))):
            return matrix[:, index[0] : index[0] + len(index)].astype(dtype)
        return matrix[:, index].astype(dtype)
    return np.stack([records[name].astype(dtype) for name in names], axis=1)


def type_name(array: np.ndarray, path, name: str) -> str:
    """PLY type name for a per-splat array (int64 / bool are narrowed when their values fit)."""
    kind = array.dtype
    if kind == np.bool_:
        return "uchar"
    if kind.kind in "iu" and kind.itemsize == 8:
        info = np.iinfo(np.int32 if kind.kind == "i" else np.uint32)
        if array.size and (array.min() < info.min or array.max() > info.max):
            raise SceneFormatError(with_path(path, f"extra property {name!r} has 64-bit values that PLY cannot store"))
        return "int" if kind.kind == "i" else "uint"
    code = f"{kind.kind}{kind.itemsize}"
    if code not in PLY_TYPE_NAMES:
        raise SceneFormatError(with_path(path, f"extra property {name!r} has type {kind}, which PLY cannot store"))
    return PLY_TYPE_NAMES[code]


def header_bytes(elements: list[tuple[str, int, list[tuple[str, str]]]], comments: tuple[str, ...] = ()) -> bytes:
    """A binary little-endian header; ``elements`` is [(name, count, [(type name, property name)])]."""
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" for c in comments]
    for name, count, props in elements:
        lines.append(f"element {name} {count}")
        lines += [f"property {kind} {prop}" for kind, prop in props]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")
