"""recon_node's worker without a node or a graph (``reconstruction.worker``): the
calibrations in force, the queue and its drops, each burst's outcome counted and judged
(``health``), the fingerprint's bookkeeping, the guarded callbacks, the calibration
prepared ahead, and the ``/diagnostics`` status built from it all
(``reconstruction.diagnostics``).

The reconstruction itself is replaced by a stand-in where only the bookkeeping is tested
(tests/core/test_recon_bad_input.py reconstructs real bursts).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import Vector3
from polling import poll_until
from sensor_msgs.msg import CameraInfo, Image

from fingerps_driver.simulation import SimulatedRig
from fingerps_msgs.msg import Burst, FlatField, LightCalibration, TaggedFrame
from fingerps_recon.errors import IncompleteBurstError, NoFingerError, RolledPrintError
from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_recon.photometric.pipeline import Model, ReconstructionOptions
from fingerps_recon.reconstruction import worker as worker_module
from fingerps_recon.reconstruction.burst_intake import BurstLimits
from fingerps_recon.reconstruction.diagnostics import reconstruction_status
from fingerps_recon.reconstruction.outputs import Output
from fingerps_recon.reconstruction.worker import (
    ReconSettings,
    ReconstructionWorker,
    StageTimes,
)
from fingerps_recon.surface.rolled_print import PrintRejection
from fingerps_ros import topics
from fingerps_ros.image_conversion import array_to_image

# Nobody watches the outputs (the stand-in reconstructions have none); the print is made.
SETTINGS = ReconSettings(ReconstructionOptions(model=Model.LAMBERT), BurstLimits(), 4095.0,
                         wanted=(), fingerprint=True)
DIAGNOSTIC_KEYS = [
    "ready", "threads", "cores", "bursts_done", "bursts_failed", "bursts_incomplete",
    "bursts_rejected", "unexpected_errors", "calibrations_refused",
    "bursts_without_flat_field", "last_error", "last_problem", "fingerprints_made",
    "fingerprints_rejected", "last_fingerprint_problem", "fingerprint_ms_median",
    "bursts_dropped", "compressed_failures", "calibrated", "calibrations_prepared"]


class RecordingLogger:
    """The worker's logger: (severity, message, keyword arguments) of every line."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict[str, Any]]] = []

    def info(self, message: str, **kwargs: Any) -> None:
        self.lines.append(("info", message, kwargs))

    def warning(self, message: str, **kwargs: Any) -> None:
        self.lines.append(("warning", message, kwargs))

    def error(self, message: str, **kwargs: Any) -> None:
        self.lines.append(("error", message, kwargs))

    def said(self, severity: str, text: str) -> list[str]:
        return [m for s, m, _ in self.lines if s == severity and text in m]


class Published:
    """The worker's ``publish``: records the outputs of each call."""

    def __init__(self) -> None:
        self.calls: list[list[Output]] = []

    def __call__(self, outputs: Iterable[Output]) -> None:
        self.calls.append(list(outputs))

    def burst_ids(self) -> list[int]:
        """The bursts of the prints published, in order (``a_burst`` stamps them)."""
        return [o.message.header.stamp.nanosec for call in self.calls for o in call]


def make_worker(*, settings: ReconSettings = SETTINGS, queue_depth: int = 2,
                health_window: int = 3) -> tuple[ReconstructionWorker, RecordingLogger,
                                                 Published]:
    log, published = RecordingLogger(), Published()
    worker = ReconstructionWorker(lambda: settings, published, log,
                                  queue_depth=queue_depth, health_window=health_window)
    return worker, log, published


def lights(directions_ps: np.ndarray | None = None) -> LightCalibration:
    """The simulated rig's distant lights (optical frame in the message)."""
    rig = SimulatedRig()
    dirs = ps_to_optical(rig.light_directions_ps() if directions_ps is None else directions_ps)
    return LightCalibration(camera_name="test", directions=[
        Vector3(x=float(x), y=float(y), z=float(z)) for x, y, z in dirs])


def a_burst(burst_id: int, *, image: Image | None = None) -> Burst:
    """A burst message; its content does not matter where the reconstruction is a stand-in
    (an empty one passes the size check)."""
    msg = Burst(burst_id=burst_id)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1000, burst_id
    if image is not None:
        msg.frames = [TaggedFrame(burst_id=burst_id, led_index=0, image=image)]
    return msg


def made(*, flat_field_used: bool = True, print_error: str = "") -> SimpleNamespace:
    """A stand-in for a BurstReconstruction."""
    def fingerprint() -> SimpleNamespace:
        if print_error:
            raise RolledPrintError(PrintRejection.TOO_SMALL, print_error)
        return SimpleNamespace(image=np.zeros((4, 4), np.uint8))
    result = SimpleNamespace(mask=np.ones((5, 6), bool), depth_m=np.ones((5, 6), np.float32),
                             albedo=np.ones((5, 6), np.float32),
                             timings_ms={"mask": 1.0, "normals": 30.0, "total": 40.0})
    return SimpleNamespace(result=result, images=np.zeros((7, 5, 6)),
                           flat_field_used=flat_field_used, fingerprint=fingerprint)


def reconstructs_as(monkeypatch: pytest.MonkeyPatch, outcome: Any) -> list[Burst]:
    """The worker's reconstruct_burst returns ``outcome`` or raises it; returns the bursts
    it was called with."""
    seen: list[Burst] = []

    def stand_in(burst: Burst, *args: Any, **kwargs: Any) -> Any:
        seen.append(burst)
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome
    monkeypatch.setattr(worker_module, "reconstruct_burst", stand_in)
    return seen


# ------------------------------------------------------------------ calibrations in force
def test_a_refused_light_calibration_leaves_the_previous_one_and_warns_until_replaced() -> None:
    worker, log, _ = make_worker()
    worker.on_lights(lights(np.zeros((7, 3))))
    assert worker.calibration.lights is None and worker.calibration.refused_count == 1
    assert log.said("error", "light calibration refused: ")[0].endswith("; none is in force")
    level, message = worker.health()
    assert level == DiagnosticStatus.WARN and message.startswith("light calibration refused")
    good = lights()
    worker.on_lights(good)
    assert worker.calibration.lights is good and worker.health()[0] == DiagnosticStatus.OK
    assert log.said("info", "light calibration received: 7 LEDs")
    worker.on_lights(lights(np.zeros((7, 3))))
    assert worker.calibration.lights is good and worker.calibration.refused_count == 2
    assert log.said("error", "refused")[-1].endswith("; the previous one stays in force")


def test_flat_fields_are_taken_or_refused_on_arrival() -> None:
    worker, log, _ = make_worker()
    maps = [array_to_image(np.full((20, 30), 0.5, np.float32), encoding="32FC1")] * 7
    worker.on_flat(FlatField(maps=maps))
    assert log.said("info", "flat field received: 7 maps (20, 30)")
    worker.on_flat(FlatField(maps=[]))
    assert worker.calibration.refused_count == 1
    assert log.said("error", "flat field refused: 0 flat-field maps")[0].endswith(
        "the previous one stays in force")
    assert worker.health() == (DiagnosticStatus.WARN, worker.last_problem)


# ------------------------------------------------------------------ bursts
def test_a_burst_is_published_counted_timed_and_logged(monkeypatch: pytest.MonkeyPatch) -> None:
    worker, log, published = make_worker()
    worker.on_lights(lights())
    product = made()
    reconstructs_as(monkeypatch, product)
    arrival = time.time_ns()
    worker.process(a_burst(3), arrival)
    [[printed]] = published.calls  # the print the worker made, its only output asked for
    assert printed.topic == topics.FINGERPRINT and printed.encoding == "mono8"
    assert printed.message.header.frame_id == topics.FINGERPRINT_FRAME
    assert printed.message.header.stamp.sec == 1000 and worker.prints_made == 1
    assert (worker.done, worker.failed, worker.last_error) == (1, 0, "")
    assert worker.health() == (DiagnosticStatus.OK,
                               "warming up: compiling or loading the solver kernels")
    worker.ready = True
    assert worker.health() == (DiagnosticStatus.OK, "ok")
    assert list(worker.stages.medians()) == list(StageTimes.KEYS)
    assert worker.stages.medians()["reconstruction_ms"] == 40.0
    assert log.said("info", "burst 3: 30 px, 40 ms (mask 1, normals 30 ms)")
    assert log.lines[-1][2] == {"throttle_duration_sec": 2.0}


def test_a_burst_without_a_light_calibration_says_what_to_do() -> None:
    worker, log, published = make_worker(health_window=2)
    worker.process(a_burst(1), time.time_ns())
    assert not published.calls and worker.failed == 1
    assert worker.last_error.startswith("burst 1: no light calibration yet: call the "
                                        "calibrate_lights service")
    assert worker.health() == (DiagnosticStatus.WARN, worker.last_error)
    worker.process(a_burst(2), time.time_ns())
    level, message = worker.health()
    assert level == DiagnosticStatus.ERROR
    assert message.startswith("the last 2 bursts all failed; last: burst 2: no light")
    assert len(log.said("error", "no light calibration yet")) == 1  # the same problem: once


@pytest.mark.parametrize(("error", "counter", "level"), [
    (IncompleteBurstError("LEDs [0] instead of 0..6"), "incomplete", DiagnosticStatus.ERROR),
    (NoFingerError("no finger"), "failed", DiagnosticStatus.WARN),
    (ValueError("zero-size array"), "unexpected", DiagnosticStatus.ERROR)])
def test_each_failure_is_counted_as_what_it_is(monkeypatch: pytest.MonkeyPatch,
                                               error: Exception, counter: str,
                                               level: bytes) -> None:
    worker, log, _ = make_worker(health_window=1)
    worker.on_lights(lights())
    reconstructs_as(monkeypatch, error)
    worker.process(a_burst(4), time.time_ns())
    assert getattr(worker, counter) == 1 and worker.done == 0
    assert worker.health()[0] == level
    line = log.said("error", "burst 4: ")[0]
    if counter == "unexpected":
        assert worker.failed == 1 and "unexpected ValueError: zero-size array (at " in line
    else:
        assert line == f"burst 4: {error}"


def test_a_flat_field_that_does_not_fit_is_a_warning(monkeypatch: pytest.MonkeyPatch) -> None:
    worker, log, _ = make_worker()
    worker.on_lights(lights())
    worker.on_flat(FlatField(maps=[array_to_image(np.ones((2, 3), np.float32),
                                                  encoding="32FC1")] * 7))
    reconstructs_as(monkeypatch, made(flat_field_used=False))
    worker.process(a_burst(5), time.time_ns())
    assert worker.done == 1 and worker.flat_unused == 1 and worker.last_error == ""
    assert worker.last_problem == ("burst 5: flat field (7, 2, 3) does not fit the images "
                                   "(7, 5, 6); not used")
    level, message = worker.health()
    assert level == DiagnosticStatus.WARN
    assert message == f"1 of the last 1 bursts failed or were degraded; last: " \
                      f"{worker.last_problem}"
    assert log.said("warning", "does not fit")


def test_a_print_not_made_is_counted_and_degrades_the_burst(
        monkeypatch: pytest.MonkeyPatch) -> None:
    worker, log, published = make_worker()
    good, bad = made(), made(print_error="too little of the finger")
    assert worker.fingerprint(good, a_burst(1)) is not None
    assert worker.fingerprint(bad, a_burst(2)) is None
    assert (worker.prints_made, worker.prints_rejected, len(worker.print_ms)) == (1, 1, 1)
    assert worker.last_print_problem == ("burst 2: no fingerprint: too little of the finger")
    assert log.said("warning", "no fingerprint")
    worker.on_lights(lights())
    reconstructs_as(monkeypatch, bad)
    worker.process(a_burst(3), time.time_ns())
    assert published.calls == [[]]  # published without the print
    assert worker.done == 1 and worker.health()[0] == DiagnosticStatus.WARN


def test_a_burst_beyond_the_bounds_never_takes_a_place_in_the_queue() -> None:
    small = ReconSettings(SETTINGS.options, BurstLimits(max_width=10), 4095.0)
    worker, log, _ = make_worker(settings=small)
    worker.on_burst(a_burst(1, image=Image(width=11, height=5, encoding="mono8")))
    assert worker.rejected == 1 and not worker._queue
    assert "beyond max_image_width" in log.said("error", "burst 1: ")[0]


def test_the_queue_drops_the_oldest_and_the_worker_runs_the_rest(
        monkeypatch: pytest.MonkeyPatch) -> None:
    worker, log, published = make_worker(queue_depth=2)
    worker.on_lights(lights())
    reconstructs_as(monkeypatch, made())
    monkeypatch.setattr(worker_module, "warm_up_kernels",
                        lambda: SimpleNamespace(summary="nothing to compile"))
    for burst_id in (1, 2, 3):
        worker.on_burst(a_burst(burst_id))
    assert worker.dropped == 1
    assert log.said("warning", "reconstruction is behind: dropped the oldest burst (1 so far)")
    thread = threading.Thread(target=worker.run)
    thread.start()
    poll_until(lambda: worker.done >= 2, 10.0, interval_s=0.01)
    worker.stop()
    thread.join(timeout=10.0)
    assert not thread.is_alive()
    assert published.burst_ids() == [2, 3]
    assert worker.ready and log.said("info", "reconstruction ready: nothing to compile")


def test_the_next_burst_is_reconstructed_while_the_last_one_is_published(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Two stages: while the output thread is held in burst 1's publish, the worker
    reconstructs bursts 2 and 3 (one waits for the output stage, the next is being made);
    the outputs still go out in order, and stop() lets the output stage finish."""
    worker, _log, published = make_worker(queue_depth=4)
    worker.on_lights(lights())
    reconstructed = reconstructs_as(monkeypatch, made())
    monkeypatch.setattr(worker_module, "warm_up_kernels",
                        lambda: SimpleNamespace(summary="nothing to compile"))
    release = threading.Event()
    publishing: list[str] = []

    def held_publish(outputs: Iterable[Output]) -> None:
        publishing.append(threading.current_thread().name)
        outputs = list(outputs)
        if outputs[0].message.header.stamp.nanosec == 1:
            release.wait(timeout=10.0)
        published(outputs)

    worker._publish = held_publish
    for burst_id in (1, 2, 3, 4):
        worker.on_burst(a_burst(burst_id))
    thread = threading.Thread(target=worker.run, name="recon_worker")
    thread.start()
    try:
        # burst 1 in publish, 2 handed over, 3 made and waiting to be handed over
        poll_until(lambda: len(reconstructed) >= 3, 10.0, interval_s=0.01)
        assert published.calls == [] and worker.done == 0
    finally:
        release.set()
    poll_until(lambda: worker.done >= 4, 10.0, interval_s=0.01)
    worker.stop()
    thread.join(timeout=10.0)
    assert not thread.is_alive()
    assert published.burst_ids() == [1, 2, 3, 4]
    assert set(publishing) == {"recon_output"}


def test_a_guarded_callback_counts_what_it_raises() -> None:
    worker, log, _ = make_worker()

    def broken(msg: object) -> None:
        raise KeyError("k")
    worker.guarded("camera_info", broken)(CameraInfo())
    assert worker.unexpected == 1
    assert worker.last_problem.startswith("camera_info: unexpected KeyError: 'k' (at ")
    assert log.lines[-1][0] == "error" and log.lines[-1][2] == {"throttle_duration_sec": 2.0}


def test_the_calibration_is_prepared_ahead_for_the_camera_seen() -> None:
    worker, log, _ = make_worker()
    rig = SimulatedRig()
    worker.prepare_ahead()  # nothing in force yet: nothing to do
    worker.on_lights(lights())
    height, width = rig.camera.height, rig.camera.width
    camera = CameraInfo(width=width, height=height,
                        k=[float(x) for x in np.asarray(rig.camera_matrix).reshape(-1)])
    worker.on_camera_info(camera)
    worker.prepare_ahead()
    worker.prepare_ahead()  # the same inputs: kept
    assert worker.calibration.prepared.count == 1
    assert log.said("info", f"calibration prepared for the {width}x{height} camera in ")[0] \
        .endswith(" ms (no flat field)")
    worker.on_camera_info(CameraInfo(width=5000, height=10, k=camera.k))
    worker.prepare_ahead()  # beyond the bounds: its bursts will say so
    assert worker.calibration.prepared.count == 1


# ------------------------------------------------------------------ /diagnostics
def test_the_status_carries_every_key_in_order(monkeypatch: pytest.MonkeyPatch) -> None:
    worker, _, _ = make_worker()
    status = reconstruction_status("recon", worker, compressed_failures=2)
    assert status.name == "recon: reconstruction"
    assert (status.level, status.message) == worker.health()
    values = {kv.key: kv.value for kv in status.values}
    assert [kv.key for kv in status.values] == DIAGNOSTIC_KEYS
    assert values["compressed_failures"] == "2" and values["calibrated"] == "False"
    assert values["fingerprint_ms_median"] == "" and values["bursts_done"] == "0"
    worker.on_lights(lights())
    reconstructs_as(monkeypatch, made())
    worker.process(a_burst(1), time.time_ns())
    worker.fingerprint(made(), a_burst(1))
    status = reconstruction_status("recon", worker, compressed_failures=0)
    assert [kv.key for kv in status.values] == DIAGNOSTIC_KEYS + list(StageTimes.KEYS)
    values = {kv.key: kv.value for kv in status.values}
    assert values["bursts_done"] == "1" and values["calibrated"] == "True"
    assert values["reconstruction_ms"] == "40.0" and values["fingerprint_ms_median"] != ""
