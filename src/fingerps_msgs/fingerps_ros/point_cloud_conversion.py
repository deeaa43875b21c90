"""Conversion between point arrays and sensor_msgs/PointCloud2 (x, y, z, intensity float32).

``points_to_cloud`` writes the points once, straight into the message's ``array.array``;
the message is made with ``check_fields=True`` so that rclpy's ``data`` setter takes that
buffer as it is instead of copying it (see ``image_conversion``).
"""

from __future__ import annotations

import array as pyarray

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from fingerps_ros.errors import MessageError

_FIELDS = ("x", "y", "z", "intensity")
_DTYPE = np.dtype([(name, "<f4") for name in _FIELDS])


def points_to_cloud(points: np.ndarray, intensity: np.ndarray, *, header: Header) -> PointCloud2:
    """Return an unorganised PointCloud2 of ``points`` (N, 3) metres with ``intensity`` (N,)
    (cast to float32 as ``astype`` does)."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or np.shape(intensity) != (pts.shape[0],):
        raise MessageError(
            f"points {pts.shape} and intensity {np.shape(intensity)} must be (N, 3) and (N,)")
    count = int(pts.shape[0])
    raw = pyarray.array("B", b"\0") * (count * _DTYPE.itemsize)
    record = np.frombuffer(raw, dtype=_DTYPE)  # writable view of the message's bytes
    # Field by field: contiguous column copies (a (N, 4) float32 view filled with
    # [:, :3] = points writes strided rows, which is slower).
    record["x"], record["y"], record["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    record["intensity"] = intensity
    del record  # releases the buffer export
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate(_FIELDS)]
    cloud = PointCloud2(
        check_fields=True, header=header, height=1, width=count, fields=fields,
        is_bigendian=False, point_step=_DTYPE.itemsize, row_step=_DTYPE.itemsize * count,
        is_dense=True)
    cloud.data = raw
    return cloud


def cloud_to_points(cloud: PointCloud2) -> tuple[np.ndarray, np.ndarray]:
    """Return (points (N, 3) float32, intensity (N,) float32), new arrays, of a cloud made
    by :func:`points_to_cloud`."""
    names = [f.name for f in cloud.fields]
    if names[:4] != list(_FIELDS) or cloud.point_step != _DTYPE.itemsize:
        raise MessageError(
            f"cloud fields {names} (step {cloud.point_step}) are not x, y, z, intensity float32")
    data = cloud.data
    if not isinstance(data, (pyarray.array, bytes, bytearray, memoryview)):
        data = bytes(data)  # a message filled by hand with a list
    record = np.frombuffer(data, dtype=_DTYPE)  # a view: no bytes() copy
    points = np.stack([record["x"], record["y"], record["z"]], axis=1, dtype=np.float32)
    return points, record["intensity"].astype(np.float32)
