"""ISO/IEC 19794-2:2005 finger minutiae records (the "FMR" template integrators match).

One finger view, big-endian, as the standard lays it out (sec. 7):

- record header, 24 bytes: format identifier ``FMR\\0``, version `` 20\\0``, record length
  (4 bytes), capture equipment certification and ID (2; 0: not certified, unknown), image
  width and height in pixels (2 + 2), horizontal and vertical resolution in pixels per
  centimetre (2 + 2; 197 for 500 ppi), number of finger views (1), reserved (1);
- finger view header, 4 bytes: finger position (0 unknown), view number (high nibble) and
  impression type (low nibble), finger quality 0-100 (the print's NFIQ 2; 0 when it has
  none), number of minutiae;
- 6 bytes a minutia: type (2 bits: 01 ridge ending, 10 bifurcation) and x (14 bits), 2
  reserved bits and y (14 bits), angle in units of 360/256 degrees (counter-clockwise from
  +x), quality 1-100;
- extended data block length, 2 bytes (0: none).

nbis-py 0.1.3 writes a record it calls ISO/IEC 19794-2:2005 but leaves out the view header's
impression and quality bytes and the extended data length, and writes resolution 0; this
module writes the standard's layout from NBIS's minutiae instead.
"""

from __future__ import annotations

import struct

import numpy as np

from fingerps_recon.errors import RecordError
from fingerps_recon.records.print_minutiae import PrintMinutiae

#: Pixels per centimetre of a 500 ppi print (500 / 2.54, rounded as NBIS rounds it).
PPCM_500PPI = 197
#: ISO/IEC 19794-2:2005 impression type "live-scan rolled": the print is a rolled-equivalent
#: made from a live capture (the 2005 edition has no code for a contactless capture).
LIVE_SCAN_ROLLED = 1
#: The record's count of minutiae is one byte.
MAX_MINUTIAE = 255
HEADER_BYTES, VIEW_HEADER_BYTES, MINUTIA_BYTES, EXTENDED_LENGTH_BYTES = 24, 4, 6, 2


def iso_minutiae_record(minutiae: PrintMinutiae, *, finger_position: int = 0,
                        impression_type: int = LIVE_SCAN_ROLLED) -> bytes:
    """The ISO/IEC 19794-2:2005 record of one print's minutiae (module docstring).

    The best :data:`MAX_MINUTIAE` by quality are kept when there are more.

    Raises
    ------
    RecordError
        When a value does not fit its field (finger position 0-10, impression type 0-15,
        coordinates below 2^14).
    """
    if not 0 <= finger_position <= 10:
        raise RecordError(f"finger position {finger_position}: ISO/IEC 19794-2 codes are 0-10")
    if not 0 <= impression_type <= 15:
        raise RecordError(f"impression type {impression_type} does not fit its 4 bits")
    if max(minutiae.width, minutiae.height) >= 1 << 14:
        raise RecordError(f"a {minutiae.width} x {minutiae.height} px print does not fit the "
                          "record's 14-bit coordinates")
    keep = np.argsort(-minutiae.quality.astype(np.int64), kind="stable")[:MAX_MINUTIAE]
    keep.sort()
    n = keep.size
    length = HEADER_BYTES + VIEW_HEADER_BYTES + MINUTIA_BYTES * n + EXTENDED_LENGTH_BYTES
    header = b"FMR\x00" + b" 20\x00" + struct.pack(
        ">IHHHHHBB", length, 0, minutiae.width, minutiae.height, PPCM_500PPI, PPCM_500PPI, 1, 0)
    view = struct.pack(">BBBB", finger_position, impression_type,
                       int(np.clip(minutiae.nfiq2 or 0, 0, 100)), n)
    table = np.zeros(n, dtype=[("type_x", ">u2"), ("y", ">u2"), ("angle", "u1"),
                               ("quality", "u1")])
    table["type_x"] = (minutiae.kind[keep].astype(np.uint16) << 14) | minutiae.x_px[keep]
    table["y"] = minutiae.y_px[keep]
    table["angle"] = np.rint(minutiae.angle_deg[keep] * 256.0 / 360.0).astype(np.int64) % 256
    table["quality"] = minutiae.quality[keep]
    record = header + view + table.tobytes() + struct.pack(">H", 0)
    if len(record) != length:  # the layout above and the length field must agree
        raise RecordError(f"ISO record of {len(record)} bytes where its header says {length}")
    return record
