"""Conversion between numpy arrays and sensor_msgs/Image (no cv_bridge wheel exists here)."""

from __future__ import annotations

import array as pyarray  # the functions' argument is called array

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from fingerps_recon.errors import FingerpsReconError

# encoding -> (dtype, channels)
_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "32FC1": (np.dtype(np.float32), 1),
    "32FC3": (np.dtype(np.float32), 3),
}


def array_to_image(array: np.ndarray, *, encoding: str, header: Header | None = None) -> Image:
    """Return a sensor_msgs/Image holding ``array`` (H, W) or (H, W, C) in ``encoding``."""
    if encoding not in _ENCODINGS:
        raise FingerpsReconError(
            f"unsupported image encoding {encoding!r}; use one of {sorted(_ENCODINGS)}")
    dtype, channels = _ENCODINGS[encoding]
    data = np.ascontiguousarray(array, dtype=dtype.newbyteorder("<"))
    if data.ndim == 2:
        data = data[:, :, None]
    if data.ndim != 3 or data.shape[2] != channels:
        raise FingerpsReconError(
            f"array of shape {np.shape(array)} does not fit encoding {encoding!r} "
            f"({channels} channel(s))")
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(data.shape[0]), int(data.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = int(data.shape[1] * channels * dtype.itemsize)
    # an array.array is taken as it is; bytes would be checked value by value (~1 ms/MB)
    raw = pyarray.array("B")
    raw.frombytes(data.reshape(-1).view(np.uint8))
    msg.data = raw
    return msg


def image_to_array(msg: Image) -> np.ndarray:
    """Return the pixels of a sensor_msgs/Image as a new (H, W) or (H, W, C) array."""
    if msg.encoding not in _ENCODINGS:
        raise FingerpsReconError(
            f"unsupported image encoding {msg.encoding!r}; use one of {sorted(_ENCODINGS)}")
    dtype, channels = _ENCODINGS[msg.encoding]
    dtype = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.step < row_bytes or len(msg.data) < msg.step * msg.height:
        raise FingerpsReconError(
            f"image {msg.width}x{msg.height} {msg.encoding} has step {msg.step} and "
            f"{len(msg.data)} bytes: too few; the publisher filled it wrongly")
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8, count=msg.step * msg.height)
    rows = raw.reshape(msg.height, msg.step)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(msg.height, msg.width, channels)
    pixels = pixels.astype(dtype.newbyteorder("="), copy=True)
    return pixels[:, :, 0] if channels == 1 else pixels
