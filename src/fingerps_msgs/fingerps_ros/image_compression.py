"""Compressed images as ROS's image_transport plugins write them: PNG/JPEG and compressedDepth.

The ``data`` and ``format`` of a ``sensor_msgs/CompressedImage``, made and read back with
OpenCV exactly as ``compressed_image_transport`` and ``compressed_depth_image_transport``
(ros-perception/image_transport_plugins, the release Jazzy uses) make and read them, so any
ROS subscriber (``image_transport`` republish, rqt_image_view, Foxglove, rosbag tools)
decodes what fingerps publishes. No rclpy, no message types: arrays and bytes.

compressed (``compressed_publisher.cpp``)
    ``format`` = ``"<encoding>; <codec> compressed <target>"``. PNG keeps the bit depth:
    colour images are written as BGR (``"rgb8; png compressed bgr8"``, ``"rgb16; png
    compressed bgr16"``); grey ones as they are, with an empty target and so a trailing
    space (``"mono8; png compressed "``, ``"mono16; png compressed "``). JPEG is always 8-bit:
    ``"<encoding>; jpeg compressed bgr8"`` for colour, ``"...; jpeg compressed mono8"`` for
    grey; a 16-bit image is scaled by 255/65535 on the way (cv_bridge's conversion) and the
    decoder multiplies by 256, as upstream does (a 12-bit image in mono16 keeps 4 bits of
    its 12: use PNG for mono16).
compressedDepth (``codec.cpp``, ``compression_common.h``)
    32FC1 depth in metres. ``format`` = ``"32FC1; compressedDepth png"``; ``data`` = a
    12-byte ``ConfigHeader`` (int32 ``compressionFormat`` ``INV_DEPTH`` = 0, float32
    ``depthParam[2]`` = A, B; little-endian) + a 16-bit PNG of the quantized inverse depth
    q = trunc(A / z + B), A = z0 (z0 + 1) with z0 = ``depth_quantization``,
    B = 1 - A / ``depth_max``, all in float32 as upstream. 0 marks no depth (NaN, z >=
    depth_max, z <= 0, and - where upstream's cast would wrap - A / z + B >= 65536, i.e.
    z nearer than :attr:`DepthQuantization.nearest_m`). Decoding: z = A / (q - B), q = 0 ->
    NaN; the decoder reads A and B from the header, so any choice of the two parameters is
    decoded by every subscriber. One step of q at depth z is z^2 / (A - z) metres
    (:meth:`DepthQuantization.step_m`); the decoded depth lies within one step of the true
    one (truncation: never nearer).

Supported: compressed PNG/JPEG of mono8, mono16, rgb8, bgr8, rgb16, bgr16; compressedDepth
PNG of 32FC1. Not supported (a ``MessageError`` says so): upstream's TIFF format and
compressedDepth's RVL format and its 16UC1 (millimetre) input.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

from fingerps_ros.errors import MessageError

COMPRESSED_FORMATS = ("png", "jpeg")
"""Values of ``<base>.compressed.format`` fingerps encodes (upstream also has tiff)."""
DEPTH_FORMATS = ("png",)
"""Values of ``<base>.compressedDepth.format`` fingerps encodes (upstream also has rvl)."""
DEPTH_ENCODING = "32FC1"

INV_DEPTH = 0  # compression_common.h: enum compressionFormat { UNDEFINED = -1, INV_DEPTH }
_CONFIG_HEADER = struct.Struct("<iff")  # ConfigHeader: int32 format, float32 depthParam[2]
CONFIG_HEADER_BYTES = _CONFIG_HEADER.size  # 12
_UINT16_LIMIT = 65536.0

# encoding -> (dtype, channels, colour channel order or "")
_ENCODINGS: dict[str, tuple[np.dtype, int, str]] = {
    "mono8": (np.dtype(np.uint8), 1, ""),
    "mono16": (np.dtype(np.uint16), 1, ""),
    "rgb8": (np.dtype(np.uint8), 3, "rgb"),
    "bgr8": (np.dtype(np.uint8), 3, "bgr"),
    "rgb16": (np.dtype(np.uint16), 3, "rgb"),
    "bgr16": (np.dtype(np.uint16), 3, "bgr"),
}


@dataclass(frozen=True)
class DepthQuantization:
    """The inverse-depth quantization of compressedDepth (parameters ``depth_max``,
    ``depth_quantization`` of ``compressed_depth_image_transport``).

    Parameters
    ----------
    depth_max_m : float
        Depths at or beyond this (metres) are sent as no depth. > 0.
    depth_quantization : float
        z0 of A = z0 (z0 + 1); the larger, the finer the steps and the nearer the nearest
        depth that still fits in 16 bits moves away from the camera. > 0.

    fingerps's defaults (0.2 m, 50) fit the rig's working range in 16 bits: depths from
    :attr:`nearest_m` = 32.6 mm to 200 mm, in steps of 3.2 µm at the 90 mm working distance
    (0.4 µm at 33 mm, 15.7 µm at 200 mm), far finer than the 50 µm ridges. Upstream's
    defaults (10 m, 100) overflow 16 bits nearer than 0.152 m.
    """

    depth_max_m: float = 0.2
    depth_quantization: float = 50.0

    def __post_init__(self) -> None:
        for name in ("depth_max_m", "depth_quantization"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise MessageError(
                    f"compressedDepth {name} {value!r}: must be a finite number > 0")

    @property
    def a(self) -> np.float32:
        """A = z0 (z0 + 1), float32 as upstream computes it."""
        z0 = np.float32(self.depth_quantization)
        return np.float32(z0 * (z0 + np.float32(1.0)))

    @property
    def b(self) -> np.float32:
        """B = 1 - A / depth_max, float32 as upstream computes it."""
        return np.float32(np.float32(1.0) - self.a / np.float32(self.depth_max_m))

    @property
    def nearest_m(self) -> float:
        """The nearest depth that fits in 16 bits: A / (65536 - B), metres; nearer ones are
        sent as no depth."""
        return float(self.a) / (_UINT16_LIMIT - float(self.b))

    def step_m(self, depth_m: np.ndarray | float) -> np.ndarray | float:
        """Size of one quantization step at ``depth_m``: z^2 / (A - z), metres; the largest
        difference between a depth and its decoded value (up to float32 rounding)."""
        z = np.asarray(depth_m, dtype=np.float64)
        step = z * z / (float(self.a) - z)
        return float(step) if step.ndim == 0 else step

    def quantize(self, depth_m: np.ndarray) -> np.ndarray:
        """Quantized inverse depth (H, W) uint16 of depths (H, W) in metres, 0 = no depth.

        q = trunc(A / z + B) in float32 (codec.cpp); 0 where z is NaN, not > 0, not below
        ``depth_max_m``, or so near that q would not fit in 16 bits.
        """
        z = np.asarray(depth_m, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            x = self.a / z + self.b
            fits = (z > 0) & (z < np.float32(self.depth_max_m)) & (x >= 1) & (x < _UINT16_LIMIT)
        q = np.zeros(z.shape, dtype=np.uint16)
        q[fits] = x[fits].astype(np.uint16)  # truncation, as the C++ float -> ushort cast
        return q

    def dequantize(self, q: np.ndarray) -> np.ndarray:
        """Depths (H, W) float32 in metres of quantized inverse depths (H, W) uint16:
        A / (q - B) in float32, NaN where q = 0."""
        return _inverse_depth_to_depth(np.asarray(q), self.a, self.b)


def compressed_format(encoding: str, *, codec: str = "png") -> str:
    """The ``format`` string compressed_image_transport writes for an image of ``encoding``
    compressed with ``codec`` (``"png"`` or ``"jpeg"``), e.g. ``"rgb8; png compressed bgr8"``,
    ``"mono8; png compressed "`` (trailing space), ``"mono16; jpeg compressed mono8"``."""
    _dtype, _channels, order = _encoding(encoding)
    _check_codec(codec)
    if codec == "jpeg":
        target = "bgr8" if order else "mono8"
    else:
        target = f"bgr{_bit_depth(encoding)}" if order else ""
    return f"{encoding}; {codec} compressed {target}"


def encode_compressed(
    image: np.ndarray,
    encoding: str,
    *,
    codec: str = "png",
    png_level: int = 3,
    jpeg_quality: int = 95,
) -> tuple[str, bytes]:
    """Compress an image as compressed_image_transport does.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        The pixels, of the encoding's type (uint8 for ``*8``, uint16 for ``*16``; other
        integer types are refused rather than cast). Not modified.
    encoding : str
        Its ROS encoding: mono8, mono16, rgb8, bgr8, rgb16, bgr16.
    codec : str
        ``"png"`` (lossless, keeps 16 bits) or ``"jpeg"`` (lossy, 8 bits).
    png_level : int
        zlib level 0-9 (``<base>.compressed.png_level``).
    jpeg_quality : int
        1-100 (``<base>.compressed.jpeg_quality``).

    Returns
    -------
    format : str
        The CompressedImage ``format`` (:func:`compressed_format`).
    data : bytes
        The PNG or JPEG file.

    Raises
    ------
    MessageError
        An unsupported encoding or codec, an array that does not fit the encoding, a level
        or quality out of range.
    """
    dtype, channels, order = _encoding(encoding)
    _check_codec(codec)
    pixels = _checked_pixels(image, encoding, dtype, channels)
    if codec == "jpeg":
        if not 1 <= int(jpeg_quality) <= 100:
            raise MessageError(f"jpeg_quality {jpeg_quality}: must be 1..100")
        if dtype == np.uint16:  # cv_bridge's 16 -> 8 bit conversion: scale 255/65535
            pixels = np.rint(pixels * (255.0 / 65535.0)).astype(np.uint8)
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
        extension = ".jpg"
    else:
        if not 0 <= int(png_level) <= 9:
            raise MessageError(f"png_level {png_level}: must be 0..9")
        params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)]
        extension = ".png"
    if order == "rgb":
        pixels = pixels[..., ::-1]  # OpenCV writes BGR: the "compressed bgr" of the format
    ok, encoded = cv2.imencode(extension, np.ascontiguousarray(pixels), params)
    if not ok:
        raise MessageError(f"OpenCV could not encode the {encoding} image as {codec}")
    return compressed_format(encoding, codec=codec), encoded.tobytes()


def encode_compressed_depth(
    depth_m: np.ndarray,
    *,
    quantization: DepthQuantization = DepthQuantization(),
    codec: str = "png",
    png_level: int = 3,
) -> tuple[str, bytes]:
    """Compress a depth image as compressed_depth_image_transport does (32FC1, PNG).

    Parameters
    ----------
    depth_m : (H, W) float array
        Depth in metres along the optical axis, NaN where there is none (the ``depth``
        topic). Cast to float32 as the 32FC1 message holds it. Not modified.
    quantization : DepthQuantization
        ``depth_max`` and ``depth_quantization``.
    codec : str
        ``<base>.compressedDepth.format``: only ``"png"``.
    png_level : int
        zlib level 0-9.

    Returns
    -------
    format : str
        ``"32FC1; compressedDepth png"``.
    data : bytes
        12-byte ConfigHeader (INV_DEPTH, A, B) + PNG of the 16-bit quantized inverse depth
        (:meth:`DepthQuantization.quantize`).

    Raises
    ------
    MessageError
        Not a 2-D real array, an unsupported codec, a level out of range.
    """
    if codec not in DEPTH_FORMATS:
        raise MessageError(
            f"compressedDepth format {codec!r} is not supported: use one of "
            f"{', '.join(DEPTH_FORMATS)} (upstream's rvl is not implemented)")
    if not 0 <= int(png_level) <= 9:
        raise MessageError(f"png_level {png_level}: must be 0..9")
    depth = np.asarray(depth_m)
    if depth.ndim != 2 or depth.size == 0 or not (
            np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
        raise MessageError(
            f"compressedDepth needs a non-empty (H, W) array of depths in metres (32FC1), "
            f"got shape {depth.shape} {depth.dtype}")
    q = quantization.quantize(depth)
    ok, encoded = cv2.imencode(".png", q, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    if not ok:
        raise MessageError("OpenCV could not encode the inverse depth as png")
    header = _CONFIG_HEADER.pack(INV_DEPTH, quantization.a, quantization.b)
    return f"{DEPTH_ENCODING}; compressedDepth {codec}", header + encoded.tobytes()


def decode_compressed(format_string: str, data: bytes) -> tuple[np.ndarray, str]:
    """Decode a CompressedImage's ``format`` and ``data`` (compressed or compressedDepth)
    back to pixels, as the upstream subscribers do.

    Parameters
    ----------
    format_string : str
        The message's ``format``, e.g. ``"rgb8; png compressed bgr8"``,
        ``"32FC1; compressedDepth png"``; a format without ``;`` (old publishers) is decoded
        as mono8 or bgr8 by its channel count.
    data : bytes
        The message's ``data``.

    Returns
    -------
    image : (H, W) or (H, W, 3) array
        The pixels in the encoding's type and channel order (float32 metres, NaN = no
        depth, for compressedDepth).
    encoding : str
        The ROS encoding (the part of ``format`` before ``;``).

    Raises
    ------
    MessageError
        A format it cannot decode, data that is not an image of that format.
    """
    encoding, separator, rest = format_string.partition(";")
    if "compressedDepth" in rest:
        return _decode_depth(encoding, rest, bytes(data)), encoding
    buffer = np.frombuffer(bytes(data), dtype=np.uint8)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if buffer.size else None
    if image is None:
        raise MessageError(
            f"the data ({len(buffer)} bytes) of a {format_string!r} message is not an image "
            "OpenCV can decode")
    if not separator:  # older compressed_image_transport: no encoding in the format
        return image, ("mono8" if image.ndim == 2 else "bgr8")
    dtype, channels, order = _encoding(encoding)
    if channels == 3 and image.ndim == 3 and order == "rgb" and "compressed bgr" in rest:
        image = image[..., ::-1]
    if "jpeg" in rest and dtype == np.uint16:
        image = image.astype(np.uint16) * np.uint16(256)  # as compressed_subscriber.cpp
    if image.dtype != dtype or (image.ndim == 3) != (channels == 3):
        raise MessageError(
            f"a {format_string!r} message decodes to {image.dtype} with "
            f"{1 if image.ndim == 2 else image.shape[2]} channel(s), not {encoding}")
    return np.ascontiguousarray(image), encoding


def _decode_depth(encoding: str, rest: str, data: bytes) -> np.ndarray:
    if "compressedDepth png" not in rest and rest.strip() != "compressedDepth":
        raise MessageError(
            f"compressedDepth format {rest.strip()!r} is not supported: only png")
    if encoding != DEPTH_ENCODING:
        raise MessageError(
            f"compressedDepth of {encoding!r}: only {DEPTH_ENCODING} depth is supported")
    if len(data) <= CONFIG_HEADER_BYTES:
        raise MessageError(
            f"compressedDepth data of {len(data)} bytes: too short for the 12-byte header "
            "and an image")
    kind, a, b = _CONFIG_HEADER.unpack_from(data)
    if kind != INV_DEPTH:
        raise MessageError(
            f"compressedDepth header says compression format {kind}, not INV_DEPTH (0)")
    buffer = np.frombuffer(data, dtype=np.uint8, offset=CONFIG_HEADER_BYTES)
    q = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    if q is None or q.dtype != np.uint16 or q.ndim != 2:
        raise MessageError(
            "compressedDepth data after the header is not a 16-bit one-channel PNG")
    return _inverse_depth_to_depth(q, np.float32(a), np.float32(b))


def _inverse_depth_to_depth(q: np.ndarray, a: np.float32, b: np.float32) -> np.ndarray:
    """z = A / (q - B) in float32 (codec.cpp's decoder), NaN where q = 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = a / (q.astype(np.float32) - b)
    return np.where(q > 0, z, np.float32(np.nan)).astype(np.float32)


def _encoding(encoding: str) -> tuple[np.dtype, int, str]:
    if encoding not in _ENCODINGS:
        hint = (" (32FC1 depth goes on compressedDepth: encode_compressed_depth)"
                if encoding == DEPTH_ENCODING else "")
        raise MessageError(
            f"cannot compress a {encoding!r} image as png/jpeg{hint}; supported encodings: "
            f"{', '.join(_ENCODINGS)}")
    return _ENCODINGS[encoding]


def _bit_depth(encoding: str) -> int:
    return 8 * _ENCODINGS[encoding][0].itemsize


def _check_codec(codec: str) -> None:
    if codec not in COMPRESSED_FORMATS:
        raise MessageError(
            f"compressed format {codec!r} is not supported: use one of "
            f"{', '.join(COMPRESSED_FORMATS)} (upstream's tiff is not implemented)")


def _checked_pixels(image: np.ndarray, encoding: str, dtype: np.dtype,
                    channels: int) -> np.ndarray:
    pixels = np.asarray(image)
    shape_ok = (pixels.ndim == 2 and channels == 1) or (
        pixels.ndim == 3 and pixels.shape[2] == channels) or (
        pixels.ndim == 3 and channels == 1 and pixels.shape[2] == 1)
    if not shape_ok or pixels.shape[0] == 0 or pixels.shape[1] == 0:
        expected = "(H, W)" if channels == 1 else "(H, W, 3)"
        raise MessageError(
            f"an array of shape {pixels.shape} is not a {encoding} image: give {expected} "
            "with H, W > 0")
    if pixels.dtype != dtype:
        raise MessageError(
            f"a {encoding} image must be {dtype}, got {pixels.dtype}: convert it first "
            "(fingerps_ros.image_conversion gives the encoding's type)")
    return pixels.reshape(pixels.shape[:2]) if channels == 1 else pixels
