"""Conversion between point arrays and sensor_msgs/PointCloud2 (x, y, z, intensity float32)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from fingerps_recon.errors import FingerpsReconError

_FIELDS = ("x", "y", "z", "intensity")
_DTYPE = np.dtype([(name, "<f4") for name in _FIELDS])


def points_to_cloud(points: np.ndarray, intensity: np.ndarray, *, header: Header) -> PointCloud2:
    """Return an unorganised PointCloud2 of ``points`` (N, 3) metres with ``intensity`` (N,)."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3 or np.shape(intensity) != (pts.shape[0],):
        raise FingerpsReconError(
            f"points {pts.shape} and intensity {np.shape(intensity)} must be (N, 3) and (N,)")
    record = np.empty(pts.shape[0], dtype=_DTYPE)
    record["x"], record["y"], record["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    record["intensity"] = np.asarray(intensity, dtype=np.float32)
    fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, name in enumerate(_FIELDS)]
    return PointCloud2(
        header=header, height=1, width=int(pts.shape[0]), fields=fields, is_bigendian=False,
        point_step=_DTYPE.itemsize, row_step=_DTYPE.itemsize * int(pts.shape[0]),
        data=record.tobytes(), is_dense=True)


def cloud_to_points(cloud: PointCloud2) -> tuple[np.ndarray, np.ndarray]:
    """Return (points (N, 3) float32, intensity (N,) float32) of a cloud made by
    :func:`points_to_cloud`."""
    names = [f.name for f in cloud.fields]
    if names[:4] != list(_FIELDS) or cloud.point_step != _DTYPE.itemsize:
        raise FingerpsReconError(
            f"cloud fields {names} (step {cloud.point_step}) are not x, y, z, intensity float32")
    record = np.frombuffer(bytes(cloud.data), dtype=_DTYPE)
    points = np.stack([record["x"], record["y"], record["z"]], axis=1).astype(np.float32)
    return points, record["intensity"].astype(np.float32)
