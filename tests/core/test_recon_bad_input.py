"""Bad Burst, LightCalibration and FlatField messages through recon_node's core functions
(``burst_reconstruction.reconstruct_burst``, ``CalibrationInForce``,
``burst_intake.check_burst_size``, ``check_light_calibration``, ``flat_field_maps``), without
a ROS graph; and the node's worker, in this process, going on after an error nobody expected.

Every bad message must end in a ``FingerpsError`` (``FingerpsReconError``, ``MessageError``)
that says what is wrong - never in
another exception (which killed recon_node's worker thread), never in an "empty" result
counted as a reconstruction - and a good burst must still reconstruct afterwards with the
same ``CalibrationInForce`` (and its prepared calibrations).
"""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Point, Vector3
from polling import poll_until
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from fingerps_driver.simulation import SimulatedRig
from fingerps_msgs.msg import Burst, FlatField, LightCalibration, TaggedFrame
from fingerps_recon import recon_node
from fingerps_recon.errors import EmptyReconstructionError, IncompleteBurstError
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_recon.photometric.pipeline import Model, ReconstructionOptions
from fingerps_recon.reconstruction import worker
from fingerps_recon.reconstruction.burst_intake import (
    BurstLimits,
    check_burst_size,
    check_light_calibration,
    flat_field_maps,
)
from fingerps_recon.reconstruction.burst_reconstruction import reconstruct_burst
from fingerps_recon.reconstruction.calibration_in_force import CalibrationInForce
from fingerps_recon.reconstruction.problem_log import LogGate, one_line
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image, images_to_array

OPTIONS = ReconstructionOptions(model=Model.LAMBERT)
NAN = math.nan


def calibration(rig: SimulatedRig, *, directions_ps: np.ndarray | None = None,
                intensities: list[float] | None = None,
                leds: np.ndarray | None = None) -> LightCalibration:
    """The rig's true distant lights (optical frame in the message), optionally changed."""
    dirs = ps_to_optical(rig.light_directions_ps() if directions_ps is None else directions_ps)
    power = rig.light_intensities()
    msg = LightCalibration(
        camera_name="test",
        directions=[Vector3(x=float(x), y=float(y), z=float(z)) for x, y, z in dirs],
        relative_intensities=(list(power / power.max()) if intensities is None
                              else intensities))
    if leds is not None:
        msg.led_positions = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in leds]
    return msg


def burst(rig: SimulatedRig, images: np.ndarray, *, leds: list[int] | None = None,
          encoding: str = "mono8", dark: Image | None = None,
          k: np.ndarray | None = None) -> Burst:
    header = Header(stamp=Time(sec=1000), frame_id="cam")
    count = len(images)
    frames = [TaggedFrame(header=header, burst_id=1, led_index=i, led_count=count,
                          image=array_to_image(images[i % count], encoding=encoding,
                                               header=header))
              for i in (range(count) if leds is None else leds)]
    matrix = rig.camera_matrix if k is None else k
    msg = Burst(header=header, burst_id=1, frames=frames, camera_info=CameraInfo(
        header=header, width=int(images.shape[2]), height=int(images.shape[1]),
        k=[float(x) for x in np.asarray(matrix).reshape(-1)]))
    if dark is not None:
        msg.has_dark_frame = True
        msg.dark_frame = TaggedFrame(header=header, burst_id=1, led_index=0, image=dark)
    return msg


def in_force(lights: LightCalibration, flat: np.ndarray | None = None,
             shared: CalibrationInForce | None = None) -> CalibrationInForce:
    """``shared`` (or a new one) with these lights and flat-field maps in force as they are,
    unchecked (as if they had got past the checks on arrival)."""
    held = shared or CalibrationInForce()
    held.lights, held.flat_maps = lights, flat
    return held


def reconstructs(rig: SimulatedRig, images: np.ndarray, shared: CalibrationInForce,
                 flat: np.ndarray | None = None) -> None:
    """A good burst still reconstructs, with the calibration in force that saw the bad ones."""
    made = reconstruct_burst(burst(rig, images), in_force(calibration(rig), flat, shared),
                             options=OPTIONS)
    assert made.result.mask.sum() > 100_000 and len(made.result.points_optical) > 100_000


def refused(msg: Burst, lights: LightCalibration, *, match: str,
            flat: np.ndarray | None = None, shared: CalibrationInForce | None = None,
            limits: BurstLimits | None = None, error: type = FingerpsError) -> str:
    with pytest.raises(error, match=match) as info:
        reconstruct_burst(msg, in_force(lights, flat, shared), options=OPTIONS, limits=limits)
    return str(info.value)


# ------------------------------------------------------------------ malformed bursts
@pytest.mark.parametrize("shape", [(0, 0), (0, 16), (16, 0)])
def test_empty_images_are_refused(rig: SimulatedRig, finger_images: np.ndarray,
                                  shape: tuple[int, int]) -> None:
    shared = CalibrationInForce()
    empty = np.zeros((rig.led_count, *shape), dtype=np.uint8)
    msg = burst(rig, empty)
    with pytest.raises(FingerpsError, match="empty"):
        check_burst_size(msg, BurstLimits())
    refused(msg, calibration(rig), match="empty", shared=shared)
    reconstructs(rig, finger_images, shared)


def test_images_beyond_the_bounds_are_refused_before_they_are_read(
        rig: SimulatedRig, finger_images: np.ndarray) -> None:
    small = BurstLimits(max_width=600, max_height=4096, max_frames=16)
    msg = burst(rig, finger_images)  # 659 px wide
    refused(msg, calibration(rig), match="beyond max_image_width", limits=small)
    # A header claiming 100000 x 100000 px over a few bytes: refused at once, by the bounds
    # and, without them, by the conversion before it allocates the stack (70 GB).
    huge = Image(height=100_000, width=100_000, encoding="mono8", step=100_000,
                 data=bytes(64))
    msg = burst(rig, finger_images)
    for frame in msg.frames:
        frame.image = huge
    tracemalloc.start()  # numpy reports its buffers to tracemalloc
    try:
        with pytest.raises(FingerpsError, match="beyond max_image_width"):
            check_burst_size(msg, BurstLimits())
        with pytest.raises(FingerpsError, match="too few"):
            images_to_array([huge] * rig.led_count)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak  # nothing of the claimed size was allocated, nor read


def test_too_many_frames_are_refused(rig: SimulatedRig, finger_images: np.ndarray) -> None:
    msg = burst(rig, finger_images, leds=list(range(17)))
    with pytest.raises(FingerpsError, match="max_burst_frames 16"):
        check_burst_size(msg, BurstLimits())
    refused(msg, calibration(rig), match="max_burst_frames")


def test_dark_and_repeat_frames_are_bounded_too(rig: SimulatedRig,
                                                finger_images: np.ndarray) -> None:
    msg = burst(rig, finger_images, dark=Image(height=0, width=0, encoding="mono8"))
    with pytest.raises(FingerpsError, match="empty"):
        check_burst_size(msg, BurstLimits())
    msg = burst(rig, finger_images)
    msg.has_repeat_frame = True
    msg.repeat_frame.image = Image(height=5000, width=10, encoding="mono8", step=10)
    with pytest.raises(FingerpsError, match="beyond"):
        check_burst_size(msg, BurstLimits())


@pytest.mark.parametrize("fault", ["short data", "step below a row", "step beyond the data"])
def test_step_and_data_that_disagree_are_refused(rig: SimulatedRig, finger_images: np.ndarray,
                                                 fault: str) -> None:
    msg = burst(rig, finger_images)
    image = msg.frames[3].image
    if fault == "short data":
        image.data = bytes(image.data)[:-1]
    elif fault == "step below a row":
        image.step = image.width - 1
    else:
        image.step = image.width + 1
    shared = CalibrationInForce()
    refused(msg, calibration(rig), match="too few", shared=shared)
    reconstructs(rig, finger_images, shared)


@pytest.mark.parametrize("leds", [[0, 1, 2, 3, 4, 5, 5], [0, 1, 2, 3, 4, 5, 99],
                                  [0, 1, 2, 3, 4, 5, 6, 6], [0, 1, 2, 3, 4, 5]])
def test_wrong_or_duplicate_led_indices_are_refused(rig: SimulatedRig, finger_images: np.ndarray,
                                                    leds: list[int]) -> None:
    refused(burst(rig, finger_images, leds=leds), calibration(rig), match="LEDs",
            error=IncompleteBurstError)


def test_float_images_with_nan_are_refused(rig: SimulatedRig, finger_images: np.ndarray) -> None:
    floats = finger_images.astype(np.float32)
    floats[:, 10, 10] = NAN
    floats[:, 11, 11] = math.inf
    refused(burst(rig, floats, encoding="32FC1"), calibration(rig), match="one grey level")


def test_a_dark_frame_of_another_encoding_or_with_nan_is_refused(
        rig: SimulatedRig, finger_images: np.ndarray) -> None:
    dark = np.zeros(finger_images.shape[1:], dtype=np.float32)
    dark[100:200, 100:200] = NAN
    nan_dark = array_to_image(dark, encoding="32FC1")
    shared = CalibrationInForce()
    refused(burst(rig, finger_images, dark=nan_dark), calibration(rig), match="dark frame",
            shared=shared)
    small = array_to_image(np.zeros((10, 10), np.uint8), encoding="mono8")
    refused(burst(rig, finger_images, dark=small), calibration(rig), match="dark frame",
            shared=shared)
    reconstructs(rig, finger_images, shared)


@pytest.mark.parametrize("k", [np.full((3, 3), NAN), np.diag([math.inf, 1.0, 1.0]),
                               np.diag([600.0, -600.0, 1.0])])
def test_a_camera_matrix_that_is_not_finite_and_positive_is_refused(
        rig: SimulatedRig, finger_images: np.ndarray, k: np.ndarray) -> None:
    text = refused(burst(rig, finger_images, k=k), calibration(rig),
                   match="intrinsics|camera matrix")
    assert "\n" not in text


def test_an_empty_reconstruction_is_not_a_result(rig: SimulatedRig) -> None:
    # Every pixel lit by only two LEDs (the others in shadow): a finger is found, but no
    # pixel has the three usable values a normal needs.
    count, h, w = rig.led_count, 60, 70
    stack = np.zeros((count, h, w), dtype=np.uint8)
    bands = np.array_split(np.arange(w), count)
    for k in range(count):
        stack[k][:, bands[k]] = 200
        stack[k][:, bands[(k + 1) % count]] = 120
    text = refused(burst(rig, stack, k=rig.camera_matrix), calibration(rig),
                   match="nothing reconstructed", error=EmptyReconstructionError)
    assert "0 pixels with a valid normal" in text


# ------------------------------------------------------------------ degenerate calibrations
def _rotated(directions: np.ndarray) -> np.ndarray:
    return directions[[1, 2, 3, 4, 5, 6, 0]]


def _degenerate(rig: SimulatedRig) -> dict[str, LightCalibration]:
    lights = rig.light_directions_ps()
    zero = lights.copy()
    zero[2] = 0.0
    flat_plane = lights.copy()
    flat_plane[:, 2] = 0.0
    flat_plane /= np.linalg.norm(flat_plane, axis=1, keepdims=True)
    leds = rig.led_positions_optical
    return {
        "a zero direction": calibration(rig, directions_ps=zero),
        "parallel directions": calibration(rig, directions_ps=np.repeat(lights[:1], 7, 0)),
        "coplanar directions": calibration(rig, directions_ps=flat_plane),
        "non-unit directions": calibration(rig, directions_ps=lights * 2.0),
        "NaN directions": calibration(rig, directions_ps=np.where(zero == 0, NAN, lights)),
        "NaN intensities": calibration(rig, intensities=[NAN] * 7),
        "NaN intensities with LED positions": calibration(rig, intensities=[NAN] * 7,
                                                          leds=leds),
        "zero intensities": calibration(rig, intensities=[0.0] * 7),
        "too few intensities": calibration(rig, intensities=[1.0] * 3),
        "NaN LED positions": calibration(rig, leds=np.where(leds > 0.03, NAN, leds)),
        "too few LED positions": calibration(rig, leds=leds[:4]),
        "too few LEDs": calibration(rig, directions_ps=lights[:2], intensities=[1.0, 1.0]),
    }


@pytest.mark.parametrize("case", list(_degenerate(SimulatedRig())))
def test_degenerate_light_calibrations_are_refused(rig: SimulatedRig, finger_images: np.ndarray,
                                                   case: str) -> None:
    lights = _degenerate(rig)[case]
    with pytest.raises(FingerpsError):
        check_light_calibration(lights)
    shared = CalibrationInForce()
    with pytest.raises(FingerpsError):
        reconstruct_burst(burst(rig, finger_images), in_force(lights, None, shared),
                          options=OPTIONS)
    reconstructs(rig, finger_images, shared)


def test_leds_that_cannot_light_the_finger_are_refused_where_used(
        rig: SimulatedRig, finger_images: np.ndarray) -> None:
    leds = rig.led_positions_optical
    for bad, match in ((np.repeat(leds[:1], 7, axis=0), "parallel or coplanar"),
                       (leds + np.array([0.0, 0.0, 0.2]), "beyond the working distance")):
        lights = calibration(rig, leds=bad)
        check_light_calibration(lights)  # finite: only the camera and distance tell
        refused(burst(rig, finger_images), lights, match=match)


def test_the_good_calibrations_pass(rig: SimulatedRig, finger_images: np.ndarray) -> None:
    check_light_calibration(calibration(rig))
    check_light_calibration(calibration(rig, leds=rig.led_positions_optical))
    reconstructs(rig, finger_images, CalibrationInForce())


# ------------------------------------------------------------------ flat fields
def _flat(maps: np.ndarray) -> FlatField:
    return FlatField(camera_name="test",
                     maps=[array_to_image(m, encoding="32FC1") for m in maps],
                     relative_intensities=[1.0] * len(maps))


@pytest.mark.parametrize("case", ["NaN", "inf", "negative", "all zero", "mixed sizes",
                                  "rgb", "none", "too many"])
def test_bad_flat_fields_are_refused_on_arrival(rig: SimulatedRig, case: str) -> None:
    maps = np.ones((7, 20, 30), dtype=np.float32)
    if case == "NaN":
        maps[3, 5, 5] = NAN
    elif case == "inf":
        maps[0, 0, 0] = math.inf
    elif case == "negative":
        maps[1] = -0.5
    elif case == "all zero":
        maps[6] = 0.0
    msg = _flat(maps)
    if case == "mixed sizes":
        msg.maps[2] = array_to_image(np.ones((20, 31), np.float32), encoding="32FC1")
    elif case == "rgb":
        msg.maps = [array_to_image(np.ones((20, 30, 3), np.uint8), encoding="rgb8")] * 7
    elif case == "none":
        msg.maps = []
    elif case == "too many":
        msg.maps = msg.maps * 3
    with pytest.raises(FingerpsError):
        flat_field_maps(msg, BurstLimits())


def test_a_good_flat_field_is_taken(rig: SimulatedRig) -> None:
    maps = flat_field_maps(_flat(np.full((7, 20, 30), 0.5, np.float32)), BurstLimits())
    assert maps.shape == (7, 20, 30) and maps.dtype == np.float32


def test_nan_flat_maps_are_refused_where_used_too(rig: SimulatedRig,
                                                  finger_images: np.ndarray) -> None:
    # Maps put in force without flat_field_maps (unchecked on arrival): refused by the
    # preparation, with the near lights (which do not divide by them) as with distant ones.
    maps = np.ones(finger_images.shape, dtype=np.float32)
    maps[:, 200:300, 300:400] = NAN
    shared = CalibrationInForce()
    for lights in (calibration(rig), calibration(rig, leds=rig.led_positions_optical)):
        refused(burst(rig, finger_images), lights, flat=maps, match="non-finite|NaN",
                shared=shared)
    reconstructs(rig, finger_images, shared, flat=np.ones(finger_images.shape, np.float32))


# ------------------------------------------------------------------ what the node logs
def test_an_unexpected_error_is_told_in_one_line_with_its_place() -> None:
    try:
        np.zeros((0, 3)).max(axis=0)
    except ValueError as exc:
        line = one_line(exc)
    assert "\n" not in line and line.startswith("ValueError: zero-size array")
    assert "(at " in line and ".py:" in line


def test_the_log_gate_lets_each_problem_through_once_per_period() -> None:
    gate = LogGate(period_s=60.0, keep=4)
    assert gate.opens("a") and gate.opens("b")
    assert not gate.opens("a") and not gate.opens("b")
    for name in "cdefgh":  # more problems than it keeps: still one line each
        assert gate.opens(name)


# ------------------------------------------------------------------ the node's worker
def test_the_worker_survives_an_unexpected_error(
        rig: SimulatedRig, finger_images: np.ndarray, ros_node: Node,
        monkeypatch: pytest.MonkeyPatch) -> None:
    real = worker.reconstruct_burst

    def flaky(burst: Burst, *args, **kwargs):
        if burst.burst_id == 1:
            raise ValueError("zero-size array to reduction operation maximum")
        return real(burst, *args, **kwargs)

    monkeypatch.setattr(worker, "reconstruct_burst", flaky)  # as the worker calls it
    node = None
    try:
        node = recon_node.ReconNode(context=ros_node.context)
        node._recon.on_lights(calibration(rig))
        for burst_id in (1, 2):
            good = burst(rig, finger_images)
            good.burst_id = burst_id
            node._recon.on_burst(good)
        poll_until(lambda: node._recon.done + node._recon.failed >= 2, 60.0)
        assert (node._recon.failed, node._recon.unexpected, node._recon.done) == (1, 1, 1)
        assert node._worker.is_alive()
        level, message = node._recon.health()
        assert level == DiagnosticStatus.WARN and "failed" in message
        assert node._recon.last_error == ""  # the good burst after it
        assert "unexpected ValueError: zero-size array" in node._recon.last_problem
    finally:
        if node is not None:
            node.destroy_node()

