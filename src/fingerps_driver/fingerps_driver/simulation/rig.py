"""The simulated rig: camera, seven near LEDs, and the scenes they light (finger, sphere, target).

``SimulatedRig.render`` is what a driver calls per frame: the noiseless image of each
(scene, LED) is computed once on first use and cached (float32, fraction of full scale); a
frame is then the sum of the lit LEDs' cached images, optionally translated, plus sensor noise
and quantisation (``sensor.SensorModel``). All reflectance comes from ``fingerps_recon``
(``hk_model.hk_reflectance`` and ``lambertian.lambertian_shading``, the skin's through
``skin_reflectance``).

Per pixel the light direction is from the surface point to the LED position (near light) and
the view direction from the point to the camera centre (perspective), as on real hardware.
``light_directions_ps`` gives the "distant-light" directions from the fingertip apex instead,
which is what a photometric-stereo solver assuming distant lights is compared against.

Units: a unit of radiance is what a Lambertian albedo-1 surface facing a power-1 LED on its
axis at the reference distance (the working distance) reflects (``led_field``);
``SensorModel.exposure_gain`` (``WhiteTarget.exposure_gain`` for the white target) maps
radiance to fraction of full scale.

The parts of the rig and their defaults are configured by ``rig_config.RigConfig``. The
finger carries the analytic spiral or, with ``FingertipShape.identity``, a synthetic
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
from fingerps_driver.simulation.fingerprint_pattern import (
    FingerprintPattern,
    render_rolled_print,
)
from fingerps_driver.simulation.fingertip import FingertipSurface, trace_fingertip
from fingerps_driver.simulation.mirror_sphere import render_sphere
from fingerps_driver.simulation.rig_config import RigConfig
from fingerps_driver.simulation.white_target import render_white_target
from fingerps_recon.photometric.frames import optical_to_ps
from fingerps_recon.photometric.lambertian import lambertian_shading


class Scene(Enum):
    """What is in front of the camera."""

    FINGER = "finger"
    SPHERE = "sphere"
    WHITE_TARGET = "white_target"
    EMPTY = "empty"


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
        With a synthetic fingerprint (``FingertipShape.identity``): where the surface
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


class SimulatedRig:
    """Renders the rig's scenes under any set of lit LEDs (see the module docstring).

    Construction is cheap; each (scene, LED) image is computed on first use (the finger's
    geometry once, then each LED's shading) or all at once by ``warm_up``; a frame from the
    cache costs only its noise. Thread-safe. With a finger ``identity`` the first rig of
    that identity also generates its fingerprint (cached per identity for the process).
    ``camera``, ``fingertip``, ``sphere``, ``white_target`` and ``sensor`` are the parts of
    ``config`` (``config.finger`` the fingertip).

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
        The synthetic fingerprint the finger carries (``FingertipShape.identity``): its
        ridges, minutiae and singular points in the rolled plane (mm); None for the spiral.
    sphere : MirrorSphere
    white_target : WhiteTarget
    sensor : SensorModel
    """

    def __init__(self, config: RigConfig | None = None) -> None:
        self.config = config if config is not None else RigConfig()
        c = self.config
        self.camera = c.camera
        self.camera_matrix = self.camera.matrix
        self.camera_matrix.setflags(write=False)
        self.leds = c.leds.ring(c.finger.apex_optical_m)
        self.led_count = self.leds.count
        self.led_positions_optical = self.leds.positions_optical
        self.fingertip = c.finger
        relief = self.fingertip.relief  # the fingerprint, generated now rather than mid-burst
        self.fingerprint: FingerprintPattern | None = None if relief is None else relief.pattern
        self.sphere = c.sphere
        self.white_target = c.white_target
        self.sensor = c.sensor
        self._lock = threading.Lock()
        self._surface: FingertipSurface | None = None
        self._target_albedo: np.ndarray | None = None
        self._cache: dict[tuple[Scene, int], np.ndarray] = {}
        self._zeros = np.zeros((self.camera.height, self.camera.width), dtype=np.float32)
        self._zeros.setflags(write=False)

    # ----------------------------------------------------------------- ground truth

    def max_value(self) -> int:
        """Largest digital value of a frame: 255 (8 bit) or 4095 (12 bit)."""
        return self.sensor.max_value

    def light_directions_ps(self) -> np.ndarray:
        """(K, 3) float64 unit "distant-light" directions, PS frame, apex -> LED k."""
        apex = np.asarray(self.fingertip.apex_optical_m, dtype=np.float64)
        return optical_to_ps(self.leds.directions_optical(apex, slice(None)))

    def light_intensities(self) -> np.ndarray:
        """(K,) float64 true relative LED intensities at the apex (lighting field E_k there).

        Times ``sensor.exposure_gain``: the finger's Lambertian term at the apex under LED k is
        ``light_intensities()[k] * rho * cos(incidence)`` in fractions of full scale.
        """
        apex = np.asarray(self.fingertip.apex_optical_m, dtype=np.float64)
        field = np.array([self.leds.irradiance(apex, k) for k in range(self.led_count)])
        return self.sensor.exposure_gain * field

    def finger_truth(self) -> FingerTruth:
        """Ground truth of the (unshifted) finger scene; fresh arrays on every call."""
        surface = self._finger_surface()
        mask = surface.mask.copy()
        depth = np.full(mask.shape, np.nan, dtype=np.float32)
        depth[mask] = surface.points_optical[mask][:, 2]
        rolled = None
        if self.fingertip.relief is not None:
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
        relief = self.fingertip.relief
        if relief is None:
            raise FingerpsDriverError(
                "this rig's finger carries the analytic spiral, not a fingerprint; set "
                "RigConfig.finger.identity"
            )
        points = self.fingertip.to_finger_frame(np.asarray(points_optical, dtype=np.float64))
        xa, ya, _ = self.fingertip.apex_optical_m
        skin = self.fingertip.skin_coordinates(points[..., 0] - xa, points[..., 1] - ya)
        return np.stack(relief.rolled_mm(*skin), axis=-1)

    def rolled_print(self, *, ppi: float = 500.0) -> np.ndarray:
        """The fingerprint's ground-truth rolled print, uint8, ridges dark, 500 ppi.

        ``fingerprint_pattern.render_rolled_print``; pixel (i, j) covers rolled-plane mm
        [j, j + 1) x [i, i + 1) times 25.4 / ppi.
        """
        if self.fingerprint is None:
            raise FingerpsDriverError(
                "this rig's finger carries the analytic spiral, not a fingerprint; set "
                "RigConfig.finger.identity"
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
        total = np.zeros((self.camera.height, self.camera.width), dtype=np.float32)
        for k in indices:
            total += self._radiance(scene, k)
        dx, dy = (float(s) for s in finger_shift_px)
        if dx != 0.0 or dy != 0.0:
            shift = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]])
            total = cv2.warpAffine(
                total,
                shift,
                (self.camera.width, self.camera.height),
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
                        self.white_target.exposure_gain
                        if scene is Scene.WHITE_TARGET
                        else self.sensor.exposure_gain
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
        shading = self.config.skin.shading(normals, lights, points, rho=surface.albedo[mask])
        image = np.zeros(mask.shape)
        image[mask] = self.leds.irradiance(points, k) * shading
        return image
