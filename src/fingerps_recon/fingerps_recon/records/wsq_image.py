"""WSQ images of a print: the FBI's wavelet scalar quantization for 500 ppi greyscale
fingerprints (IAFIS-IC-0110, "WSQ Gray-scale Fingerprint Image Compression Specification"),
the image that ANSI/NIST-ITL Type-14 records and EBTS transactions carry.

The codec is NIST's own (NBIS ``wsq`` library, as wrapped by the ``wsq`` package on PyPI);
this module only checks what goes in and what comes out. That wrapper compresses at its fixed
bit rate, 0.75 bits per pixel (about 15:1), and writes the resolution, 500 ppi, into the
file. Its Pillow plugin's encoder reads no pixels with the Pillow pinned here (the file it
writes decodes to a flat image), so the codec's functions are called directly.

NBIS's encoder can quantize a band-limited, noise-free pattern to a flat image; every file is
therefore decoded again before it is handed out, and refused (``WsqError``) unless it gives
back the image within :data:`MAX_RMS_ERROR` grey levels.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from fingerps_recon.errors import WsqError

#: Resolution of the images WSQ is specified for, pixels per inch.
WSQ_PPI = 500
#: Bit rate of the codec's output, bits per pixel (fixed by the wrapper).
WSQ_BITRATE = 0.75
#: Largest RMS difference, grey levels, between an image and its decoded WSQ file: a rolled
#: print of the simulated rig comes back within 7.2, NIST's own WSQ sample image within 5;
#: a file quantized flat is off by some 60.
MAX_RMS_ERROR = 12.0
#: Smallest side of an image given to the codec, pixels: below 32 NBIS's encoder fails, at 32
#: it returns a broken image.
MIN_SIDE_PX = 64


def _codec() -> ModuleType:
    """NBIS's WSQ codec (the C extension of the ``wsq`` package)."""
    try:
        import _wsq  # the wsq package's NBIS extension
    except ImportError as exc:
        raise WsqError(f"the WSQ codec is not installed ({exc}): pip install wsq") from exc
    return _wsq


def encode_wsq(image: np.ndarray) -> bytes:
    """A 500 ppi print (H, W) uint8, ridges dark, as a WSQ file at :data:`WSQ_BITRATE`.

    Raises
    ------
    WsqError
        When the image is not a 2-D uint8 image of at least :data:`MIN_SIDE_PX` a side, or
        the file does not decode back to it (the reason says which).
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise WsqError(f"a WSQ image is one 8-bit grey channel: got {img.dtype} {img.shape}; "
                       "give the print as (H, W) uint8")
    if min(img.shape) < MIN_SIDE_PX:
        raise WsqError(f"a WSQ image needs at least {MIN_SIDE_PX} px a side, got "
                       f"{img.shape[1]} x {img.shape[0]}")
    height, width = img.shape
    try:
        data = _codec().compress(np.ascontiguousarray(img).tobytes(), height, width,
                                 WSQ_BITRATE)
    except Exception as exc:  # the extension raises bare exceptions ("WSQ Error: -32")
        raise WsqError(f"NBIS's WSQ encoder refused the {width} x {height} print ({exc})"
                       ) from exc
    decoded, ppi = decode_wsq(data)
    if decoded.shape != img.shape or ppi != WSQ_PPI:
        raise WsqError(f"the WSQ codec wrote a {decoded.shape[1]} x {decoded.shape[0]} image "
                       f"at {ppi} ppi for a {width} x {height} one at {WSQ_PPI} ppi")
    rms = float(np.sqrt(np.mean((decoded.astype(np.float64) - img) ** 2)))
    if not rms <= MAX_RMS_ERROR:
        raise WsqError(f"the WSQ file does not give the print back (RMS difference {rms:.1f} "
                       f"grey levels, at most {MAX_RMS_ERROR:g}): no WSQ written; the PNG "
                       "print is unaffected")
    return data


def decode_wsq(data: bytes) -> tuple[np.ndarray, int]:
    """A WSQ file's image (H, W) uint8 and its resolution in ppi (-1 when it states none).

    Raises
    ------
    WsqError
        When ``data`` is not a WSQ file NBIS can decode.
    """
    if data[:2] != b"\xff\xa0":
        raise WsqError("not a WSQ file: it does not start with the SOI marker FFA0")
    try:
        pixels, width, height, ppi = _codec().decompress(bytes(data))
    except Exception as exc:  # the extension raises bare exceptions on damaged data
        raise WsqError(f"the WSQ file cannot be decoded ({exc})") from exc
    if len(pixels) != width * height:
        raise WsqError(f"the WSQ file decodes to {len(pixels)} bytes for {width} x {height} px")
    return np.frombuffer(pixels, np.uint8).reshape(height, width).copy(), int(ppi)
