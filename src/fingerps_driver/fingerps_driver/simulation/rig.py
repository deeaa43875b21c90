"""The simulated rig: camera, seven near LEDs, and the scenes they light (finger, sphere, target).

``SimulatedRig.render`` is what a driver calls per frame: the noiseless image of each
(scene, LED) is computed once on first use and cached (float32, fraction of full scale); a
frame is then the sum of the lit LEDs' cached images, optionally translated, plus sensor noise
and quantisation (``sensor.SensorModel``). All reflectance comes from ``fingerps_recon``
(``hk_model.hk_reflectance``, ``lambertian.lambertian_shading``).

Per pixel the light direction is from the surface point to the LED position (near light) and
the view direction from the point to the camera centre (perspective), as on real hardware.
``light_directions_ps`` gives the "distant-light" directions from the fingertip apex instead,
which is what a photometric-stereo solver assuming distant lights is compared against.

Units: a unit of radiance is what a Lambertian albedo-1 surface facing a power-1 LED on its
axis at the reference distance (the working distance) reflects (``led_field``);
``exposure_gain`` (``white_target_exposure_gain`` for the white target) maps radiance to
fraction of full scale.

The finger carries the analytic spiral or, with ``RigConfig.finger_identity``, a synthetic
fingerprint, whose ground truth the rig gives: ``fingerprint`` (ridges, minutiae, singular
points), ``rolled_print()`` (500 ppi) and, per pixel, ``FingerTruth.rolled_mm``.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np

from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation.camera import PinholeCamera
from fingerps_driver.simulation.fingerprint_pattern import (
    FingerprintPattern,
    render_rolled_print,
)
from fingerps_driver.simulation.fingerprint_relief import relief_for_identity
from fingerps_driver.simulation.fingertip import FingertipShape, FingertipSurface, trace_fingertip
from fingerps_driver.simulation.led_field import LedRing
from fingerps_driver.simulation.mirror_sphere import MirrorSphere, render_sphere
from fingerps_driver.simulation.sensor import SensorModel
from fingerps_driver.simulation.white_target import WhiteTarget, render_white_target
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.hk_model import FINGER, SkinParams, hk_reflectance
from fingerps_recon.photometric.lambertian import lambertian_shading


class Scene(Enum):
    """What is in front of the camera."""

    FINGER = "finger"
    SPHERE = "sphere"
    WHITE_TARGET = "white_target"
    EMPTY = "empty"


class Reflectance(Enum):
    """Reflectance model of the finger's skin."""

    HK = "hk"
    LAMBERT = "lambert"


@dataclass(frozen=True)
class RigConfig:
    """Configuration of the simulated rig; the defaults are the standard rig.

    Frames and units as in CONVENTIONS.md: positions in metres in the camera optical frame
    (x right, y down, z forward, camera centre at the origin).

    Camera
        width, height: image size, pixels. bit_depth: 8 (uint8) or 12 (uint16, 0..4095).
        focal_px: fx = fy, pixels (3000 = 30 um a pixel at 90 mm). principal_point_px:
        (cx, cy), None for the image centre ((width - 1) / 2, (height - 1) / 2).
    Finger (``fingertip.FingertipShape``)
        finger_apex_optical_m: the point nearest the camera; its z is the working distance.
        finger_radius_m, finger_tip_elongation, finger_max_slope_deg (slope at the
        silhouette), finger_length_radius_m (bend along the finger), ridge_height_m
        (peak-to-valley), ridge_period_m, ridge_core_offset_m, ridge_ellipticity,
        ridge_warp_m, ridge_spiral, albedo_mean, albedo_variation (relative std).
        finger_identity: None for the analytic whorl/spiral (ridge_period_m ..
        ridge_spiral), or the seed of a synthetic fingerprint
        (``fingerprint_pattern.generate_fingerprint``, its own period map) carried as the
        relief instead (``fingerprint_relief``; ridge_height_m still its height).
        finger_roll_deg: rotation about the finger's own axis (in [-45, 45]; moves only the
        skin, the shape is symmetric about the axis; + brings the skin at the apex towards
        +x). finger_yaw_deg: rotation of the whole finger about the optical axis through
        the apex, from +x towards +y (clockwise as displayed; in [-90, 90]).
        finger_pitch_deg: then about the optical x axis through the apex, from +y towards +z
        (+ brings the tip towards the camera; in [-15, 15]: beyond, the tip's or the
        shaft's margin comes within a few degrees of grazing). The shift is
        finger_apex_optical_m. See ``fingertip`` for the skin coordinates and the pose.
        The fingerprint is 20 mm wide (+-72 deg about an 8 mm finger) and the standard
        finger shows +-65 deg of it: beyond ~7 deg of roll one margin shows skin past the
        print's edge, where the relief fades to flat skin.
    Reflectance
        reflectance: HK (default) or LAMBERT. hk_scale: the global scale A of the
        single-scattering term (paper Eq. 4). hk_params: skin constants (default the
        paper's finger values, ``fingerps_recon.photometric.hk_model.FINGER``).
    Sphere
        sphere_radius_m, sphere_center_optical_m, sphere_diffuse_albedo,
        sphere_specular_reflectance, sphere_supersample (samples per pixel axis),
        psf_sigma_px (lens blur of the specular highlight, pixels).
    White target
        white_target_distance_m, white_target_albedo, white_target_texture (relative std).
    LEDs (one entry per LED, index order = LED index)
        led_angles_deg: azimuth on the ring in the optical x-y plane, from +x towards +y
        (clockwise as the image is displayed). led_ring_radii_m: distance from the optical
        axis. led_heights_m: z of each LED (the lens plane is z = 0). led_powers: relative
        on-axis intensity. led_exponents: m of the cos^m emission lobe. led_aim_offsets_m:
        (x, y) offset of the point each LED's axis passes through from the apex (so the
        lobes are a little off the scene centre). led_disc_radius_m: radius of each LED's
        emitting disc as seen in the mirror sphere.
    Sensor (``sensor.SensorModel``)
        full_well_e, read_noise_e (electrons), ambient_fraction (ambient light + dark
        current in every frame, fraction of full scale), exposure_gain (fraction of full
        scale per unit radiance; the default puts the brightest finger pixels under the
        brightest LED at ~80 % of full scale), white_target_exposure_gain (the same for
        the white target, imaged with a shorter exposure as a real flat-field calibration
        would be, so that it peaks at ~90 % instead of saturating).
    texture_seed: seed of every static random pattern (ridge warp, albedo, paper texture).
    """

    width: int = 659
    height: int = 493
    bit_depth: int = 8
    focal_px: float = 3000.0
    principal_point_px: tuple[float, float] | None = None
    reflectance: Reflectance = Reflectance.HK
    hk_scale: float = 45.0
    hk_params: SkinParams = FINGER
    finger_apex_optical_m: tuple[float, float, float] = (0.0, 2.5e-3, 0.090)
    finger_radius_m: float = 8e-3
    finger_tip_elongation: float = 1.15
    finger_max_slope_deg: float = 65.0
    finger_length_radius_m: float = 25e-3
    ridge_height_m: float = 50e-6
    ridge_period_m: float = 0.5e-3
    ridge_core_offset_m: tuple[float, float] = (0.6e-3, -1.0e-3)
    ridge_ellipticity: float = 1.1
    ridge_warp_m: float = 0.25e-3
    ridge_spiral: bool = True
    albedo_mean: float = 0.5
    albedo_variation: float = 0.06
    finger_identity: int | None = None
    finger_roll_deg: float = 0.0
    finger_yaw_deg: float = 0.0
    finger_pitch_deg: float = 0.0
    sphere_radius_m: float = 4e-3
    sphere_center_optical_m: tuple[float, float, float] = (2.0e-3, -1.5e-3, 0.094)
    sphere_diffuse_albedo: float = 0.08
    sphere_specular_reflectance: float = 0.6
    sphere_supersample: int = 4
    psf_sigma_px: float = 1.0
    white_target_distance_m: float = 0.090
    white_target_albedo: float = 0.9
    white_target_texture: float = 0.01
    led_angles_deg: tuple[float, ...] = (8.0, 57.0, 110.0, 160.0, 209.0, 262.0, 313.0)
    led_ring_radii_m: tuple[float, ...] = (
        40.0e-3, 38.5e-3, 41.5e-3, 39.0e-3, 42.0e-3, 37.5e-3, 40.5e-3,
    )
    led_heights_m: tuple[float, ...] = (1.0e-3, -1.5e-3, 0.5e-3, 2.0e-3, -0.5e-3, 1.5e-3, -2.0e-3)
    led_powers: tuple[float, ...] = (1.00, 0.93, 1.06, 0.88, 0.97, 1.04, 0.91)
    led_exponents: tuple[float, ...] = (4.5, 5.0, 3.8, 5.5, 4.2, 4.8, 3.5)
    led_aim_offsets_m: tuple[tuple[float, float], ...] = (
        (3.0e-3, -2.0e-3), (-2.5e-3, 3.0e-3), (4.0e-3, 1.0e-3), (-3.0e-3, -3.5e-3),
        (1.5e-3, 4.0e-3), (-4.0e-3, 0.5e-3), (2.5e-3, -3.0e-3),
    )
    led_disc_radius_m: float = 1.5e-3
    full_well_e: float = 10000.0
    read_noise_e: float = 10.0
    ambient_fraction: float = 0.002
    exposure_gain: float = 1.3
    white_target_exposure_gain: float = 1.07
    texture_seed: int = 0

    def __post_init__(self) -> None:
        def fail(message: str) -> None:
            raise FingerpsDriverError(f"RigConfig: {message}")

        if self.width < 16 or self.height < 16:
            fail(f"image size {self.width}x{self.height} too small; use at least 16x16 pixels")
        if self.bit_depth not in (8, 12):
            fail(f"bit_depth {self.bit_depth} unsupported; use 8 or 12")
        if not isinstance(self.reflectance, Reflectance):
            fail(f"reflectance must be a Reflectance, got {self.reflectance!r}")
        positive = (
            "focal_px", "finger_radius_m", "finger_tip_elongation", "finger_length_radius_m",
            "ridge_period_m", "ridge_ellipticity", "sphere_radius_m", "white_target_distance_m",
            "led_disc_radius_m", "full_well_e", "exposure_gain", "white_target_exposure_gain",
        )
        non_negative = (
            "hk_scale", "ridge_height_m", "ridge_warp_m", "albedo_variation",
            "sphere_diffuse_albedo", "sphere_specular_reflectance", "psf_sigma_px",
            "white_target_texture", "read_noise_e", "ambient_fraction",
        )
        for name in positive:
            if not getattr(self, name) > 0.0:
                fail(f"{name} must be > 0, got {getattr(self, name)}")
        for name in non_negative:
            if not getattr(self, name) >= 0.0:
                fail(f"{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.albedo_mean <= 1.0 or not 0.0 < self.white_target_albedo <= 1.0:
            fail("albedo_mean and white_target_albedo must be in (0, 1]")
        if self.finger_identity is not None and (
            isinstance(self.finger_identity, bool)
            or not isinstance(self.finger_identity, (int, np.integer))
            or self.finger_identity < 0
        ):
            fail(
                f"finger_identity must be None (the spiral) or an integer >= 0, got "
                f"{self.finger_identity!r}"
            )
        if not abs(self.finger_roll_deg) <= 45.0:
            fail(f"finger_roll_deg {self.finger_roll_deg} outside [-45, 45]")
        if not abs(self.finger_yaw_deg) <= 90.0:
            fail(f"finger_yaw_deg {self.finger_yaw_deg} outside [-90, 90]")
        if not abs(self.finger_pitch_deg) <= 15.0:
            fail(f"finger_pitch_deg {self.finger_pitch_deg} outside [-15, 15]")
        if self.sphere_supersample < 1:
            fail(f"sphere_supersample must be >= 1, got {self.sphere_supersample}")
        if not 10.0 <= self.finger_max_slope_deg <= 80.0:
            fail(f"finger_max_slope_deg {self.finger_max_slope_deg} outside [10, 80]")
        ridge_slope = np.degrees(np.arctan(np.pi * self.ridge_height_m / self.ridge_period_m))
        if self.finger_max_slope_deg + ridge_slope > 85.0:
            fail(
                f"ridges ({ridge_slope:.1f} deg flanks) on a {self.finger_max_slope_deg} deg "
                "margin come within 5 deg of grazing; lower ridge_height_m or "
                "finger_max_slope_deg"
            )
        if self.finger_apex_optical_m[2] <= self.finger_radius_m:
            fail("the finger apex must be in front of the camera by more than finger_radius_m")
        if self.sphere_center_optical_m[2] <= self.sphere_radius_m:
            fail("the sphere must lie wholly in front of the camera: centre z > sphere_radius_m")
        if self.principal_point_px is not None and len(self.principal_point_px) != 2:
            fail("principal_point_px must be (cx, cy) or None")
        count = len(self.led_angles_deg)
        per_led = (
            "led_ring_radii_m", "led_heights_m", "led_powers", "led_exponents",
            "led_aim_offsets_m",
        )
        if count < 1:
            fail("led_angles_deg is empty; give one azimuth per LED")
        for name in per_led:
            if len(getattr(self, name)) != count:
                fail(f"{name} has {len(getattr(self, name))} entries, led_angles_deg {count}")
        if any(p <= 0.0 for p in self.led_powers) or any(m < 1.0 for m in self.led_exponents):
            fail("led_powers must be > 0 and led_exponents >= 1")
        if any(len(o) != 2 for o in self.led_aim_offsets_m):
            fail("led_aim_offsets_m entries must be (x, y) pairs")


@dataclass(frozen=True)
class FingerTruth:
    """Ground truth of the finger scene (unshifted), per pixel centre.

    Attributes
    ----------
    normals_ps : (H, W, 3) float32
        Unit surface normals, PS frame; zeros outside the mask.
    depth_m : (H, W) float32
        Z along the optical axis, metres; NaN outside the mask.
    mask : (H, W) bool
        Finger silhouette.
    albedo : (H, W) float32
        Albedo rho of the Lambertian term; zeros outside the mask.
    rolled_mm : (H, W, 2) float32 or None
        With a synthetic fingerprint (``RigConfig.finger_identity``): where the surface
        point seen by each pixel lies in the fingerprint's rolled plane, (x, y) mm, x right,
        y down, origin the pattern grid's top-left corner (as ``FingerprintPattern``'s
        minutiae and ``SimulatedRig.rolled_print``); NaN outside the mask. None for the
        spiral. The camera sees the print mirrored: rolled x falls as image x rises at
        roll 0 (a print is the skin's mirror image, ``fingertip``'s module docstring).
    """

    normals_ps: np.ndarray
    depth_m: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    rolled_mm: np.ndarray | None = None


def _led_ring(config: RigConfig) -> LedRing:
    angles = np.deg2rad(np.asarray(config.led_angles_deg, dtype=np.float64))
    radii = np.asarray(config.led_ring_radii_m, dtype=np.float64)
    positions = np.stack(
        [radii * np.cos(angles), radii * np.sin(angles), np.asarray(config.led_heights_m)],
        axis=-1,
    )
    apex = np.asarray(config.finger_apex_optical_m, dtype=np.float64)
    offsets = np.asarray(config.led_aim_offsets_m, dtype=np.float64)
    aims = apex + np.concatenate([offsets, np.zeros((len(offsets), 1))], axis=-1)
    return LedRing(
        positions_optical=positions,
        axes_optical=aims - positions,
        powers=np.asarray(config.led_powers),
        exponents=np.asarray(config.led_exponents),
        reference_distance_m=float(config.finger_apex_optical_m[2]),
        disc_radius_m=config.led_disc_radius_m,
    )


class SimulatedRig:
    """Renders the rig's scenes under any set of lit LEDs (see the module docstring).

    Construction is cheap; each (scene, LED) image is computed on first use (the finger's
    geometry once, then each LED's shading) or all at once by ``warm_up``; a frame from the
    cache costs only its noise. Thread-safe. With a ``finger_identity`` the first rig of
    that identity also generates its fingerprint (cached per identity for the process).

    Attributes
    ----------
    config : RigConfig
    led_count : int
    camera_matrix : (3, 3) float64
        Intrinsic matrix K.
    led_positions_optical : (K, 3) float64
        LED positions, metres, optical frame.
    camera : PinholeCamera
    leds : LedRing
        LED model (positions, axes, lobes, powers, field and disc radiance).
    fingertip : FingertipShape
    fingerprint : FingerprintPattern or None
        The synthetic fingerprint the finger carries (``RigConfig.finger_identity``): its
        ridges, minutiae and singular points in the rolled plane (mm); None for the spiral.
    sphere : MirrorSphere
    white_target : WhiteTarget
    sensor : SensorModel
    """

    def __init__(self, config: RigConfig | None = None) -> None:
        self.config = config if config is not None else RigConfig()
        c = self.config
        cx, cy = (
            c.principal_point_px
            if c.principal_point_px is not None
            else ((c.width - 1) / 2.0, (c.height - 1) / 2.0)
        )
        self.camera = PinholeCamera(c.width, c.height, c.focal_px, c.focal_px, cx, cy)
        self.camera_matrix = self.camera.matrix
        self.camera_matrix.setflags(write=False)
        self.leds = _led_ring(c)
        self.led_count = self.leds.count
        self.led_positions_optical = self.leds.positions_optical
        relief = None if c.finger_identity is None else relief_for_identity(c.finger_identity)
        self.fingerprint: FingerprintPattern | None = None if relief is None else relief.pattern
        self._relief = relief
        self.fingertip = FingertipShape(
            apex_optical_m=tuple(c.finger_apex_optical_m),
            radius_m=c.finger_radius_m,
            tip_elongation=c.finger_tip_elongation,
            max_slope_deg=c.finger_max_slope_deg,
            length_radius_m=c.finger_length_radius_m,
            ridge_height_m=c.ridge_height_m,
            ridge_period_m=c.ridge_period_m,
            core_offset_m=tuple(c.ridge_core_offset_m),
            ridge_ellipticity=c.ridge_ellipticity,
            warp_amplitude_m=c.ridge_warp_m,
            spiral=c.ridge_spiral,
            core_radius_m=0.7 * c.ridge_period_m,
            albedo_mean=c.albedo_mean,
            albedo_variation=c.albedo_variation,
            seed=c.texture_seed,
            roll_deg=float(c.finger_roll_deg),
            yaw_deg=float(c.finger_yaw_deg),
            pitch_deg=float(c.finger_pitch_deg),
            relief=relief,
        )
        self.sphere = MirrorSphere(
            center_optical_m=tuple(c.sphere_center_optical_m),
            radius_m=c.sphere_radius_m,
            diffuse_albedo=c.sphere_diffuse_albedo,
            specular_reflectance=c.sphere_specular_reflectance,
        )
        self.white_target = WhiteTarget(
            distance_m=c.white_target_distance_m,
            albedo=c.white_target_albedo,
            texture_amplitude=c.white_target_texture,
            seed=c.texture_seed + 2,
        )
        self.sensor = SensorModel(
            bit_depth=c.bit_depth,
            full_well_e=c.full_well_e,
            read_noise_e=c.read_noise_e,
            ambient_fraction=c.ambient_fraction,
        )
        self._lock = threading.Lock()
        self._surface: FingertipSurface | None = None
        self._target_albedo: np.ndarray | None = None
        self._cache: dict[tuple[Scene, int], np.ndarray] = {}
        self._zeros = np.zeros((c.height, c.width), dtype=np.float32)
        self._zeros.setflags(write=False)

    # ----------------------------------------------------------------- ground truth

    def max_value(self) -> int:
        """Largest digital value of a frame: 255 (8 bit) or 4095 (12 bit)."""
        return self.sensor.max_value

    def light_directions_ps(self) -> np.ndarray:
        """(K, 3) float64 unit "distant-light" directions, PS frame, apex -> LED k."""
        apex = np.asarray(self.config.finger_apex_optical_m, dtype=np.float64)
        return optical_to_ps(self.leds.directions_optical(apex, slice(None)))

    def light_intensities(self) -> np.ndarray:
        """(K,) float64 true relative LED intensities at the apex (lighting field E_k there).

        Times ``exposure_gain``: the finger's Lambertian term at the apex under LED k is
        ``light_intensities()[k] * rho * cos(incidence)`` in fractions of full scale.
        """
        apex = np.asarray(self.config.finger_apex_optical_m, dtype=np.float64)
        field = np.array([self.leds.irradiance(apex, k) for k in range(self.led_count)])
        return self.config.exposure_gain * field

    def finger_truth(self) -> FingerTruth:
        """Ground truth of the (unshifted) finger scene; fresh arrays on every call."""
        surface = self._finger_surface()
        mask = surface.mask.copy()
        depth = np.full(mask.shape, np.nan, dtype=np.float32)
        depth[mask] = surface.points_optical[mask][:, 2]
        rolled = None
        if self._relief is not None:
            rolled = np.full((*mask.shape, 2), np.nan, dtype=np.float32)
            rolled[mask] = self.rolled_position_mm(surface.points_optical[mask])
        return FingerTruth(
            normals_ps=surface.normals_ps.astype(np.float32),
            depth_m=depth,
            mask=mask,
            albedo=surface.albedo.astype(np.float32),
            rolled_mm=rolled,
        )

    def rolled_position_mm(self, points_optical: np.ndarray) -> np.ndarray:
        """Where points on the finger's surface lie in the fingerprint's rolled plane.

        Parameters
        ----------
        points_optical : (..., 3) float64
            Points on the finger's surface, metres, optical frame.

        Returns
        -------
        rolled_mm : (..., 2) float64
            (x, y) mm in the rolled plane (``FingerTruth.rolled_mm``).
        """
        if self._relief is None:
            raise FingerpsDriverError(
                "this rig's finger carries the analytic spiral, not a fingerprint; set "
                "RigConfig.finger_identity"
            )
        points = self.fingertip.to_finger_frame(np.asarray(points_optical, dtype=np.float64))
        xa, ya, _ = self.config.finger_apex_optical_m
        skin = self.fingertip.skin_coordinates(points[..., 0] - xa, points[..., 1] - ya)
        return np.stack(self._relief.rolled_mm(*skin), axis=-1)

    def rolled_print(self, *, ppi: float = 500.0) -> np.ndarray:
        """The fingerprint's ground-truth rolled print, uint8, ridges dark, 500 ppi.

        ``fingerprint_pattern.render_rolled_print``; pixel (i, j) covers rolled-plane mm
        [j, j + 1) x [i, i + 1) times 25.4 / ppi.
        """
        if self.fingerprint is None:
            raise FingerpsDriverError(
                "this rig's finger carries the analytic spiral, not a fingerprint; set "
                "RigConfig.finger_identity"
            )
        return render_rolled_print(self.fingerprint, ppi=ppi)

    def finger_points_optical(self) -> np.ndarray:
        """(H, W, 3) float64 surface point seen by each pixel centre; NaN outside the mask."""
        surface = self._finger_surface()
        points = surface.points_optical.copy()
        points[~surface.mask] = np.nan
        return points

    # ----------------------------------------------------------------- rendering

    def warm_up(self, scenes: Sequence[Scene] = (Scene.FINGER,)) -> None:
        """Fill the cache for every LED of ``scenes`` now instead of on first use."""
        for scene in scenes:
            for k in range(self.led_count):
                self._radiance(scene, k)

    def noiseless(
        self,
        scene: Scene,
        lit: Sequence[int],
        *,
        finger_shift_px: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:
        """Noiseless signal (H, W) float32, fraction of full scale, without ambient level.

        Same arguments as ``render``; values above 1 saturate in a frame.
        """
        indices = self._check(scene, lit)
        total = np.zeros((self.config.height, self.config.width), dtype=np.float32)
        for k in indices:
            total += self._radiance(scene, k)
        dx, dy = (float(s) for s in finger_shift_px)
        if dx != 0.0 or dy != 0.0:
            shift = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
            total = cv2.warpAffine(
                total,
                shift,
                (self.config.width, self.config.height),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0.0,
            )
        return total

    def render(
        self,
        scene: Scene,
        lit: Sequence[int],
        *,
        rng: np.random.Generator,
        finger_shift_px: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:
        """One camera frame.

        Parameters
        ----------
        scene : Scene
        lit : sequence of int
            Indices of the LEDs switched on (distinct, 0..K-1); empty for a dark frame.
        rng : numpy.random.Generator
            Source of the sensor noise.
        finger_shift_px : (float, float)
            Translation (du, dv) of the rendered image in pixels, for motion tests (linear
            interpolation, dark fill). Ground truth stays unshifted.

        Returns
        -------
        frame : (H, W) uint8 (8 bit) or uint16 holding 0..4095 (12 bit)
        """
        return self.sensor.expose(
            self.noiseless(scene, lit, finger_shift_px=finger_shift_px), rng=rng
        )

    def render_burst(self, scene: Scene, *, seed: int | Sequence[int] | None = None,
                     rng: np.random.Generator | None = None) -> np.ndarray:
        """A burst: one frame per LED, each LED lit alone, in LED order, (K, H, W).

        The noise of LED k comes from ``np.random.default_rng(seed + k)`` for an int
        ``seed``, ``np.random.default_rng([*seed, k])`` for a sequence, or from ``rng``
        drawn in LED order (give one of ``seed`` and ``rng``)."""
        if (seed is None) == (rng is None):
            raise ValueError("give one of seed and rng")
        if rng is not None:
            streams = [rng] * self.led_count
        elif isinstance(seed, int):
            streams = [np.random.default_rng(seed + k) for k in range(self.led_count)]
        else:
            streams = [np.random.default_rng([*seed, k]) for k in range(self.led_count)]
        return np.stack([self.render(scene, [k], rng=stream)
                         for k, stream in enumerate(streams)])

    # ----------------------------------------------------------------- internals

    def _check(self, scene: Scene, lit: Sequence[int]) -> list[int]:
        if not isinstance(scene, Scene):
            raise FingerpsDriverError(f"scene must be a Scene, got {scene!r}")
        indices = [int(k) for k in lit]
        if any(k < 0 or k >= self.led_count for k in indices):
            raise FingerpsDriverError(
                f"LED indices {indices} out of range; this rig has LEDs 0..{self.led_count - 1}"
            )
        if len(set(indices)) != len(indices):
            raise FingerpsDriverError(f"LED indices {indices} repeat; list each lit LED once")
        return indices

    def _finger_surface(self) -> FingertipSurface:
        with self._lock:
            if self._surface is None:
                self._surface = trace_fingertip(self.fingertip, self.camera.pixel_rays())
            return self._surface

    def _radiance(self, scene: Scene, k: int) -> np.ndarray:
        """Cached noiseless image (H, W) float32 (read-only) of ``scene`` under LED ``k``."""
        key = (scene, k)
        image = self._cache.get(key)
        if image is not None:
            return image
        surface = self._finger_surface() if scene is Scene.FINGER else None
        with self._lock:
            image = self._cache.get(key)
            if image is None:
                if scene is Scene.FINGER:
                    radiance = self._finger_radiance(surface, k)
                elif scene is Scene.SPHERE:
                    radiance = render_sphere(
                        self.sphere,
                        self.camera,
                        self.leds,
                        k,
                        diffuse_shading=lambertian_shading,
                        supersample=self.config.sphere_supersample,
                        psf_sigma_px=self.config.psf_sigma_px,
                    )
                elif scene is Scene.WHITE_TARGET:
                    if self._target_albedo is None:
                        self._target_albedo = self.white_target.albedo_map(
                            self.camera.height, self.camera.width
                        )
                    radiance = render_white_target(
                        self.white_target,
                        self.camera,
                        self.leds,
                        k,
                        shading=lambertian_shading,
                        albedo=self._target_albedo,
                    )
                else:
                    radiance = None
                if radiance is None:
                    image = self._zeros
                else:
                    gain = (
                        self.config.white_target_exposure_gain
                        if scene is Scene.WHITE_TARGET
                        else self.config.exposure_gain
                    )
                    image = (radiance * gain).astype(np.float32)
                    image.setflags(write=False)
                self._cache[key] = image
            return image

    def _finger_radiance(self, surface: FingertipSurface, k: int) -> np.ndarray:
        mask = surface.mask
        points = surface.points_optical[mask]
        normals = surface.normals_ps[mask]
        lights = optical_to_ps(self.leds.directions_optical(points, k))
        rho = surface.albedo[mask]
        if self.config.reflectance is Reflectance.HK:
            views = optical_to_ps(-points / np.linalg.norm(points, axis=-1, keepdims=True))
            shading = hk_reflectance(
                normals, lights, views, rho=rho, scale=self.config.hk_scale,
                params=self.config.hk_params,
            )
        else:
            shading = lambertian_shading(normals, lights, rho=rho)
        image = np.zeros(mask.shape)
        image[mask] = self.leds.irradiance(points, k) * shading
        return image
