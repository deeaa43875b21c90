"""Configuration of the simulated rig: its components' configurations and their checks.

Frames and units as in CONVENTIONS.md: positions in metres in the camera optical frame
(x right, y down, z forward, camera centre at the origin). Each component's defaults are
written in its own dataclass, so ``RigConfig()`` is the standard rig; change one part with
e.g. ``RigConfig(finger=FingertipShape(identity=3, roll_deg=10.0))`` or
``dataclasses.replace(config, sphere=replace(config.sphere, center_optical_m=c))``.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, field

import numpy as np

from fingerps_driver.errors import FingerpsDriverError
from fingerps_driver.simulation.camera import PinholeCamera
from fingerps_driver.simulation.fingertip import FingertipShape
from fingerps_driver.simulation.led_field import LedLayout
from fingerps_driver.simulation.mirror_sphere import MirrorSphere
from fingerps_driver.simulation.sensor import SensorModel
from fingerps_driver.simulation.skin_reflectance import Reflectance, SkinReflectance
from fingerps_driver.simulation.white_target import WhiteTarget

MIN_IMAGE_SIZE_PX = 16
BIT_DEPTHS = (8, 12)
MAX_ROLL_DEG = 45.0
"""Roll beyond which the skin seen leaves the rolled print."""
MAX_YAW_DEG = 90.0
MAX_PITCH_DEG = 15.0
"""Pitch beyond which the tip's or the shaft's margin comes within a few degrees of grazing."""
MARGIN_SLOPE_RANGE_DEG = (10.0, 80.0)
"""Range of the finger's slope at its silhouette (``FingertipShape.max_slope_deg``)."""
STEEPEST_FLANK_DEG = 85.0
"""Steepest a ridge flank on the margin may be: 5 degrees from grazing."""

_POSITIVE = (
    "camera.fx", "camera.fy", "finger.radius_m", "finger.tip_elongation",
    "finger.length_radius_m", "finger.ridge_period_m", "finger.ridge_ellipticity",
    "sphere.radius_m", "white_target.distance_m", "leds.disc_radius_m", "sensor.full_well_e",
    "sensor.exposure_gain", "white_target.exposure_gain",
)
_NON_NEGATIVE = (
    "skin.hk_scale", "finger.ridge_height_m", "finger.warp_amplitude_m",
    "finger.albedo_variation", "sphere.diffuse_albedo", "sphere.specular_reflectance",
    "sphere.psf_sigma_px", "white_target.texture_amplitude", "sensor.read_noise_e",
    "sensor.ambient_fraction",
)
_PER_LED = ("ring_radii_m", "heights_m", "powers", "exponents", "aim_offsets_m")


@dataclass(frozen=True)
class RigConfig:
    """The simulated rig's parts, each its own configuration; the defaults are the standard
    rig. ``camera``: image size and intrinsics; ``sensor``: bit depth, noise and the exposure
    of the finger and the sphere; ``leds``: the LEDs, aimed about the finger's apex;
    ``skin``: the finger skin's reflectance; ``finger``: its shape, ridges or fingerprint,
    albedo and pose; ``sphere``: the calibration sphere and how it is imaged;
    ``white_target``: the flat-field target and its exposure.
    """

    camera: PinholeCamera = field(default_factory=PinholeCamera)
    sensor: SensorModel = field(default_factory=SensorModel)
    leds: LedLayout = field(default_factory=LedLayout)
    skin: SkinReflectance = field(default_factory=SkinReflectance)
    finger: FingertipShape = field(default_factory=FingertipShape)
    sphere: MirrorSphere = field(default_factory=MirrorSphere)
    white_target: WhiteTarget = field(default_factory=WhiteTarget)

    def __post_init__(self) -> None:
        problem = (
            _range_problem(self) or _camera_problem(self.camera, self.sensor)
            or _finger_problem(self.finger) or _scene_problem(self)
            or _led_problem(self.leds)
        )
        if problem is not None:
            raise FingerpsDriverError(f"RigConfig: {problem}")


def _range_problem(config: RigConfig) -> str | None:
    """Why a value that must be > 0 or >= 0 is not, or None."""
    for name in _POSITIVE:
        value = operator.attrgetter(name)(config)
        if not value > 0.0:
            return f"{name} must be > 0, got {value}"
    for name in _NON_NEGATIVE:
        value = operator.attrgetter(name)(config)
        if not value >= 0.0:
            return f"{name} must be >= 0, got {value}"
    if not 0.0 < config.finger.albedo_mean <= 1.0 or not 0.0 < config.white_target.albedo <= 1.0:
        return "finger.albedo_mean and white_target.albedo must be in (0, 1]"
    if not isinstance(config.skin.model, Reflectance):
        return f"skin.model must be a Reflectance, got {config.skin.model!r}"
    return None


def _camera_problem(camera: PinholeCamera, sensor: SensorModel) -> str | None:
    """Why the camera or the sensor cannot be rendered, or None."""
    if camera.width < MIN_IMAGE_SIZE_PX or camera.height < MIN_IMAGE_SIZE_PX:
        return (f"image size {camera.width}x{camera.height} too small; use at least "
                f"{MIN_IMAGE_SIZE_PX}x{MIN_IMAGE_SIZE_PX} pixels")
    if sensor.bit_depth not in BIT_DEPTHS:
        return f"bit_depth {sensor.bit_depth} unsupported; use 8 or 12"
    if camera.principal_point_px is not None and len(camera.principal_point_px) != 2:
        return "camera.principal_point_px must be (cx, cy) or None"
    return None


def _finger_problem(finger: FingertipShape) -> str | None:
    """Why the finger's identity, pose or shape is refused, or None."""
    identity = finger.identity
    if identity is not None and (
        isinstance(identity, bool) or not isinstance(identity, (int, np.integer))
        or identity < 0
    ):
        return (f"finger.identity must be None (the spiral) or an integer >= 0, got "
                f"{identity!r}")
    for name, limit in (("roll_deg", MAX_ROLL_DEG), ("yaw_deg", MAX_YAW_DEG),
                        ("pitch_deg", MAX_PITCH_DEG)):
        value = getattr(finger, name)
        if not abs(value) <= limit:
            return f"finger.{name} {value} outside [-{limit:g}, {limit:g}]"
    low, high = MARGIN_SLOPE_RANGE_DEG
    if not low <= finger.max_slope_deg <= high:
        return f"finger.max_slope_deg {finger.max_slope_deg} outside [{low:g}, {high:g}]"
    ridge_slope = np.degrees(np.arctan(np.pi * finger.ridge_height_m / finger.ridge_period_m))
    if finger.max_slope_deg + ridge_slope > STEEPEST_FLANK_DEG:
        return (f"ridges ({ridge_slope:.1f} deg flanks) on a {finger.max_slope_deg} deg "
                f"margin come within {90.0 - STEEPEST_FLANK_DEG:g} deg of grazing; lower "
                "finger.ridge_height_m or finger.max_slope_deg")
    return None


def _scene_problem(config: RigConfig) -> str | None:
    """Why the finger or the sphere is not in front of the camera, or None."""
    if config.finger.apex_optical_m[2] <= config.finger.radius_m:
        return "the finger apex must be in front of the camera by more than finger.radius_m"
    if config.sphere.center_optical_m[2] <= config.sphere.radius_m:
        return "the sphere must lie wholly in front of the camera: centre z > sphere.radius_m"
    if config.sphere.supersample < 1:
        return f"sphere.supersample must be >= 1, got {config.sphere.supersample}"
    return None


def _led_problem(leds: LedLayout) -> str | None:
    """Why the LEDs do not fit together, or None."""
    count = len(leds.angles_deg)
    if count < 1:
        return "leds.angles_deg is empty; give one azimuth per LED"
    for name in _PER_LED:
        if len(getattr(leds, name)) != count:
            return f"leds.{name} has {len(getattr(leds, name))} entries, leds.angles_deg {count}"
    if any(p <= 0.0 for p in leds.powers) or any(m < 1.0 for m in leds.exponents):
        return "leds.powers must be > 0 and leds.exponents >= 1"
    if any(len(o) != 2 for o in leds.aim_offsets_m):
        return "leds.aim_offsets_m entries must be (x, y) pairs"
    return None
