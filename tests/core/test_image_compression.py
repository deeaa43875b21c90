"""image_compression: CompressedImage format strings and data as image_transport's plugins
write them (compressed_image_transport, compressed_depth_image_transport), round trips, the
inverse-depth quantization at the rig's working range, and bad input."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from fingerps_driver.simulation import SimulatedRig
from fingerps_ros.errors import MessageError
from fingerps_ros.image_compression import (
    CONFIG_HEADER_BYTES,
    DepthQuantization,
    compressed_format,
    decode_compressed,
    encode_compressed,
    encode_compressed_depth,
)

H, W = 13, 17
RIDGE_HEIGHT_M = 50e-6


def _random(encoding: str, rng: np.random.Generator) -> np.ndarray:
    dtype = np.uint16 if encoding.endswith("16") else np.uint8
    shape = (H, W) if encoding.startswith("mono") else (H, W, 3)
    return rng.integers(0, np.iinfo(dtype).max + 1, shape, dtype=dtype)


def _smooth(encoding: str) -> np.ndarray:
    """A smooth picture JPEG keeps well: ramps, one per channel."""
    rows, cols = np.mgrid[0:64, 0:80].astype(np.float64)
    scale = 65535.0 if encoding.endswith("16") else 255.0
    dtype = np.uint16 if encoding.endswith("16") else np.uint8
    grey = scale * (0.2 + 0.6 * (rows / 63 + cols / 79) / 2)
    if encoding.startswith("mono"):
        return np.rint(grey).astype(dtype)
    return np.rint(np.stack([grey, scale - grey, np.full_like(grey, scale / 2)], axis=-1)
                   ).astype(dtype)


# ------------------------------------------------------------------ format strings
@pytest.mark.parametrize(("encoding", "codec", "expected"), [
    # compressed_publisher.cpp: PNG "bgr<bitDepth>" for colour, "" (trailing space) for grey
    ("mono8", "png", "mono8; png compressed "),
    ("mono16", "png", "mono16; png compressed "),
    ("rgb8", "png", "rgb8; png compressed bgr8"),
    ("bgr8", "png", "bgr8; png compressed bgr8"),
    ("rgb16", "png", "rgb16; png compressed bgr16"),
    ("bgr16", "png", "bgr16; png compressed bgr16"),
    # JPEG: always 8-bit, bgr8 for colour, mono8 for grey (mono16 too)
    ("mono8", "jpeg", "mono8; jpeg compressed mono8"),
    ("mono16", "jpeg", "mono16; jpeg compressed mono8"),
    ("rgb8", "jpeg", "rgb8; jpeg compressed bgr8"),
    ("bgr8", "jpeg", "bgr8; jpeg compressed bgr8"),
    ("rgb16", "jpeg", "rgb16; jpeg compressed bgr8"),
])
def test_format_strings_are_upstreams(encoding: str, codec: str, expected: str) -> None:
    assert compressed_format(encoding, codec=codec) == expected
    image = _random(encoding, np.random.default_rng(1))
    fmt, _data = encode_compressed(image, encoding, codec=codec)
    assert fmt == expected


# ------------------------------------------------------------------ png / jpeg
@pytest.mark.parametrize("encoding", ["mono8", "mono16", "rgb8", "bgr8", "rgb16", "bgr16"])
def test_png_round_trip_is_exact_and_written_as_opencv_reads_it(encoding: str) -> None:
    image = _random(encoding, np.random.default_rng(len(encoding)))
    original = image.copy()
    fmt, data = encode_compressed(image, encoding, codec="png", png_level=9)
    assert isinstance(data, bytes) and data[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(image, original)  # input untouched
    back, back_encoding = decode_compressed(fmt, data)
    assert back_encoding == encoding and back.dtype == image.dtype
    np.testing.assert_array_equal(back, image)
    # what any OpenCV subscriber sees: the file holds BGR for colour ("compressed bgr")
    plain = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    expected = image[..., ::-1] if encoding.startswith("rgb") else image
    np.testing.assert_array_equal(plain, expected)


@pytest.mark.parametrize("level", [0, 1, 3, 9])
def test_png_level_changes_the_size_not_the_pixels(level: int) -> None:
    image = _smooth("rgb8")
    fmt, data = encode_compressed(image, "rgb8", png_level=level)
    np.testing.assert_array_equal(decode_compressed(fmt, data)[0], image)
    if level == 0:
        assert len(data) > image.nbytes  # stored
    else:
        assert len(data) < image.nbytes / 4


@pytest.mark.parametrize("encoding", ["mono8", "rgb8", "bgr8"])
def test_jpeg_round_trip_is_close(encoding: str) -> None:
    image = _smooth(encoding)
    fmt, data = encode_compressed(image, encoding, codec="jpeg", jpeg_quality=95)
    assert data[:2] == b"\xff\xd8"
    back, back_encoding = decode_compressed(fmt, data)
    assert back_encoding == encoding and back.shape == image.shape
    error = np.abs(back.astype(int) - image.astype(int))
    assert error.mean() < 1.5 and error.max() <= 8
    small = encode_compressed(image, encoding, codec="jpeg", jpeg_quality=10)[1]
    assert len(small) < len(data)


def test_jpeg_of_mono16_is_scaled_as_cv_bridge_and_the_subscriber_do() -> None:
    image = _smooth("mono16")
    fmt, data = encode_compressed(image, "mono16", codec="jpeg", jpeg_quality=100)
    plain = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert plain.dtype == np.uint8  # 8-bit JPEG of round(v * 255 / 65535)
    expected8 = np.rint(image * (255 / 65535)).astype(int)
    assert np.abs(plain.astype(int) - expected8).max() <= 2
    back, encoding = decode_compressed(fmt, data)  # compressed_subscriber: times 256
    assert encoding == "mono16" and back.dtype == np.uint16
    np.testing.assert_array_equal(back % 256, 0)
    assert np.abs(back.astype(int) - image.astype(int)).max() <= 3 * 256


def test_format_of_old_publishers_without_encoding_is_decoded() -> None:
    image = _random("bgr8", np.random.default_rng(3))
    _fmt, data = encode_compressed(image, "bgr8")
    back, encoding = decode_compressed("png", data)
    assert encoding == "bgr8"
    np.testing.assert_array_equal(back, image)


# ------------------------------------------------------------------ compressedDepth
def test_compressed_depth_layout_is_upstreams() -> None:
    quantization = DepthQuantization()
    assert (quantization.depth_max_m, quantization.depth_quantization) == (0.2, 50.0)
    depth = np.full((H, W), 0.09, np.float32)
    depth[0, 0] = np.nan
    fmt, data = encode_compressed_depth(depth)
    assert fmt == "32FC1; compressedDepth png"
    # ConfigHeader: int32 compressionFormat (INV_DEPTH = 0), float32 depthParam[2] = A, B
    assert CONFIG_HEADER_BYTES == 12
    kind, a, b = struct.unpack("<iff", data[:12])
    assert kind == 0
    assert a == np.float32(50.0 * 51.0) == quantization.a
    assert b == np.float32(1.0 - 2550.0 / 0.2) == quantization.b
    assert data[12:20] == b"\x89PNG\r\n\x1a\n"
    q = cv2.imdecode(np.frombuffer(data[12:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert q.dtype == np.uint16 and q.shape == (H, W)
    # q = (unsigned short)(A / z + B) in float32, as codec.cpp; 0 for NaN
    expected = np.float32(a) / np.float32(0.09) + np.float32(b)
    assert q[0, 0] == 0 and np.all(q.reshape(-1)[1:] == np.uint16(expected))
    np.testing.assert_array_equal(q, quantization.quantize(depth))


def test_depth_round_trip_within_one_step_at_the_working_range() -> None:
    """The rig's true fingertip depth (apex at 90 mm, 50 um ridges): every decoded depth
    within one quantization step of the truth, and the step far finer than the ridges."""
    truth = SimulatedRig().finger_truth()
    depth = truth.depth_m
    original = depth.copy()
    quantization = DepthQuantization()
    fmt, data = encode_compressed_depth(depth, quantization=quantization)
    np.testing.assert_array_equal(depth, original)
    back, encoding = decode_compressed(fmt, data)
    assert encoding == "32FC1" and back.dtype == np.float32 and back.shape == depth.shape
    np.testing.assert_array_equal(np.isfinite(back), truth.mask)
    z = depth[truth.mask].astype(np.float64)
    assert 0.088 < z.min() and z.max() < 0.1
    error = back[truth.mask].astype(np.float64) - z
    step = quantization.step_m(z)
    float_tolerance = 1e-7 * z  # float32 arithmetic of encoder and decoder
    assert np.all(error >= -float_tolerance)  # truncation: never nearer than the truth
    assert np.all(error <= step + float_tolerance)
    # the resolution the README states: 3.2 um at 90 mm, < 1/10 of the ridge height
    assert quantization.step_m(0.09) == pytest.approx(0.09**2 / (2550 - 0.09))
    assert 3.1e-6 < quantization.step_m(0.09) < 3.2e-6 < RIDGE_HEIGHT_M / 10
    assert quantization.step_m(0.2) < 16e-6
    assert error.max() < 4e-6
    np.testing.assert_array_equal(back, quantization.dequantize(quantization.quantize(depth)))


def test_depths_that_do_not_fit_become_nan_not_wrapped() -> None:
    quantization = DepthQuantization()
    nearest = quantization.nearest_m
    assert nearest == pytest.approx(2550.0 / (65536.0 + 12749.0))
    assert 0.0325 < nearest < 0.0327
    near_ok, far_ok = nearest * 1.0001, 0.1999
    values = np.array([[near_ok, far_ok, 0.09, nearest * 0.9999, 0.02, 1e-6],
                       [0.2, 0.5, np.inf, np.nan, 0.0, -0.09]], dtype=np.float32)
    back, _ = decode_compressed(*encode_compressed_depth(values, quantization=quantization))
    fits = np.array([[1, 1, 1, 0, 0, 0], [0, 0, 0, 0, 0, 0]], dtype=bool)
    np.testing.assert_array_equal(np.isfinite(back), fits)
    np.testing.assert_allclose(back[fits], values[fits], rtol=1e-4)
    last = np.array([[2550.0 / (65535.5 + 12749.0)]], np.float32)
    assert quantization.quantize(last)[0, 0] == 65535  # the last code is used


def test_upstream_defaults_would_lose_the_finger_and_any_header_decodes() -> None:
    upstream = DepthQuantization(depth_max_m=10.0, depth_quantization=100.0)
    assert 0.151 < upstream.nearest_m < 0.152  # the finger at 90 mm does not fit
    depth = np.full((4, 5), 0.09, np.float32)
    assert not np.isfinite(decode_compressed(*encode_compressed_depth(
        depth, quantization=upstream))[0]).any()
    # any A, B: the decoder reads them from the header
    other = DepthQuantization(depth_max_m=1.0, depth_quantization=20.0)
    depth = np.linspace(0.05, 0.9, 20, dtype=np.float32).reshape(4, 5)
    back, _ = decode_compressed(*encode_compressed_depth(depth, quantization=other))
    np.testing.assert_array_equal(back, other.dequantize(other.quantize(depth)))
    assert np.all(back - depth <= other.step_m(depth) + 1e-7)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(("call", "words"), [
    (lambda: encode_compressed(np.zeros((4, 4), np.float32), "32FC1"),
     ["'32FC1'", "compressedDepth", "mono8"]),
    (lambda: encode_compressed(np.zeros((4, 4, 3), np.float32), "32FC3"),
     ["'32FC3'", "supported encodings"]),
    (lambda: encode_compressed(np.zeros((4, 4), np.uint8), "mono8", codec="tiff"),
     ["'tiff'", "png, jpeg"]),
    (lambda: encode_compressed(np.zeros((4, 4), np.uint16), "mono8"),
     ["must be uint8", "uint16"]),
    (lambda: encode_compressed(np.zeros((4, 4), np.uint8), "rgb8"),
     ["(4, 4)", "(H, W, 3)"]),
    (lambda: encode_compressed(np.zeros((0, 4), np.uint8), "mono8"), ["(0, 4)"]),
    (lambda: encode_compressed(np.zeros((4, 4), np.uint8), "mono8", png_level=10),
     ["png_level 10", "0..9"]),
    (lambda: encode_compressed(np.zeros((4, 4), np.uint8), "mono8", codec="jpeg",
                               jpeg_quality=0), ["jpeg_quality 0", "1..100"]),
    (lambda: encode_compressed_depth(np.zeros((4, 4), np.float32), codec="rvl"),
     ["'rvl'", "png"]),
    (lambda: encode_compressed_depth(np.zeros((4, 4, 3), np.float32)), ["(4, 4, 3)"]),
    (lambda: DepthQuantization(depth_max_m=0.0), ["depth_max_m", "> 0"]),
    (lambda: DepthQuantization(depth_quantization=float("nan")), ["depth_quantization"]),
    (lambda: decode_compressed("mono8; png compressed ", b"not an image"),
     ["12 bytes", "not an image"]),
    (lambda: decode_compressed("mono8; png compressed ", b""), ["0 bytes"]),
    (lambda: decode_compressed("32FC1; compressedDepth png", b"\0" * 12), ["too short"]),
    (lambda: decode_compressed("32FC1; compressedDepth rvl", b"\0" * 40),
     ["'compressedDepth rvl'"]),
    (lambda: decode_compressed("16UC1; compressedDepth png", b"\0" * 40), ["'16UC1'"]),
    (lambda: decode_compressed(
        "32FC1; compressedDepth png",
        struct.pack("<iff", -1, 1.0, 0.0) + encode_compressed(
            np.zeros((2, 2), np.uint16), "mono16")[1]), ["format -1", "INV_DEPTH"]),
    (lambda: decode_compressed("rgb8; png compressed bgr8",
                               encode_compressed(np.zeros((2, 2), np.uint8), "mono8")[1]),
     ["1 channel", "not rgb8"]),
])
def test_bad_input_is_refused_with_a_reason(call, words: list[str]) -> None:
    with pytest.raises(MessageError) as raised:
        call()
    for word in words:
        assert word in str(raised.value), (word, str(raised.value))
