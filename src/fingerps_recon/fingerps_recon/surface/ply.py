"""PLY point clouds: a binary little-endian writer and a general reader.

The writer stores one ``vertex`` element with float32 ``x y z``, optionally ``intensity``
and ``nx ny nz``. The reader parses any PLY 1.0 header (ascii, binary_little_endian,
binary_big_endian; scalar and list properties; any element order) and returns the vertex
element.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

from fingerps_recon.errors import FingerpsReconError

# PLY scalar type names (both spellings of the PLY specification) -> numpy type codes.
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def write_ply(
    path: str | os.PathLike | BinaryIO,
    points: np.ndarray,
    *,
    intensity: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> None:
    """Write points as a binary little-endian PLY file.

    Parameters
    ----------
    path : str, path-like or binary file object
        Destination; a file object is written to and left open.
    points : (N, 3) float
        Positions, stored as float32 ``x y z`` (metres, optical frame by convention).
    intensity : (N,) float, optional
        Stored as float32 ``intensity``.
    normals : (N, 3) float, optional
        Stored as float32 ``nx ny nz``.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FingerpsReconError(f"points must have shape (N, 3), got {pts.shape}")
    count = pts.shape[0]
    columns: list[tuple[str, np.ndarray]] = [
        ("x", pts[:, 0]), ("y", pts[:, 1]), ("z", pts[:, 2])
    ]  # fmt: skip
    if intensity is not None:
        inten = np.asarray(intensity)
        if inten.shape != (count,):
            raise FingerpsReconError(
                f"intensity must have shape (N,) = ({count},), got {inten.shape}"
            )
        columns.append(("intensity", inten))
    if normals is not None:
        nrm = np.asarray(normals)
        if nrm.shape != (count, 3):
            raise FingerpsReconError(
                f"normals must have shape (N, 3) = ({count}, 3), got {nrm.shape}"
            )
        columns += [("nx", nrm[:, 0]), ("ny", nrm[:, 1]), ("nz", nrm[:, 2])]

    record = np.empty(count, dtype=[(name, "<f4") for name, _ in columns])
    for name, values in columns:
        record[name] = values
    header = ["ply", "format binary_little_endian 1.0", "comment written by fingerps_recon"]
    header.append(f"element vertex {count}")
    header += [f"property float {name}" for name, _ in columns]
    header.append("end_header")
    payload = ("\n".join(header) + "\n").encode("ascii") + record.tobytes()

    if hasattr(path, "write"):
        path.write(payload)
    else:
        with open(path, "wb") as f:
            f.write(payload)


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]]  # (name, value type, list count type)


def read_ply(path: str | os.PathLike | BinaryIO) -> dict[str, np.ndarray]:
    """Read the vertex element of a PLY file.

    Parameters
    ----------
    path : str, path-like or binary file object

    Returns
    -------
    data : dict of str to ndarray
        ``"points"`` (N, 3) from ``x y z``; ``"normals"`` (N, 3) if ``nx ny nz`` are present;
        every other scalar vertex property under its own name, shape (N,) (e.g.
        ``"intensity"``). Arrays keep the file's types, in native byte order.

    Raises
    ------
    FingerpsReconError
        If the file is not a valid PLY file or has no vertex element with x, y, z.
    """
    if hasattr(path, "read"):
        return _read(path)
    with open(path, "rb") as f:
        return _read(f)


def _read(f: BinaryIO) -> dict[str, np.ndarray]:
    fmt, elements = _parse_header(f)
    data: dict[str, np.ndarray] = {}
    for element in elements:
        table = _read_element(f, fmt, element)
        if element.name == "vertex":
            data = table
    missing = [c for c in ("x", "y", "z") if c not in data]
    if missing:
        raise FingerpsReconError(f"PLY file has no vertex properties {missing}")
    result = {"points": np.stack([data.pop(c) for c in ("x", "y", "z")], axis=1)}
    if all(c in data for c in ("nx", "ny", "nz")):
        result["normals"] = np.stack([data.pop(c) for c in ("nx", "ny", "nz")], axis=1)
    result.update(data)
    return result


def _parse_header(f: BinaryIO) -> tuple[str, list[_Element]]:
    magic = f.readline()
    if magic.rstrip(b"\r\n") != b"ply":
        raise FingerpsReconError("not a PLY file (the first line is not 'ply')")
    fmt = None
    elements: list[_Element] = []
    while True:
        raw = f.readline()
        if not raw:
            raise FingerpsReconError("PLY header ends without 'end_header'")
        words = raw.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "end_header":
            break
        if keyword == "format":
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise FingerpsReconError(f"unsupported PLY format line: {raw!r}")
            fmt = words[1]
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise FingerpsReconError(f"bad PLY element line: {raw!r}")
            elements.append(_Element(words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise FingerpsReconError("PLY property before any element")
            if len(words) == 5 and words[1] == "list":
                count_type, value_type, name = words[2:]
                _check_type(count_type, raw)
                _check_type(value_type, raw)
                elements[-1].properties.append((name, value_type, count_type))
            elif len(words) == 3:
                _check_type(words[1], raw)
                elements[-1].properties.append((words[2], words[1], None))
            else:
                raise FingerpsReconError(f"bad PLY property line: {raw!r}")
        else:
            raise FingerpsReconError(f"unknown PLY header keyword in line {raw!r}")
    if fmt is None:
        raise FingerpsReconError("PLY header has no format line")
    return fmt, elements


def _check_type(name: str, line: bytes) -> None:
    if name not in _PLY_TYPES:
        raise FingerpsReconError(f"unknown PLY type {name!r} in line {line!r}")


def _read_element(f: BinaryIO, fmt: str, element: _Element) -> dict[str, np.ndarray]:
    """Read one element's rows; list properties come back as 1-D object arrays of arrays."""
    byte_order = _FORMATS[fmt]
    has_list = any(count_type is not None for _, _, count_type in element.properties)
    if fmt == "ascii":
        rows = [f.readline().split() for _ in range(element.count)]
        if element.count and not rows[-1]:
            raise FingerpsReconError(f"PLY file ends inside element {element.name!r}")
        return _columns_from_ascii(rows, element)
    if not has_list:
        dtype = np.dtype([(n, byte_order + _PLY_TYPES[t]) for n, t, _ in element.properties])
        buf = f.read(dtype.itemsize * element.count)
        if len(buf) != dtype.itemsize * element.count:
            raise FingerpsReconError(f"PLY file ends inside element {element.name!r}")
        table = np.frombuffer(buf, dtype=dtype, count=element.count)
        return {n: table[n].astype(table[n].dtype.newbyteorder("=")) for n in table.dtype.names}
    # Elements with list properties (e.g. faces) have variable-length rows.
    out: dict[str, list] = {n: [] for n, _, _ in element.properties}
    for _ in range(element.count):
        for name, value_type, count_type in element.properties:
            if count_type is None:
                out[name].append(_read_scalars(f, byte_order + _PLY_TYPES[value_type], 1)[0])
            else:
                length = int(_read_scalars(f, byte_order + _PLY_TYPES[count_type], 1)[0])
                out[name].append(_read_scalars(f, byte_order + _PLY_TYPES[value_type], length))
    return {n: _as_array(v) for n, v in out.items()}


def _read_scalars(f: BinaryIO, type_code: str, count: int) -> np.ndarray:
    dtype = np.dtype(type_code)
    buf = f.read(dtype.itemsize * count)
    if len(buf) != dtype.itemsize * count:
        raise FingerpsReconError("PLY file ends inside its data")
    return np.frombuffer(buf, dtype=dtype).astype(dtype.newbyteorder("="))


def _columns_from_ascii(rows: list[list[bytes]], element: _Element) -> dict[str, np.ndarray]:
    out: dict[str, list] = {n: [] for n, _, _ in element.properties}
    for row in rows:
        pos = 0
        for name, value_type, count_type in element.properties:
            try:
                if count_type is None:
                    out[name].append(float(row[pos]))
                    pos += 1
                else:
                    length = int(row[pos])
                    out[name].append(
                        np.array([float(x) for x in row[pos + 1 : pos + 1 + length]]).astype(
                            _PLY_TYPES[value_type]
                        )
                    )
                    pos += 1 + length
            except (IndexError, ValueError):
                raise FingerpsReconError(
                    f"bad ascii PLY row in element {element.name!r}: {row!r}"
                ) from None
    table = {}
    for name, value_type, count_type in element.properties:
        if count_type is None:
            table[name] = np.array(out[name], dtype=np.float64).astype(_PLY_TYPES[value_type])
        else:
            table[name] = _as_array(out[name])
    return table


def _as_array(values: list) -> np.ndarray:
    """Scalars to a 1-D array; variable-length lists to a 1-D object array."""
    if values and isinstance(values[0], np.ndarray):
        arr = np.empty(len(values), dtype=object)
        arr[:] = values
        return arr
    return np.asarray(values)
