"""Perspective pinhole camera of the simulated rig (paper Sec. 3.1).

The camera centre is the origin of the optical frame (x right, y down, z forward). A pixel
(u, v) looks along the ray (u - cx, v - cy, f) (CONVENTIONS.md); here rays are scaled to
z = 1, so the point at depth Z on the ray through (u, v) is ``Z * ray``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_WIDTH_PX = 659
_HEIGHT_PX = 493
_FOCAL_PX = 3000.0  # 30 um a pixel at the 90 mm working distance


@dataclass(frozen=True)
class PinholeCamera:
    """Ideal pinhole camera without distortion; the defaults are the rig's camera.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    fx, fy : float
        Focal lengths in pixels.
    principal_point_px : (float, float) or None
        Principal point (cx, cy) in pixels (column, row; pixel centres at integers); None
        for the image centre ((width - 1) / 2, (height - 1) / 2).
    """

    width: int = _WIDTH_PX
    height: int = _HEIGHT_PX
    fx: float = _FOCAL_PX
    fy: float = _FOCAL_PX
    principal_point_px: tuple[float, float] | None = None

    @property
    def cx(self) -> float:
        """Principal point's column, pixels."""
        if self.principal_point_px is None:
            return (self.width - 1) / 2.0
        return float(self.principal_point_px[0])

    @property
    def cy(self) -> float:
        """Principal point's row, pixels."""
        if self.principal_point_px is None:
            return (self.height - 1) / 2.0
        return float(self.principal_point_px[1])

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix K."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def pixel_rays(
        self,
        *,
        rows: tuple[int, int] | None = None,
        cols: tuple[int, int] | None = None,
        supersample: int = 1,
    ) -> np.ndarray:
        """Rays through pixels, optical frame, scaled to z = 1.

        Parameters
        ----------
        rows, cols : (start, stop), optional
            Half-open pixel window; the whole image when omitted.
        supersample : int
            ``s`` sub-pixel samples per axis on a regular grid inside each pixel (a pixel
            covers its centre +/- 0.5).

        Returns
        -------
        rays : (h, w, 3) float64 when ``supersample == 1``, else (h, w, s*s, 3) float64
        """
        r0, r1 = rows if rows is not None else (0, self.height)
        c0, c1 = cols if cols is not None else (0, self.width)
        offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
        v = np.arange(r0, r1, dtype=np.float64)[:, None, None, None] + offsets[None, None, :, None]
        u = np.arange(c0, c1, dtype=np.float64)[None, :, None, None] + offsets[None, None, None, :]
        x = np.broadcast_to((u - self.cx) / self.fx, (r1 - r0, c1 - c0, supersample, supersample))
        y = np.broadcast_to((v - self.cy) / self.fy, (r1 - r0, c1 - c0, supersample, supersample))
        rays = np.stack([x, y, np.ones_like(x)], axis=-1).reshape(r1 - r0, c1 - c0, -1, 3)
        return rays[:, :, 0, :] if supersample == 1 else rays

    def project(self, points_optical: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) = (u, v) of points (..., 3) in the optical frame."""
        p = np.asarray(points_optical, dtype=np.float64)
        return np.stack(
            [self.fx * p[..., 0] / p[..., 2] + self.cx, self.fy * p[..., 1] / p[..., 2] + self.cy],
            axis=-1,
        )
