"""Ground-truth minutiae of a synthetic ridge pattern: skeleton and crossing number.

The classical extraction (Maltoni et al., Handbook of Fingerprint Recognition, sec. "Minutiae
detection"): binarise (ridges > 0), thin to a one-pixel skeleton (Zhang & Suen, "A fast
parallel algorithm for thinning digital patterns", CACM 27(3), 1984), and classify skeleton
pixels by the crossing number CN = 1/2 sum |P_i - P_(i+1)| over the 8 neighbours: CN = 1 a
ridge ending, CN = 3 a bifurcation. Minutiae near the print's border, near a singular point,
or closer than ``min_separation_mm`` to another one (skeleton spurs, tiny holes) are dropped.

Angle convention (rad, counter-clockwise on the image from +x towards up, in [0, 2 pi)): the
ridge orientation at the minutia, pointed away from the minutia along its ridge for an ending
(into the ridge body) and along the two branches for a bifurcation (into the valley that ends
there). Positions in mm in the rolled plane (``fingerprint_orientation``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from scipy import ndimage

from fingerps_driver.simulation.fingerprint_orientation import SingularPoint


class MinutiaType(Enum):
    ENDING = "ending"
    BIFURCATION = "bifurcation"


@dataclass(frozen=True)
class Minutia:
    """A minutia at (x_mm, y_mm), direction ``angle_rad`` (module docstring), of ``kind``."""

    x_mm: float
    y_mm: float
    angle_rad: float
    kind: MinutiaType


def _neighbours(image: np.ndarray) -> list[np.ndarray]:
    """P2..P9 of Zhang-Suen (N, NE, E, SE, S, SW, W, NW), zero outside the image."""
    p = np.pad(image, 1)
    h, w = image.shape
    offsets = [(-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1)]
    return [p[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] for dr, dc in offsets]


def thin(binary: np.ndarray) -> np.ndarray:
    """Zhang-Suen thinning of a boolean image to a one-pixel-wide skeleton (vectorised)."""
    skeleton = binary.astype(np.uint8)
    while True:
        changed = False
        for step in (0, 1):
            n = _neighbours(skeleton)
            b = sum(n)
            a = sum((n[i] == 0) & (n[(i + 1) % 8] == 1) for i in range(8))
            p2, p4, p6, p8 = n[0], n[2], n[4], n[6]
            if step == 0:
                c = (p2 * p4 * p6 == 0) & (p4 * p6 * p8 == 0)
            else:
                c = (p2 * p4 * p8 == 0) & (p2 * p6 * p8 == 0)
            remove = (skeleton == 1) & (b >= 2) & (b <= 6) & (a == 1) & c
            if remove.any():
                skeleton[remove] = 0
                changed = True
        if not changed:
            return skeleton.astype(bool)


def crossing_number(skeleton: np.ndarray) -> np.ndarray:
    """Crossing number of every skeleton pixel (0 off the skeleton), (H, W) int."""
    n = [x.astype(np.int16) for x in _neighbours(skeleton.astype(np.uint8))]
    cn = sum(np.abs(n[i] - n[(i + 1) % 8]) for i in range(8)) // 2
    return np.where(skeleton, cn, 0)


def extract_minutiae(
    ridges: np.ndarray,
    *,
    pixel_mm: float,
    orientation_rad: np.ndarray,
    mask: np.ndarray,
    singular_points: tuple[SingularPoint, ...] = (),
    border_mm: float = 1.0,
    singular_zone_mm: float = 1.5,
    min_separation_mm: float = 0.25,
    direction_radius_mm: float = 0.35,
) -> tuple[Minutia, ...]:
    """Minutiae of ``ridges > 0`` by thinning and crossing number (module docstring).

    Parameters
    ----------
    ridges : (H, W) float, ridges > 0.
    orientation_rad : (H, W) float, ridge orientation in [0, pi) (gives each angle's line).
    mask : (H, W) bool, the print's area; minutiae within ``border_mm`` of its edge dropped.
    singular_points : minutiae within ``singular_zone_mm`` of one dropped.
    """
    skeleton = thin(ridges > 0)
    cn = crossing_number(skeleton)
    inner = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1] * pixel_mm > border_mm
    candidates = ((cn == 1) | (cn == 3)) & inner
    rows, cols = np.nonzero(candidates)
    x = (cols + 0.5) * pixel_mm
    y = (rows + 0.5) * pixel_mm
    keep = np.ones(len(rows), bool)
    for sp in singular_points:
        keep &= np.hypot(x - sp.x_mm, y - sp.y_mm) > singular_zone_mm
    if len(rows) > 1:
        d = np.hypot(x[:, None] - x[None, :], y[:, None] - y[None, :])
        np.fill_diagonal(d, np.inf)
        keep &= d.min(axis=1) > min_separation_mm
    labels, _ = ndimage.label(skeleton, structure=np.ones((3, 3)))
    r = int(np.ceil(direction_radius_mm / pixel_mm))
    minutiae = []
    for i in np.nonzero(keep)[0]:
        row, col = rows[i], cols[i]
        r0, c0 = max(row - r, 0), max(col - r, 0)
        window = labels[r0:row + r + 1, c0:col + r + 1] == labels[row, col]
        wr, wc = np.nonzero(window)
        dr, dc = wr + r0 - row, wc + c0 - col
        near = np.hypot(dr, dc) <= r
        vx, vy = dc[near].mean(), -dr[near].mean()  # counter-clockwise frame (y up)
        theta = float(orientation_rad[row, col])
        if np.cos(theta) * vx + np.sin(theta) * vy < 0:
            theta += np.pi
        kind = MinutiaType.ENDING if cn[row, col] == 1 else MinutiaType.BIFURCATION
        minutiae.append(Minutia(float(x[i]), float(y[i]), float(theta % (2 * np.pi)), kind))
    return tuple(minutiae)
