"""A contact (plain) impression of a synthetic finger, as a 500 ppi plate scanner makes it.

The finger's ridge pattern is its rolled print (``fingerprint_pattern``, the rolled plane in
mm, sampled through ``fingerprint_relief.RidgeRelief.value_at_mm``, the interpolant the rig
renders the skin with). A finger pressed flat on a plate touches it with its central pad;
the impression is built in four steps, each drawn per impression from a seeded generator:

1. Contact (the skin that touches). Pressed flat, the pad's skin lies on the plate with its
   arc lengths kept (skin hardly stretches in its plane), so the undistorted impression is
   the rolled plane itself about the contact's centre: u = r - c, mm. The contact is an
   ellipse about c (c = the apex of the rolled plane, ``RidgeRelief.apex_mm``, shifted by
   up to +-``centre_jitter_mm``: which part of the pad is pressed), of semi-axes
   ``semi_axes_mm`` x (F / F0)^(1/3) (Hertz: the contact radius of an elastic body on a
   flat grows as the cube root of the force), the relative force F / F0 log-uniform in
   ``force_range``; the pressure inside follows Hertz's profile P = sqrt(1 - rho^2)
   (rho the ellipse's normalised radius). Skin outside the fingertip's outline (the
   pattern's mask) does not touch.
2. Plastic distortion: the model of Cappelli, Maio & Maltoni, "Modelling plastic
   distortion in fingerprint images", ICAPR 2001 (LNCS 2013; also in the Handbook of
   Fingerprint Recognition, Maltoni et al., on synthetic fingerprints): a
   close-contact region a (an ellipse about the contact's centre, ``close_fraction`` of the
   contact's semi-axes) where pressure and friction keep the skin from slipping; an
   external region c, dragged with the finger by a rigid transform T (rotation theta about
   a's centre, uniform in +-``drag_rotation_deg``, then translation d, uniform in a disc of
   radius ``drag_translation_mm``); and a transition region b between them where the skin
   is compressed and stretched. Each point moves by

       distortion(u) = u + Delta(u) brake(shapedist_a(u), k),   Delta(u) = T(u) - u,

   with shapedist_a(u) the distance of u outside a (0 inside; here measured along the ray
   from a's centre, |u| (1 - 1/rho_a)) and the brake function, here
   brake(s, k) = 1 - exp(-s^2 / (2 k^2)) (0 in a, rising smoothly to 1; ``brake_k_mm`` = k;
   the Gaussian form is our reading of the paper, not checked against its text, which was
   not at hand: a brake that rises linearly from a's border would put a crease there).
   The map is smooth (C1 across a's border) and, for the drawn ranges, one-to-one: its
   Jacobian determinant stays positive (|Delta| <= ~1.5 mm, |grad brake| <= 0.61 / k;
   0.64-1.36 over 200 draws of the defaults: the skin compressed or stretched by up to
   ~35 % in b), so the skin neither tears nor folds. The impression shows, at plate
   point w, the skin u with distortion(u) = w: solved by the fixed-point iteration
   u <- w - Delta(u) brake(u) (a contraction with the factor above).
3. Placement: the distorted impression is turned by phi (uniform +-``placement_deg``) and
   shifted (uniform +-``placement_mm`` in x and y) on the plate, about the plate's centre.
4. The scanner's look (an FTIR optical scanner: ridges in contact dark, valleys and the
   empty plate light): a ridge touches where its relief value exceeds a threshold that
   falls with the local pressure (``threshold_centre`` at the centre, ``threshold_edge`` at
   the edge, above the ridge tops: the ridges thin out towards the contact's outline; each
   doubling of the force lowers it by ``threshold_per_doubling``: wider ridges) and rises
   with the skin's dryness (a smooth random field of correlation ``dryness_scale_mm``, its
   amplitude drawn per impression: broken, thin ridges where the skin is dry);
   the grey is a ridge grey and a valley grey drawn per impression, blurred by the optics
   (``blur_px``), with a gentle illumination ramp and sensor noise (drawn sigma).

Coordinates: the plate image is ``height_px`` x ``width_px`` at ``ppi``; pixel (i, j)
centred at ((j + 0.5) p, (i + 0.5) p) mm, x right, y down, as the rolled plane. A contact
print, like the rolled print, is the mirror image of the skin seen from outside: it is in
the rolled plane's orientation (no flip).

Public API::

    impression = contact_impression(relief_for_identity(3), seed=[7, 3, 0])
    impression.image      # (H, W) uint8, 500 ppi
    impression.rolled_mm  # (H, W, 2): the rolled-plane point each pixel shows, NaN off contact
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from fingerps_driver.simulation.fingerprint_relief import RidgeRelief

_FIXED_POINT_TOLERANCE_MM = 1e-9
_FIXED_POINT_MAX_ITER = 200


@dataclass(frozen=True)
class ContactScanner:
    """The scanner and the ranges each impression's parameters are drawn from (module
    docstring). Lengths in mm on the plate; the image is 0.8 x 1.0 in at 500 ppi."""

    width_px: int = 400
    height_px: int = 500
    ppi: float = 500.0
    semi_axes_mm: tuple[float, float] = (6.5, 8.5)
    force_range: tuple[float, float] = (0.5, 2.0)
    centre_jitter_mm: float = 1.0
    close_fraction: float = 0.35
    brake_k_mm: float = 1.75
    drag_rotation_deg: float = 3.0
    drag_translation_mm: float = 1.0
    placement_deg: float = 15.0
    placement_mm: float = 2.0
    threshold_centre: float = 0.0
    threshold_edge: float = 1.2
    threshold_per_doubling: float = 0.15
    flank_width: float = 0.35
    dryness_scale_mm: float = 1.5
    dryness_range: tuple[float, float] = (0.05, 0.3)
    ridge_grey_range: tuple[float, float] = (25.0, 70.0)
    valley_grey_range: tuple[float, float] = (200.0, 235.0)
    illumination_ramp: float = 0.05
    noise_sigma_range: tuple[float, float] = (3.0, 8.0)
    blur_px: float = 0.6

    @property
    def pixel_mm(self) -> float:
        return 25.4 / self.ppi


@dataclass(frozen=True)
class ContactDraw:
    """One impression's drawn parameters.

    Attributes
    ----------
    force : float
        F / F0.
    centre_mm : (2,) float
        The contact's centre c in the rolled plane.
    semi_axes_mm, close_semi_axes_mm : (2,) float
        The contact ellipse and the close-contact region a (x, y semi-axes, mm).
    drag_rotation_rad : float
        theta of the rigid transform T (positive: from +x towards +y, i.e. clockwise as
        displayed), about a's centre.
    drag_translation_mm : (2,) float
        d of T.
    placement_rad : float
        phi, the impression's rotation on the plate (same sense).
    placement_shift_mm : (2,) float
        The contact's centre on the plate relative to the plate's centre.
    dryness : float
        Amplitude of the dryness field (threshold units).
    ridge_grey, valley_grey, noise_sigma : float
    """

    force: float
    centre_mm: tuple[float, float]
    semi_axes_mm: tuple[float, float]
    close_semi_axes_mm: tuple[float, float]
    drag_rotation_rad: float
    drag_translation_mm: tuple[float, float]
    placement_rad: float
    placement_shift_mm: tuple[float, float]
    dryness: float
    ridge_grey: float
    valley_grey: float
    noise_sigma: float


@dataclass(frozen=True)
class ContactImpression:
    """One contact impression.

    Attributes
    ----------
    image : (H, W) uint8
        The scanner's image, ridges dark, ``pixel_mm`` a pixel.
    rolled_mm : (H, W, 2) float64
        The rolled-plane point (x, y) mm whose skin each pixel shows; NaN off the contact.
    contact : (H, W) bool
        Pixels showing skin in contact (the ellipse, inside the fingertip's outline).
    brake : (H, W) float64
        brake(shapedist_a(u), k) of the skin each pixel shows: 0 in the close-contact
        region, -> 1 in the external region; NaN off the contact.
    draw : ContactDraw
    pixel_mm : float
    """

    image: np.ndarray
    rolled_mm: np.ndarray
    contact: np.ndarray
    brake: np.ndarray
    draw: ContactDraw
    pixel_mm: float


def rotation(angle_rad: float) -> np.ndarray:
    """(2, 2) rotation from +x towards +y (x right, y down: clockwise as displayed)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s], [s, c]])


def brake(shapedist_mm: np.ndarray, k_mm: float) -> np.ndarray:
    """Cappelli et al.'s brake: 0 for s <= 0, 1 - exp(-s^2 / (2 k^2)) beyond."""
    s = np.maximum(np.asarray(shapedist_mm, dtype=np.float64), 0.0)
    return 1.0 - np.exp(-(s * s) / (2.0 * k_mm * k_mm))


def ellipse_radius(u_mm: np.ndarray, semi_axes_mm: Sequence[float]) -> np.ndarray:
    """(...) normalised radius rho of points (..., 2) in an ellipse about 0 (1 on it)."""
    return np.hypot(u_mm[..., 0] / semi_axes_mm[0], u_mm[..., 1] / semi_axes_mm[1])


def shapedist(u_mm: np.ndarray, semi_axes_mm: Sequence[float]) -> np.ndarray:
    """(...) distance (mm) of points (..., 2) outside the ellipse about 0, along the ray
    from its centre: |u| (1 - 1/rho), 0 inside."""
    rho = ellipse_radius(u_mm, semi_axes_mm)
    outside = rho > 1.0
    return np.where(outside, np.hypot(u_mm[..., 0], u_mm[..., 1])
                    * (1.0 - 1.0 / np.where(outside, rho, 1.0)), 0.0)


def drag_displacement(u_mm: np.ndarray, draw: ContactDraw) -> np.ndarray:
    """(..., 2) Delta(u) = T(u) - u of Cappelli et al.'s rigid transform T."""
    r = rotation(draw.drag_rotation_rad)
    return u_mm @ (r - np.eye(2)).T + np.asarray(draw.drag_translation_mm)


def distort(u_mm: np.ndarray, draw: ContactDraw, *, k_mm: float) -> np.ndarray:
    """(..., 2) distortion(u) = u + Delta(u) brake(shapedist_a(u), k) (module docstring)."""
    b = brake(shapedist(u_mm, draw.close_semi_axes_mm), k_mm)
    return u_mm + drag_displacement(u_mm, draw) * b[..., None]


def undistort(w_mm: np.ndarray, draw: ContactDraw, *, k_mm: float) -> np.ndarray:
    """(..., 2) the skin u with ``distort(u) == w``, by fixed-point iteration.

    Raises
    ------
    ValueError
        If it does not converge (a drawn distortion that folds the skin: keep
        ``drag_translation_mm`` and ``drag_rotation_deg`` small against ``brake_k_mm``).
    """
    w = np.asarray(w_mm, dtype=np.float64)
    u = w.copy()
    for _ in range(_FIXED_POINT_MAX_ITER):
        b = brake(shapedist(u, draw.close_semi_axes_mm), k_mm)
        nxt = w - drag_displacement(u, draw) * b[..., None]
        step = float(np.max(np.abs(nxt - u), initial=0.0))
        u = nxt
        if step < _FIXED_POINT_TOLERANCE_MM:
            return u
    raise ValueError(f"the contact distortion did not invert (last step {step:.2e} mm): "
                     "reduce the drag against brake_k_mm")


def draw_contact(rng: np.random.Generator, apex_mm: Sequence[float],
                 scanner: ContactScanner) -> ContactDraw:
    """One impression's parameters drawn from ``scanner``'s ranges (module docstring)."""
    force = float(np.exp(rng.uniform(*np.log(scanner.force_range))))
    size = force ** (1.0 / 3.0)
    centre = np.asarray(apex_mm, dtype=np.float64) + rng.uniform(
        -scanner.centre_jitter_mm, scanner.centre_jitter_mm, 2)
    semi = np.asarray(scanner.semi_axes_mm) * size
    theta = np.radians(rng.uniform(-scanner.drag_rotation_deg, scanner.drag_rotation_deg))
    radius = scanner.drag_translation_mm * np.sqrt(rng.uniform())
    direction = rng.uniform(0.0, 2.0 * np.pi)
    phi = np.radians(rng.uniform(-scanner.placement_deg, scanner.placement_deg))
    shift = rng.uniform(-scanner.placement_mm, scanner.placement_mm, 2)
    return ContactDraw(
        force=force,
        centre_mm=(float(centre[0]), float(centre[1])),
        semi_axes_mm=(float(semi[0]), float(semi[1])),
        close_semi_axes_mm=(float(semi[0] * scanner.close_fraction),
                            float(semi[1] * scanner.close_fraction)),
        drag_rotation_rad=float(theta),
        drag_translation_mm=(float(radius * np.cos(direction)),
                             float(radius * np.sin(direction))),
        placement_rad=float(phi),
        placement_shift_mm=(float(shift[0]), float(shift[1])),
        dryness=float(rng.uniform(*scanner.dryness_range)),
        ridge_grey=float(rng.uniform(*scanner.ridge_grey_range)),
        valley_grey=float(rng.uniform(*scanner.valley_grey_range)),
        noise_sigma=float(rng.uniform(*scanner.noise_sigma_range)),
    )


def plate_mm(scanner: ContactScanner) -> np.ndarray:
    """(H, W, 2) the plate position (x, y) mm of each pixel's centre."""
    p = scanner.pixel_mm
    x = (np.arange(scanner.width_px) + 0.5) * p
    y = (np.arange(scanner.height_px) + 0.5) * p
    return np.stack(np.meshgrid(x, y), axis=-1)


def plate_to_impression(plate: np.ndarray, draw: ContactDraw,
                        scanner: ContactScanner) -> np.ndarray:
    """(..., 2) the distorted impression's point w (about the contact's centre) at plate
    points (..., 2): the placement undone."""
    centre = np.array([scanner.width_px, scanner.height_px]) * scanner.pixel_mm / 2.0
    rel = plate - centre - np.asarray(draw.placement_shift_mm)
    return rel @ rotation(draw.placement_rad)  # R^T applied to row vectors


def contact_impression(relief: RidgeRelief, *, seed: int | Sequence[int],
                       scanner: ContactScanner | None = None) -> ContactImpression:
    """A contact impression of the finger carrying ``relief`` (module docstring).

    Parameters
    ----------
    relief : RidgeRelief
        The finger (``fingerprint_relief.relief_for_identity``).
    seed : int or sequence of int
        The impression's seed (``numpy.random.SeedSequence``): the same seed gives the same
        impression; each impression of a finger takes its own.
    scanner : ContactScanner, optional

    Returns
    -------
    ContactImpression
    """
    scanner = ContactScanner() if scanner is None else scanner
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    draw = draw_contact(rng, relief.apex_mm, scanner)
    p = scanner.pixel_mm
    w = plate_to_impression(plate_mm(scanner), draw, scanner)
    u = undistort(w, draw, k_mm=scanner.brake_k_mm)
    rolled = u + np.asarray(draw.centre_mm)

    pattern = relief.pattern
    rows = np.floor(rolled[..., 1] / pattern.pixel_mm).astype(int)
    cols = np.floor(rolled[..., 0] / pattern.pixel_mm).astype(int)
    on_grid = ((rows >= 0) & (rows < pattern.mask.shape[0])
               & (cols >= 0) & (cols < pattern.mask.shape[1]))
    rho = ellipse_radius(u, draw.semi_axes_mm)
    contact = (rho < 1.0) & on_grid
    contact[on_grid] &= pattern.mask[rows[on_grid], cols[on_grid]]

    # Where a ridge touches: its relief above a threshold that falls with the pressure
    # (Hertz's profile; more force, a lower threshold) and rises where the skin is dry.
    pressure = np.sqrt(np.clip(1.0 - rho * rho, 0.0, 1.0))
    centre_level = scanner.threshold_centre - scanner.threshold_per_doubling * np.log2(
        draw.force)
    dry = ndimage.gaussian_filter(rng.standard_normal(contact.shape),
                                  scanner.dryness_scale_mm / p, mode="reflect")
    dry /= max(float(dry.std()), 1e-12)
    threshold = (scanner.threshold_edge
                 - (scanner.threshold_edge - centre_level) * pressure
                 + draw.dryness * dry)
    value = np.zeros(contact.shape)
    value[contact] = relief.value_at_mm(rolled[contact, 0], rolled[contact, 1])
    t = np.clip((value - threshold) / scanner.flank_width + 0.5, 0.0, 1.0)
    touching = np.where(contact, t * t * (3.0 - 2.0 * t), 0.0)

    grey = draw.valley_grey - (draw.valley_grey - draw.ridge_grey) * touching
    grey = cv2.GaussianBlur(grey, (0, 0), scanner.blur_px)
    ramp_dir = rng.uniform(0.0, 2.0 * np.pi)
    plate = plate_mm(scanner)
    extent = np.array([scanner.width_px, scanner.height_px]) * p
    ramp = ((plate[..., 0] / extent[0] - 0.5) * np.cos(ramp_dir)
            + (plate[..., 1] / extent[1] - 0.5) * np.sin(ramp_dir))
    grey = grey * (1.0 + scanner.illumination_ramp * ramp)
    grey = grey + draw.noise_sigma * rng.standard_normal(grey.shape)
    image = np.clip(np.rint(grey), 0, 255).astype(np.uint8)

    rolled_out = np.where(contact[..., None], rolled, np.nan)
    b = np.where(contact, brake(shapedist(u, draw.close_semi_axes_mm), scanner.brake_k_mm),
                 np.nan)
    return ContactImpression(image=image, rolled_mm=rolled_out, contact=contact, brake=b,
                             draw=draw, pixel_mm=p)
