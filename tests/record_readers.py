"""Readers of the exchange records written from the standards' layouts, independent of the
code that writes them (no import from ``fingerps_recon.records``, no nistitl).

- :func:`read_iso_19794_2_2005`: ISO/IEC 19794-2:2005 finger minutiae record, one view;
- :func:`read_ansi_nist`: ANSI/NIST-ITL 1-2011 traditional encoding, tagged records (Type-1,
  Type-9, Type-14): fields ``T.NNN:value`` split by GS (0x1D), subfields by RS (0x1E), items
  by US (0x1F), records ended by FS (0x1C); a record's x.001 LEN is its length in bytes,
  and its x.999 field (binary data) runs to the byte before its FS.
"""

from __future__ import annotations

import struct

FS, GS, RS, US = b"\x1c", b"\x1d", b"\x1e", b"\x1f"


def read_iso_19794_2_2005(data: bytes) -> dict:
    """The header, view and minutiae (x, y, type, angle byte, quality) of an FMR record."""
    assert data[:8] == b"FMR\x00 20\x00", data[:8]
    (length, equipment, width, height, res_x, res_y, views,
     reserved) = struct.unpack(">IHHHHHBB", data[8:24])
    assert length == len(data), (length, len(data))
    position, view_impression, quality, count = struct.unpack(">BBBB", data[24:28])
    minutiae = []
    for i in range(count):
        word1, word2, angle, q = struct.unpack(">HHBB", data[28 + 6 * i:34 + 6 * i])
        minutiae.append({"type": word1 >> 14, "x": word1 & 0x3FFF, "reserved": word2 >> 14,
                         "y": word2 & 0x3FFF, "angle": angle, "quality": q})
    end = 28 + 6 * count
    (extended,) = struct.unpack(">H", data[end:end + 2])
    assert end + 2 + extended == len(data)
    return {"equipment": equipment, "width": width, "height": height, "res_x": res_x,
            "res_y": res_y, "views": views, "reserved": reserved, "position": position,
            "view": view_impression >> 4, "impression": view_impression & 0x0F,
            "quality": quality, "minutiae": minutiae}


def read_ansi_nist(data: bytes) -> list[tuple[int, dict[int, bytes | list[list[str]]]]]:
    """The records of a transaction as (type, {field number: value}); ASCII values as
    subfields of items (``[['a', 'b'], ['c']]`` for ``a^b`` RS ``c``), x.999 as bytes."""
    records = []
    pos = 0
    while pos < len(data):
        header_end = data.index(GS, pos)
        tag, length = data[pos:header_end].split(b":")
        record_type, number = tag.split(b".")
        assert int(number) == 1, tag
        record = data[pos:pos + int(length)]
        assert record.endswith(FS), record[-8:]
        fields: dict[int, bytes | list[list[str]]] = {}
        body = record[:-1]
        binary_tag = b"%d.999:" % int(record_type)
        binary_at = body.find(binary_tag)
        if binary_at >= 0:
            fields[999] = body[binary_at + len(binary_tag):]
            body = body[:binary_at].rstrip(GS)
        for text in body.split(GS):
            field_tag, value = text.split(b":", 1)
            fields[int(field_tag.split(b".")[1])] = [
                [item.decode("latin-1") for item in sub.split(US)] for sub in value.split(RS)]
        records.append((int(record_type), fields))
        pos += int(length)
    return records


def scalar(fields: dict, number: int) -> str:
    """The single value of an ASCII field."""
    value = fields[number]
    assert len(value) == 1 and len(value[0]) == 1, value
    return value[0][0]
