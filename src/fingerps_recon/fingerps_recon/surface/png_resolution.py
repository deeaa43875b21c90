"""PNG files that say their resolution: the ``pHYs`` chunk (PNG specification, 11.3.5.3).

A fingerprint image is only usable at its scale: matchers, NIST's tools and image viewers
read the pixels per metre from ``pHYs`` (unit 1 = metre). OpenCV's PNG writer does not
write the chunk, so `png_with_resolution` inserts it right after ``IHDR`` (it must come
before the first ``IDAT``). 500 ppi = 19 685 pixels per metre.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

from fingerps_recon.errors import FingerpsReconError

METRES_PER_INCH = 0.0254
_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IHDR_END = len(_SIGNATURE) + 8 + 13 + 4  # length, type, 13 data bytes, CRC


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(
        ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_with_resolution(image: np.ndarray, ppi: float) -> bytes:
    """Encode ``image`` (uint8 grey or BGR) as PNG with a ``pHYs`` chunk of ``ppi``.

    Raises
    ------
    FingerpsReconError
        When OpenCV cannot encode the image or ``ppi`` is not positive.
    """
    if not ppi > 0:
        raise FingerpsReconError(f"resolution must be positive, got {ppi} ppi")
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise FingerpsReconError("OpenCV could not encode the image as PNG")
    data = encoded.tobytes()
    per_metre = round(ppi / METRES_PER_INCH)
    phys = _chunk(b"pHYs", struct.pack(">IIB", per_metre, per_metre, 1))
    return data[:_IHDR_END] + phys + data[_IHDR_END:]
