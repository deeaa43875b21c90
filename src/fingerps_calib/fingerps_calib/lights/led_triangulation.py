"""LED positions from several sphere placements (near light), and light directions from them.

One placement of the sphere gives, for each LED k, a ray towards it: from the highlight's
surface point S1 along the mirror direction l_k (paper Eq. 10; `sphere_calibration`). The
paper assumes distant lights, one direction per LED for the whole scene; but the LEDs of a
fingertip rig are ~90 mm away, so the direction to an LED changes by several degrees across
the fingertip and between the sphere and the finger (../shared/paper/NOTES.md Sec. 3.1).
Moving the sphere moves the ray, and the LED is where the rays of all placements meet:

- `triangulate_point`: the least-squares point x closest to N >= 2 rays (p_i, d_i):
  minimise sum_i |(I - d_i d_i^T)(x - p_i)|^2, i.e. solve
  [sum_i (I - d_i d_i^T)] x = sum_i (I - d_i d_i^T) p_i. Its residual is the rms distance
  of x from the rays.
- `triangulate_leds`: that for every LED, with checks, and the combined light directions:
  the unit vectors from a *reference point* to the triangulated LEDs. The reference point is
  where the object will be; calib_node uses its ``reference_point`` parameter (on the
  optical axis at the working distance by default). Without one, the mean of the placement
  centres.

Conditioning. The rays of one LED from placements b apart meet at an angle of about
b / distance (5 mm at 95 mm: 3 deg), so a lateral error e of a ray becomes an error of about
e / sin(angle) along the rays, i.e. in the LED's range, not across it. A range error dr
turns the direction from the reference point only by dr * sin(beta) / |L - ref|, where beta
(the angle at the LED between the rays and the line to the reference point) is small when
the reference point is near the placements. On the simulated rig, four placements a few
millimetres apart give LED positions within ~1 mm and directions within ~0.1 deg
(bench/bench_calib.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.lights.sphere_calibration import LightCalibrationResult
from fingerps_recon.photometric.frames import optical_to_ps


@dataclass(frozen=True, eq=False)
class Placement:
    """What one sphere placement contributes: per LED a ray towards it.

    Attributes
    ----------
    sphere_center_optical_m : (3,) float64
        Fitted sphere centre, metres, optical frame.
    radius_m : float
    edge_rms_px : float
        RMS residual of the silhouette fit, pixels.
    highlight_points_optical_m : (K, 3) float64
        Surface points S1 of the highlights (ray origins), metres; NaN where not found.
    directions_optical : (K, 3) float64
        Unit mirror directions at S1 towards each LED (ray directions); NaN where not found.
    highlights_uv : (K, 2) float64
        Highlight centroids, ideal pixels.
    residuals_px : (K,) float64
        Stability of the highlight centroids, pixels.
    """

    sphere_center_optical_m: np.ndarray
    radius_m: float
    edge_rms_px: float
    highlight_points_optical_m: np.ndarray
    directions_optical: np.ndarray
    highlights_uv: np.ndarray
    residuals_px: np.ndarray

    def __post_init__(self) -> None:
        for name, shape in (("sphere_center_optical_m", (3,)),
                            ("highlight_points_optical_m", (None, 3)),
                            ("directions_optical", (None, 3)), ("highlights_uv", (None, 2)),
                            ("residuals_px", (None,))):
            array = np.array(getattr(self, name), dtype=np.float64)
            if array.ndim != len(shape) or any(
                    want is not None and got != want
                    for got, want in zip(array.shape, shape, strict=True)):
                raise FingerpsCalibError(
                    f"Placement.{name} has shape {array.shape}, expected {shape} (None: K)")
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        counts = {len(self.highlight_points_optical_m), len(self.directions_optical),
                  len(self.highlights_uv), len(self.residuals_px)}
        if len(counts) != 1:
            raise FingerpsCalibError(f"Placement arrays disagree on the LED count: {counts}")
        object.__setattr__(self, "radius_m", float(self.radius_m))
        object.__setattr__(self, "edge_rms_px", float(self.edge_rms_px))

    @property
    def led_count(self) -> int:
        """Number of LEDs K."""
        return len(self.directions_optical)

    @classmethod
    def from_result(cls, result: LightCalibrationResult) -> Placement:
        """The placement of a single-sphere calibration (`calibrate_lights`)."""
        return cls(**{f.name: getattr(result, f.name) for f in fields(cls)})


@dataclass(frozen=True, eq=False)
class TriangulatedLights:
    """LED positions from N >= 2 sphere placements and the directions from a reference point.

    Attributes
    ----------
    led_positions_optical_m : (K, 3) float64
        Least-squares LED positions, metres, optical frame; NaN where not triangulated.
    position_residuals_m : (K,) float64
        RMS distance of each position from its rays, metres.
    direction_residuals_deg : (K,) float64
        Largest angle, over the placements, between the measured mirror direction and the
        direction from that placement's highlight point to the triangulated LED.
    ray_angles_deg : (K,) float64
        Largest angle between two rays of the LED (the triangulation's baseline).
    range_uncertainty_m : (K,) float64
        position_residual / sin(ray angle): a rough bound of the error along the rays.
    reference_point_optical_m : (3,) float64
        Where the directions start, metres.
    directions_optical : (K, 3) float64
        Unit vectors from the reference point towards each LED, optical frame.
    placements : int
        Number of placements combined.
    ok : bool
        Every check passed; otherwise ``problems`` says why and what to do.
    problems : tuple of str
    """

    led_positions_optical_m: np.ndarray
    position_residuals_m: np.ndarray
    direction_residuals_deg: np.ndarray
    ray_angles_deg: np.ndarray
    range_uncertainty_m: np.ndarray
    reference_point_optical_m: np.ndarray
    directions_optical: np.ndarray
    placements: int
    ok: bool
    problems: tuple[str, ...]

    @property
    def directions_ps(self) -> np.ndarray:
        """(K, 3) float64: ``directions_optical`` in the PS frame."""
        return optical_to_ps(self.directions_optical)


def triangulate_point(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """The point closest to N >= 2 rays in the least-squares sense.

    Parameters
    ----------
    origins : (N, 3) float
        A point of each ray.
    directions : (N, 3) float
        Each ray's direction (any length > 0).

    Returns
    -------
    point : (3,) float64
    rms_distance : float
        RMS distance of ``point`` from the rays (lines), in the units of ``origins``.

    Raises
    ------
    FingerpsCalibError
        Bad shapes, fewer than two rays, or parallel rays (no unique point).
    """
    p = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or d.shape != p.shape or len(p) < 2:
        raise FingerpsCalibError(
            f"origins {p.shape} and directions {d.shape}: expected two (N, 3) arrays, N >= 2")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # (N, 3, 3)
    a = projectors.sum(axis=0)
    b = np.einsum("nij,nj->i", projectors, p)
    eigen = np.linalg.eigvalsh(a)
    if eigen[0] < 1e-12 * len(p):
        raise FingerpsCalibError(
            "the rays are parallel: they have no single closest point; move the sphere "
            "between placements")
    point = np.linalg.solve(a, b)
    offsets = np.einsum("nij,nj->ni", projectors, point[None, :] - p)
    return point, float(np.sqrt(np.mean(np.sum(offsets**2, axis=1))))


def triangulate_leds(
    placements: Sequence[Placement],
    *,
    reference_point_optical_m: np.ndarray | None = None,
    min_ray_angle_deg: float = 1.5,
    max_position_residual_m: float = 0.5e-3,
) -> TriangulatedLights:
    """Triangulate each LED from its rays in N >= 2 placements; directions from a reference.

    Checks (each failing one adds a reason to ``problems``): every LED has a ray in at
    least two placements; its rays spread by at least ``min_ray_angle_deg`` (else the
    placements are too close together for a position); they meet within
    ``max_position_residual_m`` rms (else the sphere moved during a capture, or the
    placements disagree on the radius or the camera); and they meet in front of every
    highlight point (the LED is on the side the light comes from). Two rays always have a
    closest point, and an error within the plane of the two moves it without a residual;
    from three placements on, the rays check each other.

    Parameters
    ----------
    placements : sequence of Placement
        Two or more, all with the same LED count.
    reference_point_optical_m : (3,) float, optional
        Start of the combined directions, metres; default the mean of the sphere centres.
    min_ray_angle_deg, max_position_residual_m : float
        Limits of the checks above. On the simulated rig the residuals are 0.08-0.18 mm
        (two to four placements, up to four times the read noise); one of three placements
        shifted by 3 mm gives 0.6-0.8 mm.

    Returns
    -------
    TriangulatedLights

    Raises
    ------
    FingerpsCalibError
        Fewer than two placements, different LED counts, or a bad reference point.
    """
    placements = list(placements)
    if len(placements) < 2:
        raise FingerpsCalibError(
            f"{len(placements)} sphere placement(s): triangulating the LEDs needs two or "
            "more; move the sphere and calibrate again with add_placement")
    counts = sorted({pl.led_count for pl in placements})
    if len(counts) != 1:
        raise FingerpsCalibError(
            f"the placements have different LED counts {counts}; start a new set of "
            "placements")
    n_led = counts[0]
    centres = np.stack([pl.sphere_center_optical_m for pl in placements])
    if reference_point_optical_m is None:
        reference = centres.mean(axis=0)
    else:
        reference = np.asarray(reference_point_optical_m, dtype=np.float64)
        if reference.shape != (3,) or not np.all(np.isfinite(reference)):
            raise FingerpsCalibError(
                f"reference point {reference.tolist()} must be three finite numbers (metres)")
    origins = np.stack([pl.highlight_points_optical_m for pl in placements], axis=1)  # K,N,3
    rays = np.stack([pl.directions_optical for pl in placements], axis=1)
    positions = np.full((n_led, 3), np.nan)
    residuals = np.full(n_led, np.nan)
    direction_residuals = np.full(n_led, np.nan)
    angles = np.full(n_led, np.nan)
    uncertainty = np.full(n_led, np.nan)
    problems: list[str] = []
    spread = float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    for k in range(n_led):
        have = np.all(np.isfinite(origins[k]), axis=1) & np.all(np.isfinite(rays[k]), axis=1)
        if have.sum() < 2:
            problems.append(
                f"LED {k}: its highlight was found in {int(have.sum())} placement(s), two "
                "are needed; recalibrate the placements where it is missing")
            continue
        p, d = origins[k][have], rays[k][have]
        cos = np.clip(d @ d.T, -1.0, 1.0)
        angles[k] = float(np.degrees(np.arccos(cos.min())))
        if angles[k] < min_ray_angle_deg:
            distance = float(np.linalg.norm(centres.mean(axis=0)))  # ~ to the LEDs
            problems.append(
                f"LED {k}: its rays from the {int(have.sum())} placements meet at only "
                f"{angles[k]:.2f} deg (at least {min_ray_angle_deg:g} deg needed); the "
                f"placements are too close together (they lie within {1e3 * spread:.1f} mm "
                "of their mean): move the sphere by at least "
                f"{1e3 * np.radians(2 * min_ray_angle_deg) * distance:.0f} mm between "
                "placements")
            continue
        positions[k], residuals[k] = triangulate_point(p, d)
        along = np.einsum("ni,ni->n", positions[k][None, :] - p, d)
        towards = positions[k][None, :] - p
        towards /= np.linalg.norm(towards, axis=1, keepdims=True)
        direction_residuals[k] = float(np.degrees(np.arccos(
            np.clip(np.einsum("ni,ni->n", towards, d), -1.0, 1.0))).max())
        uncertainty[k] = residuals[k] / np.sin(np.radians(angles[k]))
        if np.any(along <= 0):
            problems.append(
                f"LED {k}: its rays meet behind the sphere, not towards the light; a "
                "highlight is probably a stray reflection: check the placements' pictures")
        if residuals[k] > max_position_residual_m:
            problems.append(
                f"LED {k}: its rays miss each other by {1e3 * residuals[k]:.2f} mm rms (at "
                f"most {1e3 * max_position_residual_m:.2f} mm): did the sphere move during a "
                "capture, or do the placements use different radii? Start a new set of "
                "placements")
    directions = positions - reference[None, :]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return TriangulatedLights(
        led_positions_optical_m=positions,
        position_residuals_m=residuals,
        direction_residuals_deg=direction_residuals,
        ray_angles_deg=angles,
        range_uncertainty_m=uncertainty,
        reference_point_optical_m=reference,
        directions_optical=directions,
        placements=len(placements),
        ok=not problems,
        problems=tuple(problems),
    )


@dataclass(frozen=True, eq=False)
class CombinedLights:
    """The light calibration of one or more sphere placements (`combine_placements`).

    Attributes
    ----------
    directions_optical : (K, 3) float64
        One placement: the mirror directions at its highlight points (distant-light
        assumption, as the paper). Two or more: from the reference point to the
        triangulated LEDs.
    residuals_px : (K,) float64
        Highlight centroid stability, the largest over the placements, pixels.
    sphere_center_optical_m : (3,) float64
        Centre of the latest placement, metres.
    edge_rms_px : float
        Largest silhouette-fit rms over the placements, pixels.
    placements : tuple of Placement
    triangulation : TriangulatedLights or None
        None for a single placement.
    ok : bool
    problems : tuple of str
    """

    directions_optical: np.ndarray
    residuals_px: np.ndarray
    sphere_center_optical_m: np.ndarray
    edge_rms_px: float
    placements: tuple[Placement, ...]
    triangulation: TriangulatedLights | None
    ok: bool
    problems: tuple[str, ...]

    @property
    def led_count(self) -> int:
        """Number of LEDs K."""
        return len(self.directions_optical)

    @property
    def led_positions_optical_m(self) -> np.ndarray:
        """(K, 3) triangulated LED positions, metres; (0, 3) for a single placement."""
        if self.triangulation is None:
            return np.zeros((0, 3))
        return self.triangulation.led_positions_optical_m

    @property
    def directions_ps(self) -> np.ndarray:
        """(K, 3) float64: ``directions_optical`` in the PS frame."""
        return optical_to_ps(self.directions_optical)


def combine_placements(
    placements: Sequence[Placement],
    *,
    reference_point_optical_m: np.ndarray | None = None,
    min_ray_angle_deg: float = 1.5,
    max_position_residual_m: float = 0.5e-3,
) -> CombinedLights:
    """The calibration in force after one or more sphere placements.

    A single placement gives its own directions (from the highlight points, the paper's
    distant-light assumption). Two or more are triangulated (`triangulate_leds`, whose
    checks and options apply) and give the directions from the reference point.

    Parameters
    ----------
    placements : sequence of Placement
        One or more, with the same LED count.
    reference_point_optical_m : (3,) float, optional
        See `triangulate_leds`.
    min_ray_angle_deg, max_position_residual_m : float
        See `triangulate_leds`.

    Returns
    -------
    CombinedLights

    Raises
    ------
    FingerpsCalibError
        No placement, or different LED counts.
    """
    placements = tuple(placements)
    if not placements:
        raise FingerpsCalibError("no sphere placement to combine; calibrate the lights first")
    counts = sorted({pl.led_count for pl in placements})
    if len(counts) != 1:
        raise FingerpsCalibError(
            f"the placements have different LED counts {counts}; start a new set of "
            "placements")
    residuals = np.max(np.stack([pl.residuals_px for pl in placements]), axis=0)
    latest = placements[-1]
    edge_rms = max(pl.edge_rms_px for pl in placements)
    if len(placements) == 1:
        return CombinedLights(
            directions_optical=latest.directions_optical, residuals_px=residuals,
            sphere_center_optical_m=latest.sphere_center_optical_m, edge_rms_px=edge_rms,
            placements=placements, triangulation=None, ok=True, problems=())
    triangulation = triangulate_leds(
        placements, reference_point_optical_m=reference_point_optical_m,
        min_ray_angle_deg=min_ray_angle_deg, max_position_residual_m=max_position_residual_m)
    return CombinedLights(
        directions_optical=triangulation.directions_optical, residuals_px=residuals,
        sphere_center_optical_m=latest.sphere_center_optical_m, edge_rms_px=edge_rms,
        placements=placements, triangulation=triangulation, ok=triangulation.ok,
        problems=triangulation.problems)
