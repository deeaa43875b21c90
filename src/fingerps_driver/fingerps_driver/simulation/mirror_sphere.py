"""Shiny calibration sphere of known radius (paper Sec. 3.1), rendered by exact ray casting.

Per sub-pixel sample the camera ray is intersected with the sphere. The sphere reflects a
weak Lambertian part (so its silhouette shows against the dark background wherever some
lit LED reaches it; under one LED the limb facing away from it is in attached shadow) plus
a mirror part: the view ray reflected about the normal, R = 2 (N.V) N - V (Eq. 10), picks up
the radiance of the LED's emitting disc where it hits it. The mirror image of a 1.5 mm disc
80-100 mm away in a 4 mm ball is only ~1 pixel across, so the specular part is blurred by a
Gaussian point-spread function (the lens), which makes the highlight a small saturating
blob with soft edges centred on the exact mirror point (``specular_point``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from fingerps_driver.simulation.camera import PinholeCamera
from fingerps_driver.simulation.led_field import LedRing
from fingerps_recon.photometric.frames import optical_to_ps

_ROW_CHUNK = 32
_HIGHLIGHT_SUPERSAMPLE = 8
_BISECTION_STEPS = 80


@dataclass(frozen=True)
class MirrorSphere:
    """A ball with a mirror finish and a weak diffuse part, and how it is imaged; the
    defaults are the rig's 4 mm steel ball.

    Attributes
    ----------
    center_optical_m : (3,) float
        Centre, metres, optical frame.
    radius_m : float
        Radius r.
    diffuse_albedo : float
        Albedo of the Lambertian part.
    specular_reflectance : float
        Mirror reflectance (steel ~0.6).
    supersample : int
        Sub-pixel samples per pixel axis for the coverage of silhouette pixels.
    psf_sigma_px : float
        Lens blur of the specular highlight: standard deviation of a Gaussian, pixels.
    """

    center_optical_m: tuple[float, float, float] = (2.0e-3, -1.5e-3, 0.094)
    radius_m: float = 4e-3
    diffuse_albedo: float = 0.08
    specular_reflectance: float = 0.6
    supersample: int = 4
    psf_sigma_px: float = 1.0

    def intersect(self, rays_optical: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First intersection of rays from the camera centre with the sphere.

        Parameters
        ----------
        rays_optical : (..., 3) float64
            Ray directions (any length), optical frame.

        Returns
        -------
        points : (..., 3) float64
            Intersection points (undefined where ``hit`` is False).
        normals_optical : (..., 3) float64
            Outward unit normals there.
        hit : (...) bool
        """
        d = np.asarray(rays_optical, dtype=np.float64)
        s = np.asarray(self.center_optical_m, dtype=np.float64)
        a = np.einsum("...i,...i->...", d, d)
        b = d @ s
        disc = b * b - a * (s @ s - self.radius_m**2)
        hit = disc >= 0.0
        t = (b - np.sqrt(np.maximum(disc, 0.0))) / a
        points = t[..., None] * d
        return points, (points - s) / self.radius_m, hit

    def nearest_points(self, rays_optical: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Intersection points of rays, or for rays that miss, the limb point nearest them.

        Returns (points, normals_optical), both (..., 3) float64.
        """
        d = np.asarray(rays_optical, dtype=np.float64)
        _, normals, hit = self.intersect(d)
        s = np.asarray(self.center_optical_m, dtype=np.float64)
        closest = ((d @ s) / np.einsum("...i,...i->...", d, d))[..., None] * d
        outward = closest - s
        outward /= np.maximum(np.linalg.norm(outward, axis=-1, keepdims=True), 1e-300)
        normals = np.where(hit[..., None], normals, outward)
        return s + self.radius_m * normals, normals

    def coverage(
        self,
        camera: PinholeCamera,
        *,
        rows: tuple[int, int],
        cols: tuple[int, int],
        supersample: int,
    ) -> np.ndarray:
        """Fraction (h, w) float64 of each pixel's sub-pixel rays that hit the sphere."""
        s = np.asarray(self.center_optical_m, dtype=np.float64)
        c = s @ s - self.radius_m**2
        out = np.empty((rows[1] - rows[0], cols[1] - cols[0]))
        for a in range(rows[0], rows[1], _ROW_CHUNK):
            b = min(a + _ROW_CHUNK, rows[1])
            d = camera.pixel_rays(rows=(a, b), cols=cols, supersample=supersample)
            d = d.reshape(b - a, cols[1] - cols[0], -1, 3)
            proj = d @ s
            out[a - rows[0] : b - rows[0]] = (
                proj * proj >= np.einsum("...i,...i->...", d, d) * c
            ).mean(axis=-1)
        return out

    def pixel_window(
        self, camera: PinholeCamera, *, margin_px: int = 2
    ) -> tuple[tuple[int, int], tuple[int, int]]:
        """Rows and columns (half-open, clipped to the image) covering the silhouette."""
        s = np.asarray(self.center_optical_m, dtype=np.float64)
        dist2 = s @ s
        centre = s * (1.0 - self.radius_m**2 / dist2)  # of the circle of tangency
        radius = self.radius_m * np.sqrt(1.0 - self.radius_m**2 / dist2)
        e1 = np.cross(s, [0.0, 1.0, 0.0] if abs(s[1]) < abs(s[0]) else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(s, e1) / np.sqrt(dist2)
        phi = np.linspace(0.0, 2.0 * np.pi, 721)[:, None]
        rim = centre + radius * (np.cos(phi) * e1 + np.sin(phi) * e2)
        uv = camera.project(rim)
        c0 = int(np.clip(np.floor(uv[:, 0].min()) - margin_px, 0, camera.width))
        c1 = int(np.clip(np.ceil(uv[:, 0].max()) + margin_px + 1, 0, camera.width))
        r0 = int(np.clip(np.floor(uv[:, 1].min()) - margin_px, 0, camera.height))
        r1 = int(np.clip(np.ceil(uv[:, 1].max()) + margin_px + 1, 0, camera.height))
        return (r0, r1), (c0, c1)

    def specular_point(self, led_position_optical: np.ndarray) -> np.ndarray:
        """Point (3,) on the sphere that mirrors a point light into the camera centre.

        Its normal bisects the directions to the camera (the origin) and to the light; it lies
        in the plane through the camera, the centre and the light. Solved by bisection on the
        angle of the normal in that plane.
        """
        s = np.asarray(self.center_optical_m, dtype=np.float64)
        light = np.asarray(led_position_optical, dtype=np.float64)
        e1 = -s / np.linalg.norm(s)
        e2 = (light - s) - ((light - s) @ e1) * e1
        e2 /= np.linalg.norm(e2)
        e3 = np.cross(e1, e2)

        def mismatch(theta: float) -> float:
            n = np.cos(theta) * e1 + np.sin(theta) * e2
            p = s + self.radius_m * n
            v = -p / np.linalg.norm(p)
            lv = (light - p) / np.linalg.norm(light - p)
            return float(np.cross(n, v + lv) @ e3)

        lo, hi = 0.0, 0.5 * np.pi
        f_lo = mismatch(lo)
        for _ in range(_BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            f_mid = mismatch(mid)
            if (f_mid > 0.0) == (f_lo > 0.0):
                lo, f_lo = mid, f_mid
            else:
                hi = mid
        theta = 0.5 * (lo + hi)
        return s + self.radius_m * (np.cos(theta) * e1 + np.sin(theta) * e2)


def render_sphere(
    sphere: MirrorSphere,
    camera: PinholeCamera,
    leds: LedRing,
    k: int,
    *,
    diffuse_shading: Callable[..., np.ndarray],
) -> np.ndarray:
    """Noiseless radiance image of the sphere under LED ``k``.

    The diffuse part is shaded at each pixel centre's ray (at the limb point nearest the
    ray where the centre misses the sphere) and weighted by the pixel's coverage, measured
    on ``sphere.supersample`` x ``sphere.supersample`` sub-pixel rays: an anti-aliased
    silhouette. The specular part is ray-traced on 8 x 8 sub-pixel rays in a window around
    the mirror point of the LED's centre (outside it the disc's image is zero to ~1e-8),
    then blurred by the lens PSF (``sphere.psf_sigma_px``).

    Parameters
    ----------
    sphere, camera, leds : the scene
    k : int
        LED index.
    diffuse_shading : callable
        ``lambertian_shading(normals_ps, lights_ps, *, rho)`` of ``fingerps_recon``.

    Returns
    -------
    radiance : (H, W) float64
        Zero outside the sphere (apart from the blurred highlight's tails).
    """
    image = np.zeros((camera.height, camera.width))
    rows, cols = sphere.pixel_window(camera)
    if rows[1] > rows[0] and cols[1] > cols[0]:
        coverage = sphere.coverage(camera, rows=rows, cols=cols,
                                   supersample=sphere.supersample)
        points, normals = sphere.nearest_points(camera.pixel_rays(rows=rows, cols=cols))
        lights = leds.directions_optical(points, k)
        diffuse = leds.irradiance(points, k) * diffuse_shading(
            optical_to_ps(normals), optical_to_ps(lights), rho=sphere.diffuse_albedo
        )
        image[rows[0] : rows[1], cols[0] : cols[1]] = coverage * diffuse
    if sphere.specular_reflectance > 0.0:
        _add_highlight(image, sphere, camera, leds, k)
    return image


def _add_highlight(
    image: np.ndarray,
    sphere: MirrorSphere,
    camera: PinholeCamera,
    leds: LedRing,
    k: int,
) -> None:
    """Add LED ``k``'s blurred specular highlight to ``image`` (H, W) in place."""
    led = leds.positions_optical[k]
    mirror_point = sphere.specular_point(led)
    u, v = camera.project(mirror_point)
    # the disc's virtual image in a convex mirror of focal length r/2, in pixels
    led_distance = np.linalg.norm(led - mirror_point)
    image_radius_px = (
        leds.disc_radius_m * sphere.radius_m / (2.0 * led_distance) * camera.fx / mirror_point[2]
    )
    half = int(np.ceil(3.0 * image_radius_px + 2.0))
    psf_sigma_px = sphere.psf_sigma_px
    pad = int(np.ceil(4.0 * psf_sigma_px)) + 1
    r0, r1 = int(np.floor(v)) - half, int(np.floor(v)) + half + 2
    c0, c1 = int(np.floor(u)) - half, int(np.floor(u)) + half + 2
    window = np.zeros((r1 - r0 + 2 * pad, c1 - c0 + 2 * pad))
    rv0, rv1 = max(r0, 0), min(r1, camera.height)
    cv0, cv1 = max(c0, 0), min(c1, camera.width)
    if rv1 <= rv0 or cv1 <= cv0:
        return
    rays = camera.pixel_rays(rows=(rv0, rv1), cols=(cv0, cv1), supersample=_HIGHLIGHT_SUPERSAMPLE)
    points, normals, hit = sphere.intersect(rays)
    p, n, d = points[hit], normals[hit], rays[hit]
    view = -d / np.linalg.norm(d, axis=-1, keepdims=True)
    reflected = 2.0 * np.einsum("...i,...i->...", n, view)[..., None] * n - view
    samples = np.zeros(hit.shape)
    samples[hit] = sphere.specular_reflectance * leds.disc_radiance(p, reflected, k)
    window[rv0 - r0 + pad : rv1 - r0 + pad, cv0 - c0 + pad : cv1 - c0 + pad] = samples.mean(-1)
    if psf_sigma_px > 0.0:
        window = cv2.GaussianBlur(window, (0, 0), psf_sigma_px, borderType=cv2.BORDER_CONSTANT)
    a0, a1 = max(r0 - pad, 0), min(r1 + pad, camera.height)
    b0, b1 = max(c0 - pad, 0), min(c1 + pad, camera.width)
    image[a0:a1, b0:b1] += window[a0 - r0 + pad : a1 - r0 + pad, b0 - c0 + pad : b1 - c0 + pad]
