"""Conversion between numpy arrays and sensor_msgs/Image (no cv_bridge wheel exists here).

Copies. ``array_to_image`` writes the pixels once, straight into the message's
``array.array`` (casting on the way if needed); the message is made with
``check_fields=True`` because rclpy's ``data`` setter then takes an ``array.array('B')`` as
it is, where by default it copies it once more (``array.array('B', value)``). Such a
message type-checks later assignments to its fields, as ROS_PYTHON_CHECK_FIELDS=1 would.
``image_to_array`` reads the message's buffer without copying it to ``bytes`` first and
copies the pixels once; ``images_to_array`` copies each image once, straight into the stack.
"""

from __future__ import annotations

import array as pyarray  # the functions' argument is called array
from collections.abc import Sequence

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Header

from fingerps_ros.errors import MessageError

# encoding -> (dtype, channels)
_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "mono8": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "32FC1": (np.dtype(np.float32), 1),
    "32FC3": (np.dtype(np.float32), 3),
}


def _encoding(encoding: str) -> tuple[np.dtype, int]:
    if encoding not in _ENCODINGS:
        raise MessageError(
            f"unsupported image encoding {encoding!r}; use one of {sorted(_ENCODINGS)}")
    return _ENCODINGS[encoding]


def array_to_image(array: np.ndarray, *, encoding: str, header: Header | None = None) -> Image:
    """Return a sensor_msgs/Image holding ``array`` (H, W) or (H, W, C) in ``encoding``.

    The pixels are cast to the encoding's type (as ``astype``: float64 -> float32 rounds)
    and stored little-endian, rows unpadded; the message shares no memory with ``array``.
    """
    dtype, channels = _encoding(encoding)
    pixels = np.asarray(array)
    shape = (*pixels.shape, 1) if pixels.ndim == 2 else pixels.shape
    if len(shape) != 3 or shape[2] != channels:
        raise MessageError(
            f"array of shape {np.shape(array)} does not fit encoding {encoding!r} "
            f"({channels} channel(s))")
    height, width = int(shape[0]), int(shape[1])
    raw = pyarray.array("B", b"\0") * (height * width * channels * dtype.itemsize)
    target = np.frombuffer(raw, dtype=dtype.newbyteorder("<")).reshape(shape)
    np.copyto(target, pixels.reshape(shape), casting="unsafe")
    del target  # releases the buffer export, so the array.array may be resized again
    msg = Image(check_fields=True)  # see the module docstring
    if header is not None:
        msg.header = header
    msg.height, msg.width = height, width
    msg.encoding = encoding
    msg.is_bigendian = 0
    msg.step = width * channels * dtype.itemsize
    msg.data = raw
    return msg


def _pixels(msg: Image) -> np.ndarray:
    """An (H, W, C) read-only view of the message's pixels in their byte order (no copy);
    or an error when the message is unusable."""
    dtype, channels = _encoding(msg.encoding)
    dtype = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    row_bytes = msg.width * channels * dtype.itemsize
    if msg.step < row_bytes or len(msg.data) < msg.step * msg.height:
        raise MessageError(
            f"image {msg.width}x{msg.height} {msg.encoding} has step {msg.step} and "
            f"{len(msg.data)} bytes: too few; the publisher filled it wrongly")
    data = msg.data
    if not isinstance(data, (pyarray.array, bytes, bytearray, memoryview)):
        data = bytes(data)  # a message filled by hand with a list
    raw = np.frombuffer(data, dtype=np.uint8, count=msg.step * msg.height)
    rows = raw.reshape(msg.height, msg.step)[:, :row_bytes]
    return rows.view(dtype).reshape(msg.height, msg.width, channels)


def image_to_array(msg: Image) -> np.ndarray:
    """Return the pixels of a sensor_msgs/Image as a new (H, W) or (H, W, C) array of the
    encoding's type in native byte order."""
    pixels = _pixels(msg)
    array = pixels.astype(pixels.dtype.newbyteorder("="), order="C")  # the one copy
    return array[:, :, 0] if array.shape[2] == 1 else array


def images_to_array(msgs: Sequence[Image]) -> np.ndarray:
    """Return K images of one encoding and size as a new (K, H, W) or (K, H, W, C) array:
    ``np.stack([image_to_array(m) for m in msgs])`` with one copy per image instead of two.
    """
    if not msgs:
        raise MessageError("no images to stack: give at least one")
    kinds = {(m.encoding, m.height, m.width) for m in msgs}
    if len(kinds) != 1:
        raise MessageError(
            f"images of different encodings or sizes {sorted(kinds)} (encoding, height, "
            "width) cannot be stacked; every image must come from one camera mode")
    dtype, channels = _encoding(msgs[0].encoding)
    # Every message checked (height, step and data length agree) before the stack is
    # allocated: a header claiming a huge image over little data allocates nothing.
    pixels = [_pixels(msg) for msg in msgs]
    stack = np.empty((len(msgs), msgs[0].height, msgs[0].width, channels), dtype=dtype)
    for k, view in enumerate(pixels):
        stack[k] = view
    return stack[..., 0] if channels == 1 else stack
