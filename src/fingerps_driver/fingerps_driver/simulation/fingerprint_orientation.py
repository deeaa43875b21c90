"""Pattern classes, singular points, orientation field and ridge-period map of a synthetic finger.

The first half of SFinGe (Cappelli, Maio & Maltoni, "Synthetic fingerprint-image generation",
ICPR 2000; Maltoni et al., Handbook of Fingerprint Recognition, ch. "Synthetic fingerprint
generation"); ``fingerprint_pattern`` grows the ridges on these maps.

Coordinates: the rolled plane (arc length on the skin), millimetres, on a grid of square
pixels of side ``pixel_mm``; x along the columns (right), y along the rows (down), origin at
the top-left corner of the grid, pixel (r, c) centred at ((c + 0.5) p, (r + 0.5) p). Angles
(ridge orientation, minutia direction) are counter-clockwise as seen on the image, from +x
towards -y (up), as in ISO/IEC 19794-2 and NBIS.

Orientation: the zero-pole model of Sherlock & Monro ("A model for interpreting fingerprint
topology", Pattern Recognition 26(7), 1993) with the per-singularity correction of Vizcaya &
Gerhardt ("A nonlinear orientation model for global description of fingerprints", Pattern
Recognition 29(7), 1996) that SFinGe uses::

    theta(z) = theta_inf + 1/2 [sum_cores g_c(arg(z - z_c)) - sum_deltas g_d(arg(z - z_d))]

g_k is piecewise linear through 8 knots, g_k(a) = a + small seeded offsets, zero at +-pi, so
it keeps each Poincare index (+1/2 a core, -1/2 a delta) and only bends the ridges. Plain
arches have no singular point; as SFinGe does, they get an analytic arch field instead (ridge
lines y = y0 - h(y0) cos(pi x / W), flat at the bottom, humped above).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter


class PatternClass(Enum):
    """Henry classes SFinGe generates."""

    ARCH = "arch"
    TENTED_ARCH = "tented_arch"
    LEFT_LOOP = "left_loop"
    RIGHT_LOOP = "right_loop"
    WHORL = "whorl"


# Natural class frequencies (Wilson, Candela & Watson 1994, as quoted in the Handbook).
CLASS_FREQUENCIES: dict[PatternClass, float] = {
    PatternClass.ARCH: 0.037,
    PatternClass.TENTED_ARCH: 0.029,
    PatternClass.LEFT_LOOP: 0.338,
    PatternClass.RIGHT_LOOP: 0.317,
    PatternClass.WHORL: 0.279,
}


class SingularKind(Enum):
    CORE = "core"
    DELTA = "delta"


@dataclass(frozen=True)
class SingularPoint:
    """A core (Poincare index +1/2) or delta (-1/2) at (x_mm, y_mm) in the rolled plane."""

    kind: SingularKind
    x_mm: float
    y_mm: float


@dataclass(frozen=True)
class OrientationModel:
    """Everything the orientation field depends on (drawn from a seed by ``draw_model``).

    ``corrections`` holds, per singular point, the 9 knot offsets (rad) of the
    Vizcaya-Gerhardt function g at arg = -pi, -3pi/4, ..., pi (first and last 0).
    ``arch_height`` is the slope scale of the analytic arch (plain arches only).
    """

    pattern_class: PatternClass
    singular_points: tuple[SingularPoint, ...]
    corrections: tuple[tuple[float, ...], ...]
    theta_inf_rad: float = 0.0
    arch_height: float = 0.0
    arch_centre_mm: tuple[float, float] = (0.0, 0.0)


def draw_class(rng: np.random.Generator) -> PatternClass:
    """A pattern class with the natural frequencies ``CLASS_FREQUENCIES``."""
    classes = list(CLASS_FREQUENCIES)
    p = np.array([CLASS_FREQUENCIES[c] for c in classes])
    return classes[int(rng.choice(len(classes), p=p / p.sum()))]


def draw_model(
    pattern_class: PatternClass, rng: np.random.Generator, *, width_mm: float, height_mm: float
) -> OrientationModel:
    """Singular points and orientation corrections of one finger of ``pattern_class``.

    Positions (mm, rolled plane) are jittered around typical ones: the core(s) near the
    centre, slightly above it; loop deltas 4-7 mm to the side of the open end and 5-7.5 mm
    below; whorl deltas on both sides; the tented-arch delta 2-3.5 mm straight below its core.
    """
    cx = width_mm / 2 + rng.uniform(-1.0, 1.0)
    cy = height_mm / 2 + rng.uniform(-2.0, 0.5)
    core, delta = SingularKind.CORE, SingularKind.DELTA
    points: list[SingularPoint] = []
    if pattern_class in (PatternClass.LEFT_LOOP, PatternClass.RIGHT_LOOP):
        side = 1.0 if pattern_class is PatternClass.LEFT_LOOP else -1.0
        points = [
            SingularPoint(core, cx, cy),
            SingularPoint(delta, cx + side * rng.uniform(4.0, 7.0), cy + rng.uniform(5.0, 7.5)),
        ]
    elif pattern_class is PatternClass.WHORL:
        half = rng.uniform(0.4, 1.2)
        tilt = rng.uniform(-0.6, 0.6) + np.pi / 2
        dx, dy = half * np.cos(tilt), half * np.sin(tilt)
        drop = rng.uniform(5.0, 7.5, 2)
        points = [
            SingularPoint(core, cx - dx, cy - dy),
            SingularPoint(core, cx + dx, cy + dy),
            SingularPoint(delta, cx - rng.uniform(5.0, 7.0), cy + drop[0]),
            SingularPoint(delta, cx + rng.uniform(5.0, 7.0), cy + drop[1]),
        ]
    elif pattern_class is PatternClass.TENTED_ARCH:
        points = [
            SingularPoint(core, cx, cy),
            SingularPoint(delta, cx + rng.uniform(-0.3, 0.3), cy + rng.uniform(2.0, 3.5)),
        ]
    corrections = []
    for _ in points:
        knots = rng.uniform(-0.25, 0.25, 9)
        knots[0] = knots[-1] = 0.0
        corrections.append(tuple(float(k) for k in knots))
    return OrientationModel(
        pattern_class=pattern_class,
        singular_points=tuple(points),
        corrections=tuple(corrections),
        theta_inf_rad=float(rng.uniform(-0.05, 0.05)),
        arch_height=float(rng.uniform(0.5, 1.0)),
        arch_centre_mm=(float(cx), float(cy + 1.5)),
    )


def _grid_mm(shape: tuple[int, int], pixel_mm: float) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = shape
    x = (np.arange(cols, dtype=np.float64) + 0.5) * pixel_mm
    y = (np.arange(rows, dtype=np.float64) + 0.5) * pixel_mm
    return np.meshgrid(x, y)


def orientation_field(
    model: OrientationModel, shape: tuple[int, int], *, pixel_mm: float
) -> np.ndarray:
    """Ridge orientation on the grid (zero-pole model with Vizcaya-Gerhardt correction).

    Returns
    -------
    theta : (H, W) float64
        Ridge tangent angle in [0, pi), counter-clockwise on the image (module docstring).
    """
    x, y = _grid_mm(shape, pixel_mm)
    if model.pattern_class is PatternClass.ARCH:
        return _arch_field(model, x, y, shape, pixel_mm)
    knots = np.linspace(-np.pi, np.pi, 9)
    theta = np.full(shape, model.theta_inf_rad)
    for point, offsets in zip(model.singular_points, model.corrections, strict=True):
        # arg measured counter-clockwise on the image: y points down, hence -(y - y_k).
        alpha = np.arctan2(-(y - point.y_mm), x - point.x_mm)
        g = alpha + np.interp(alpha, knots, np.asarray(offsets))
        theta += 0.5 * g if point.kind is SingularKind.CORE else -0.5 * g
    return np.mod(theta, np.pi)


def _arch_field(
    model: OrientationModel, x: np.ndarray, y: np.ndarray, shape: tuple[int, int], pixel_mm: float
) -> np.ndarray:
    width = shape[1] * pixel_mm
    cx, cy = model.arch_centre_mm
    # Hump height grows from 0 below the arch centre to its full value above it.
    rise = 1.0 / (1.0 + np.exp((y - cy) / 2.0))
    slope = model.arch_height * rise * np.sin(np.pi * (x - cx) / width)
    return np.mod(np.arctan(slope) + model.theta_inf_rad, np.pi)


def period_map(
    shape: tuple[int, int],
    rng: np.random.Generator,
    *,
    pixel_mm: float,
    period_range_mm: tuple[float, float] = (0.40, 0.55),
    smoothness_mm: float = 4.0,
) -> np.ndarray:
    """A smoothly varying ridge period (mm) within ``period_range_mm``.

    A seeded mean period in the middle of the range plus a Gaussian-filtered random field
    (correlation length ``smoothness_mm``) and a mild vertical trend (finer ridges towards
    the tip, as on real fingers), clipped to the range.

    Returns
    -------
    period : (H, W) float64
    """
    lo, hi = period_range_mm
    span = hi - lo
    coarse_mm = 0.5
    coarse_shape = (
        max(2, round(shape[0] * pixel_mm / coarse_mm)),
        max(2, round(shape[1] * pixel_mm / coarse_mm)),
    )
    field = gaussian_filter(rng.standard_normal(coarse_shape), smoothness_mm / coarse_mm)
    field /= max(float(field.std()), 1e-12)
    field = cv2.resize(field, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    trend = np.linspace(-1.0, 1.0, shape[0])[:, None]
    mean = lo + span * rng.uniform(0.35, 0.65)
    period = mean + span * (0.18 * field + 0.12 * trend)
    return np.clip(period, lo, hi)


def poincare_index(
    theta: np.ndarray, *, pixel_mm: float, x_mm: float, y_mm: float, radius_mm: float
) -> float:
    """Poincare index of an orientation field along a circle about (x_mm, y_mm).

    Sum of the orientation changes (each wrapped to (-pi/2, pi/2]) along 64 samples of the
    circle, counter-clockwise on the image, over 2 pi: +1/2 about a core, -1/2 about a
    delta, +1 about a whorl's pair of cores, 0 elsewhere.
    """
    phi = np.linspace(0.0, 2 * np.pi, 65)
    cols = np.rint((x_mm + radius_mm * np.cos(phi)) / pixel_mm - 0.5).astype(int)
    rows = np.rint((y_mm - radius_mm * np.sin(phi)) / pixel_mm - 0.5).astype(int)
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= theta.shape[0] or (
        cols.max() >= theta.shape[1]
    ):
        raise ValueError("the circle leaves the grid; choose a smaller radius_mm")
    samples = theta[rows, cols]
    steps = np.diff(samples)
    steps = (steps + np.pi / 2) % np.pi - np.pi / 2
    return float(steps.sum() / (2 * np.pi))
