"""Synthetic fingertip: a curved pad carrying a whorl of papillary ridges, as a height field.

Geometry (optical frame, metres). Let (dx, dy) = (X - Xa, Y - Ya) be the offset from the
apex (Xa, Ya, Za), the point nearest the camera. The finger points up the image (towards -Y):

* tip (dy < 0): an ellipsoidal cap, r = sqrt(dx**2 + (dy / e)**2);
* pad and shaft (dy >= 0): a cylinder of the same radius, r = |dx|, bent away from the
  camera along its length with radius ``length_radius_m``.

The base surface is Z = Za + R - sqrt(R**2 - r**2) (+ the bend), and the finger ends where its
slope reaches ``max_slope_deg`` (r = R sin theta_max): that contour is the silhouette, the
mask. Outside it the height field continues as a cone of the same slope, only so that ray
casting is well defined there.

Ridges are a displacement delta along the base normal (raised ridges towards the camera) of
peak-to-valley ``ridge_height_m``, written as the equivalent Z offset delta / n_z. Their phase
is defined on "unrolled" surface coordinates (U, V) (arc length over the cap / around the
cylinder), so the period on the skin is ``ridge_period_m`` everywhere, also on the steep
margins: distorted concentric ellipses (a whorl, optionally a one-armed spiral) about a core
near the apex, warped by a low-frequency sinusoidal displacement. The ridge amplitude fades
out within ~``core_radius`` of the core, where the phase is singular.

A synthetic fingerprint (``identity``, its ``relief`` a ``fingerprint_relief.RidgeRelief``)
replaces the whorl when given: the displacement is 0.5 * ``ridge_height_m`` * its value at
the point's skin coordinates (``skin_coordinates``), so its ridges are raised towards the
camera. Skin coordinates use the finger's symmetry: the cap is an ellipsoid of revolution
and every cross-section of the shaft a circle of radius R about the (bent) finger axis, so a
point is (theta, dY), its azimuth about the axis (theta = 0 facing the camera, + towards +x)
and its position along it. Its skin x is -rho(dY) * theta (arc length along the
cross-section circle of radius rho; exactly R * theta on the shaft; the sign: Mirroring,
below), its skin y the arc length along the meridian from the apex's cross-section (on the
cap an incomplete elliptic integral of the second kind, on the bent shaft the arc length of
the parabola). Both are exact distances along the coordinate lines; the cap and the bent
shaft are not developable, so no flat map keeps all distances (the coordinate lines meet at
right angles on the cap, and within ~atan(slope_x * slope_y) of them on the shaft).

Mirroring: skin x runs towards -x of the image, so the skin seen by the camera carries the
pattern mirrored left-right. The pattern is the finger's rolled print (its ground truth),
and a rolled or contact print is the mirror image of the skin seen from outside, like a
stamp's print of its face; legacy prints, which matchers' galleries hold, are in that
orientation. ``fingerps_recon.surface.rolled_print`` mirrors the camera's view back, so the print
it recovers equals the ground-truth print up to a small similarity transform, with no flip.

Pose: ``roll_deg`` turns the finger about its own axis; the geometry is symmetric about it, so
only the skin moves: theta -> theta - roll, exact on the cap and the shaft (a skin point at
the apex moves to theta = roll, towards +x for roll > 0; on the shaft the skin x of a
pixel's point rises by R * roll). ``yaw_deg`` turns the whole finger about the optical axis
through the apex, from +x towards +y (clockwise as the image is displayed), exactly: (dx, dy)
is rotated into the finger's frame and the gradient back. ``pitch_deg`` then turns it about
the optical x axis through the apex, from +y towards +z (+ brings the tip, at -y, towards the
camera), also exactly: ``trace_fingertip`` traces the camera's rays in the finger's frame
(the camera centre moved, the rays turned; the height field is unchanged) and turns the hits
and normals back. The apex position is the shift.

Normals are from central differences of the full height field (step 0.25 um: truncation
below 2e-5 rad, at its largest where the ridges are steepest in the image, and round-off
below 1e-9 rad), so they are those of the surface the renderer sees.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np
from scipy import special

from fingerps_driver.simulation.fingerprint_relief import RidgeRelief, relief_for_identity
from fingerps_recon.photometric.frames import optical_to_ps, ps_to_optical

_WARP_WAVELENGTHS_M = (9.0e-3, 13.0e-3)
_ALBEDO_COMPONENTS = 8
_ALBEDO_WAVELENGTHS_M = (1.5e-3, 8.0e-3)
_FD_STEP_M = 0.25e-6
_NEWTON_TOLERANCE_M = 1e-12
_NEWTON_MAX_ITER = 60
_CORE_RADIUS_PERIODS = 0.7


@dataclass(frozen=True)
class FingertipShape:
    """Parameters of the synthetic fingertip (see the module docstring); the defaults are the
    rig's standard finger: the analytic whorl, 90 mm from the camera, no pose.

    Attributes
    ----------
    apex_optical_m : (3,) float
        Apex position, optical frame: the point nearest the camera; its z is the working
        distance.
    radius_m : float
        Radius R of the cap and the cylinder.
    tip_elongation : float
        e: the cap's semi-axis along the finger is e * R.
    max_slope_deg : float
        Surface slope at the silhouette.
    length_radius_m : float
        Radius of the bend along the finger, away from the camera.
    ridge_height_m, ridge_period_m : float
        Ridge peak-to-valley height and period on the skin (the height also that of a
        fingerprint's relief).
    core_offset_m : (2,) float
        Whorl core in unrolled coordinates (U, V) relative to the apex.
    ridge_ellipticity : float
        q >= 1: ridge spacing is period / sqrt(q) across and period * sqrt(q) along the finger.
    warp_amplitude_m : float
        Amplitude of the low-frequency warp of the ridge coordinates.
    spiral : bool
        One-armed spiral whorl (True) or closed concentric ellipses (False).
    albedo_mean, albedo_variation : float
        Mean albedo and the relative standard deviation of its smooth variation.
    seed : int
        Seed of the warp phases (``seed``) and the albedo pattern (``seed + 1``).
    identity : int or None
        None for the whorl, or the seed of the synthetic fingerprint carried instead
        (``fingerprint_relief.relief_for_identity``, its own period map). The fingerprint is
        20 mm wide (+-72 deg about an 8 mm finger) and the standard finger shows +-65 deg of
        it: beyond ~7 deg of roll one margin shows skin past the print's edge, where the
        relief fades to flat skin.
    roll_deg : float
        Rotation about the finger's own axis, within +-45 deg (see the module docstring).
    yaw_deg : float
        Rotation of the whole finger about the optical axis through the apex, from +x
        towards +y (clockwise as displayed), within +-90 deg.
    pitch_deg : float
        Then about the optical x axis through the apex, from +y towards +z (+ brings the tip
        towards the camera), within +-15 deg: beyond, the tip's or the shaft's margin comes
        within a few degrees of grazing.
    """

    apex_optical_m: tuple[float, float, float] = (0.0, 2.5e-3, 0.090)
    radius_m: float = 8e-3
    tip_elongation: float = 1.15
    max_slope_deg: float = 65.0
    length_radius_m: float = 25e-3
    ridge_height_m: float = 50e-6
    ridge_period_m: float = 0.5e-3
    core_offset_m: tuple[float, float] = (0.6e-3, -1.0e-3)
    ridge_ellipticity: float = 1.1
    warp_amplitude_m: float = 0.25e-3
    spiral: bool = True
    albedo_mean: float = 0.5
    albedo_variation: float = 0.06
    seed: int = 0
    identity: int | None = None
    roll_deg: float = 0.0
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0

    @property
    def core_radius_m(self) -> float:
        """Radius over which the whorl's ridge amplitude fades out at the core."""
        return _CORE_RADIUS_PERIODS * self.ridge_period_m

    @functools.cached_property
    def relief(self) -> RidgeRelief | None:
        """The synthetic fingerprint of ``identity`` (None: the whorl), cached per identity."""
        return None if self.identity is None else relief_for_identity(self.identity)

    def pitch_matrix(self) -> np.ndarray:
        """(3, 3) rotation, optical frame <- finger frame, about the x axis (``pitch_deg``)."""
        c, s = np.cos(np.deg2rad(self.pitch_deg)), np.sin(np.deg2rad(self.pitch_deg))
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])

    def to_finger_frame(self, points_optical: np.ndarray) -> np.ndarray:
        """Points (..., 3) of the optical frame in the frame the height field is defined in
        (``pitch_deg`` undone about the apex); the points themselves when it is 0."""
        if self.pitch_deg == 0.0:
            return points_optical
        apex = np.asarray(self.apex_optical_m, dtype=np.float64)
        return (np.asarray(points_optical) - apex) @ self.pitch_matrix() + apex

    def _base(
        self, dx: np.ndarray, dy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Base surface: (sag, dsag/dX, dsag/dY, inside, U, V), all shaped like ``dx``."""
        big_r = self.radius_m
        theta = np.deg2rad(self.max_slope_deg)
        r_max = big_r * np.sin(theta)
        e = self.tip_elongation
        tip = dy < 0.0
        ey = np.where(tip, dy / e, 0.0)
        r = np.hypot(dx, ey)
        inside = r <= r_max
        rc = np.minimum(r, r_max)
        root = np.sqrt(big_r * big_r - rc * rc)
        cone = big_r * (1.0 - np.cos(theta)) + np.tan(theta) * (r - r_max)
        sag = np.where(inside, big_r - root, cone)
        slope_over_r = np.where(inside, 1.0 / root, np.tan(theta) / np.maximum(r, 1e-300))
        gx = slope_over_r * dx
        gy = slope_over_r * ey / e
        shaft_dy = np.where(tip, 0.0, dy)
        sag = sag + shaft_dy**2 / (2.0 * self.length_radius_m)
        gy = gy + shaft_dy / self.length_radius_m
        safe = np.maximum(rc, 1e-12)
        unroll = np.where(rc > 1e-12, big_r * np.arcsin(safe / big_r) / safe, 1.0)
        u = dx * unroll
        v = np.where(tip, dy * unroll, dy)
        return sag, gx, gy, inside, u, v

    def _ridge(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Ridge displacement along the normal (towards the camera), metres."""
        rng = np.random.default_rng(self.seed)
        phi1, phi2 = rng.uniform(0.0, 2.0 * np.pi, size=2)
        w = self.warp_amplitude_m
        uu = u - self.core_offset_m[0] + w * np.sin(2.0 * np.pi * v / _WARP_WAVELENGTHS_M[0] + phi1)
        vv = v - self.core_offset_m[1] + w * np.sin(2.0 * np.pi * u / _WARP_WAVELENGTHS_M[1] + phi2)
        q = self.ridge_ellipticity
        rho = np.sqrt(q * uu * uu + vv * vv / q)
        phase = rho / self.ridge_period_m
        if self.spiral:
            phase = phase + np.arctan2(vv, uu) / (2.0 * np.pi)
        fade = -np.expm1(-((rho / self.core_radius_m) ** 2))
        return 0.5 * self.ridge_height_m * np.cos(2.0 * np.pi * phase) * fade

    def height(self, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, ...]:
        """Surface Z relative to the apex plane, + away from the camera.

        Parameters
        ----------
        dx, dy : ndarray float64
            X - Xa, Y - Ya, metres.

        Returns
        -------
        h, base_gx, base_gy : ndarray float64
            Height and the gradient of the base surface (without ridges).
        inside : ndarray bool
            Inside the finger's silhouette contour.
        u, v : ndarray float64
            Unrolled surface coordinates, metres, where the skin pattern and the albedo are
            evaluated: the whorl's (U, V), or ``skin_coordinates`` with a ``relief``.
        """
        fx, fy = self._to_finger(dx, dy)
        sag, gx, gy, inside, u, v = self._base(fx, fy)
        if self.relief is not None:
            u, v = self.skin_coordinates(fx, fy, finger_frame=True)
            ridge = 0.5 * self.ridge_height_m * self.relief(u, v)
        else:
            if self.roll_deg != 0.0:
                u, v = self._rolled_whorl_coordinates(fx, fy)
            ridge = self._ridge(u, v)
        h = sag - ridge * np.sqrt(1.0 + gx * gx + gy * gy)
        if self.yaw_deg != 0.0:
            c, s = np.cos(np.deg2rad(self.yaw_deg)), np.sin(np.deg2rad(self.yaw_deg))
            gx, gy = c * gx - s * gy, s * gx + c * gy
        return h, gx, gy, inside, u, v

    def _to_finger(self, dx: np.ndarray, dy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Offsets from the apex in the finger's frame (``yaw_deg`` undone)."""
        if self.yaw_deg == 0.0:
            return dx, dy
        c, s = np.cos(np.deg2rad(self.yaw_deg)), np.sin(np.deg2rad(self.yaw_deg))
        return c * dx + s * dy, c * dy - s * dx

    def _azimuth(
        self, fx: np.ndarray, fy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(theta - roll, rho, dY / e on the cap else 0) in the finger's frame."""
        big_r = self.radius_m
        tip = fy < 0.0
        ey = np.where(tip, fy / self.tip_elongation, 0.0)
        rho = np.sqrt(np.maximum(big_r * big_r - ey * ey, (1e-3 * big_r) ** 2))
        theta = np.arcsin(np.clip(fx / rho, -1.0, 1.0)) - np.deg2rad(self.roll_deg)
        return theta, rho, ey

    def skin_coordinates(
        self, dx: np.ndarray, dy: np.ndarray, *, finger_frame: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Skin coordinates (x, y), metres from the apex, of surface points (module docstring).

        Parameters
        ----------
        dx, dy : ndarray float64
            X - Xa, Y - Ya of points on the surface, metres (already in the finger's frame,
            ``yaw_deg`` undone, when ``finger_frame``).

        Returns
        -------
        x, y : ndarray float64
            Arc length around the finger, -rho * (theta - roll) (mirrored: towards -x as
            the camera sees it, module docstring), and along it from the apex.
        """
        fx, fy = (dx, dy) if finger_frame else self._to_finger(dx, dy)
        theta, rho, ey = self._azimuth(fx, fy)
        big_r, e = self.radius_m, self.tip_elongation
        beta = np.arcsin(np.clip(ey / big_r, -1.0, 0.0))
        cap_y = e * big_r * special.ellipeinc(beta, 1.0 - 1.0 / (e * e))
        big_l = self.length_radius_m
        shaft = np.maximum(fy, 0.0) / big_l
        shaft_y = 0.5 * big_l * (shaft * np.sqrt(1.0 + shaft * shaft) + np.arcsinh(shaft))
        return -rho * theta, np.where(fy < 0.0, cap_y, shaft_y)

    def _rolled_whorl_coordinates(
        self, fx: np.ndarray, fy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The whorl's (U, V) of the skin point ``roll_deg`` brought to (fx, fy)."""
        theta, rho, ey = self._azimuth(fx, fy)
        big_r = self.radius_m
        sx = rho * np.sin(theta)
        r = np.hypot(sx, ey)
        safe = np.maximum(r, 1e-12)
        unroll = np.where(
            r > 1e-12, big_r * np.arcsin(np.minimum(safe / big_r, 1.0)) / safe, 1.0
        )
        return sx * unroll, np.where(fy < 0.0, fy * unroll, fy)

    def albedo(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Smoothly varying albedo at unrolled coordinates (u, v), clipped to [0.02, 1]."""
        rng = np.random.default_rng(self.seed + 1)
        angles = rng.uniform(0.0, np.pi, _ALBEDO_COMPONENTS)
        wavelengths = rng.uniform(*_ALBEDO_WAVELENGTHS_M, _ALBEDO_COMPONENTS)
        phases = rng.uniform(0.0, 2.0 * np.pi, _ALBEDO_COMPONENTS)
        pattern = np.zeros(np.shape(u))
        for a, lam, ph in zip(angles, wavelengths, phases, strict=True):
            pattern += np.cos(2.0 * np.pi * (u * np.cos(a) + v * np.sin(a)) / lam + ph)
        pattern *= np.sqrt(2.0 / _ALBEDO_COMPONENTS)  # unit standard deviation
        return np.clip(self.albedo_mean * (1.0 + self.albedo_variation * pattern), 0.02, 1.0)


@dataclass(frozen=True)
class FingertipSurface:
    """The fingertip as seen through each pixel centre.

    Attributes
    ----------
    points_optical : (H, W, 3) float64
        Surface point on each pixel's ray (also outside the mask, on the continuation).
    normals_ps : (H, W, 3) float64
        Unit normals, PS frame; zeros outside the mask.
    mask : (H, W) bool
        Finger silhouette.
    albedo : (H, W) float64
        Albedo; zeros outside the mask.
    """

    points_optical: np.ndarray
    normals_ps: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray


def _intersect(shape: FingertipShape, rx: np.ndarray, ry: np.ndarray) -> np.ndarray:
    """Depth t (N,) of the first intersection of rays (rx, ry, 1) (N,) with the height field.

    Three Newton steps with the base surface's gradient as the Jacobian (it ignores the
    ridges), then secant steps on the pixels not yet converged.
    """
    xa, ya, za = shape.apex_optical_m
    t = np.full(rx.shape, float(za))
    for _ in range(3):
        h, gx, gy = shape.height(t * rx - xa, t * ry - ya)[:3]
        t_prev, f_prev = t, za + h - t
        t = t - f_prev / (gx * rx + gy * ry - 1.0)
    active = np.arange(rx.size)
    for _ in range(_NEWTON_MAX_ITER):
        ta, rxa, rya = t[active], rx[active], ry[active]
        f = za + shape.height(ta * rxa - xa, ta * rya - ya)[0] - ta
        done = np.abs(f) < _NEWTON_TOLERANCE_M
        df = f - f_prev[active]
        step = np.where(df != 0.0, f * (ta - t_prev[active]) / np.where(df != 0.0, df, 1.0), 0.0)
        t_prev[active] = ta
        f_prev[active] = f
        t[active] = np.where(done, ta, ta - step)
        active = active[~done]
        if active.size == 0:
            break
    return t


def trace_fingertip(shape: FingertipShape, rays_optical: np.ndarray) -> FingertipSurface:
    """Intersect pixel rays with the fingertip height field.

    Newton iteration on t = Za + h(t*rx - Xa, t*ry - Ya) along each ray (rays scaled to
    z = 1, so t is the depth Z), with the base surface's gradient as the Jacobian. With a
    ``pitch_deg``, in the finger's frame (module docstring).

    Parameters
    ----------
    shape : FingertipShape
    rays_optical : (H, W, 3) float64
        Pixel rays with z = 1 (``PinholeCamera.pixel_rays``).

    Returns
    -------
    FingertipSurface
    """
    if shape.pitch_deg != 0.0:
        return _trace_pitched(shape, rays_optical)
    xa, ya, za = shape.apex_optical_m
    rx = rays_optical[..., 0].ravel()
    ry = rays_optical[..., 1].ravel()
    t = _intersect(shape, rx, ry)
    h, _, _, inside, u, v = shape.height(t * rx - xa, t * ry - ya)
    converged = np.abs(za + h - t) < 1e-9
    shape_2d = rays_optical.shape[:-1]
    t, inside, converged, u, v = (a.reshape(shape_2d) for a in (t, inside, converged, u, v))
    mask = inside & converged
    points = t[..., None] * rays_optical

    dx = points[mask][:, 0] - xa
    dy = points[mask][:, 1] - ya
    eps = _FD_STEP_M
    hx = (shape.height(dx + eps, dy)[0] - shape.height(dx - eps, dy)[0]) / (2.0 * eps)
    hy = (shape.height(dx, dy + eps)[0] - shape.height(dx, dy - eps)[0]) / (2.0 * eps)
    n_opt = np.stack([hx, hy, -np.ones_like(hx)], axis=-1)
    n_opt /= np.linalg.norm(n_opt, axis=-1, keepdims=True)
    normals = np.zeros(points.shape)
    normals[mask] = optical_to_ps(n_opt)
    albedo = np.zeros(mask.shape)
    albedo[mask] = shape.albedo(u[mask], v[mask])
    return FingertipSurface(points_optical=points, normals_ps=normals, mask=mask, albedo=albedo)


def _trace_pitched(shape: FingertipShape, rays_optical: np.ndarray) -> FingertipSurface:
    """``trace_fingertip`` of a pitched finger: in the finger's frame, where the camera
    centre is at ``origin`` and a ray's direction is R^T d; the tracer takes rays from its
    origin, so the apex is moved by -origin instead, and the hits are moved back."""
    rot = shape.pitch_matrix()
    apex = np.asarray(shape.apex_optical_m, dtype=np.float64)
    origin = apex - rot.T @ apex
    rays = rays_optical @ rot
    if np.any(rays[..., 2] <= 0.0):
        raise ValueError("pitch_deg turns some pixel rays away from the finger")
    rays = rays / rays[..., 2:]
    level = replace(shape, apex_optical_m=tuple(apex - origin), pitch_deg=0.0)
    surface = trace_fingertip(level, rays)
    points = (surface.points_optical + origin - apex) @ rot.T + apex
    normals = optical_to_ps(ps_to_optical(surface.normals_ps) @ rot.T)
    return FingertipSurface(
        points_optical=points, normals_ps=normals, mask=surface.mask, albedo=surface.albedo
    )
