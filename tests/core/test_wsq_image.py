"""records.wsq_image: a print as a WSQ file, read back and checked against the WSQ format.

The file's structure is read here byte by byte from the specification (IAFIS-IC-0110:
markers FFA0 start of image, FFA2 start of frame with the height and width, FFA8 comments,
one of them NISTCOM with the resolution), independently of the codec; the pixels come back
through NBIS's decoder.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from rig_prints import true_rolled_print

from fingerps_recon.errors import WsqError
from fingerps_recon.records.wsq_image import (
    MAX_RMS_ERROR,
    MIN_SIDE_PX,
    WSQ_BITRATE,
    WSQ_PPI,
    decode_wsq,
    encode_wsq,
)


def _segments(data: bytes) -> dict[int, list[bytes]]:
    """The WSQ file's marker segments up to the first block: marker -> payloads."""
    assert data[:2] == b"\xff\xa0"  # SOI
    found: dict[int, list[bytes]] = {}
    at = 2
    while at < len(data):
        (marker,) = struct.unpack(">H", data[at:at + 2])
        (length,) = struct.unpack(">H", data[at + 2:at + 4])
        found.setdefault(marker, []).append(data[at + 4:at + 2 + length])
        if marker == 0xFFA3:  # start of block: entropy-coded data follows
            break
        at += 2 + length
    return found


@pytest.fixture(scope="module")
def finger_print() -> np.ndarray:
    return true_rolled_print(3)


def test_a_print_round_trips_with_the_format_s_fields(finger_print: np.ndarray) -> None:
    data = encode_wsq(finger_print)
    height, width = finger_print.shape
    segments = _segments(data)
    # Start of frame: black, white (1 byte each), height, width (2 bytes each), ...
    _, _, frame_height, frame_width = struct.unpack(">BBHH", segments[0xFFA2][0][:6])
    assert (frame_height, frame_width) == (height, width)
    comments = [c for c in segments.get(0xFFA8, []) if c.startswith(b"NIST_COM")]
    assert comments, "no NISTCOM comment"
    fields = dict(line.split(b" ", 1) for line in comments[0].split(b"\n")[1:] if b" " in line)
    assert int(fields[b"PPI"]) == WSQ_PPI
    assert (int(fields[b"PIX_WIDTH"]), int(fields[b"PIX_HEIGHT"])) == (width, height)
    # About the codec's bit rate (its headers and tables on top).
    assert len(data) * 8 / (height * width) == pytest.approx(WSQ_BITRATE, rel=0.35)
    decoded, ppi = decode_wsq(data)
    assert ppi == WSQ_PPI and decoded.shape == finger_print.shape
    rms = np.sqrt(np.mean((decoded.astype(np.float64) - finger_print) ** 2))
    print(f"\nWSQ of a {width}x{height} print: {len(data)} bytes, RMS {rms:.2f} grey levels")
    assert rms <= MAX_RMS_ERROR  # measured 7.2


@pytest.mark.parametrize(("image", "words"), [
    (np.zeros((200, 200), np.float32), "8-bit grey"),
    (np.zeros((200, 200, 3), np.uint8), "8-bit grey"),
    (np.zeros((MIN_SIDE_PX - 1, 200), np.uint8), f"{MIN_SIDE_PX} px a side"),
])
def test_what_is_not_a_print_image_is_refused(image: np.ndarray, words: str) -> None:
    with pytest.raises(WsqError, match=words):
        encode_wsq(image)


def test_a_file_that_does_not_give_the_image_back_is_refused() -> None:
    # NBIS quantizes a noise-free, band-limited pattern to a flat image: refused, not written.
    y, x = np.mgrid[0:400, 0:352]
    pattern = (128 + 100 * np.sin(x / 4.0 + y / 9.0)).astype(np.uint8)
    with pytest.raises(WsqError, match="does not give the print back"):
        encode_wsq(pattern)


def test_damaged_files_are_refused_with_the_reason(finger_print: np.ndarray) -> None:
    with pytest.raises(WsqError, match="SOI marker"):
        decode_wsq(b"\x89PNG\r\n")
    data = encode_wsq(finger_print)
    with pytest.raises(WsqError, match="cannot be decoded"):
        decode_wsq(data[:2] + b"\x00" * 64)
