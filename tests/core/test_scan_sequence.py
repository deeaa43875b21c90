"""Tests of the Scan action's sequence without a ROS graph: fingerps_recon.scan.scan_sequence
and scan_settings.

The driver is a plain function returning prepared bursts (arrays), the reconstruction one
returning a stand-in with the arrays the verdict looks at; the clock and sleep are fakes.
"""

from __future__ import annotations

from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from rig_prints import true_rolled_print

from fingerps_recon.errors import ImpossibleGoalError, RolledPrintError, ScanAbortedError
from fingerps_recon.photometric.pipeline import Model, ReconstructionOptions
from fingerps_recon.scan.scan_sequence import (
    GoalEnd,
    ScanBurst,
    ScanFeedback,
    ScanOutcome,
    ScanSequence,
    ScanState,
    ScanTally,
)
from fingerps_recon.scan.scan_settings import (
    GOAL_PARAMETERS,
    MAX_BURSTS,
    SCAN_PARAMETERS,
    ScanSettings,
    goal_settings,
)
from fingerps_recon.surface.rolled_print import PrintRejection
from fingerps_ros.errors import FingerpsError

H = W = 64
RIDGE_PERIOD_PX = 8.0


def _logger(lines: list[tuple[str, str]]) -> SimpleNamespace:
    """A logger that keeps its lines as (level, text)."""
    return SimpleNamespace(info=lambda text, **_: lines.append(("info", text)),
                           warning=lambda text, **_: lines.append(("warning", text)))


class FakeClock:
    """Monotonic seconds that move only when the test sleeps or captures."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


def _frame(finger: bool, shift_px: int = 0) -> np.ndarray:
    """A lit frame: a textured fingertip disk on a dark background (uint8)."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    cols = cols - shift_px
    disk = (rows - H / 2) ** 2 + (cols - W / 2) ** 2 < (0.35 * H) ** 2
    texture = 40.0 * np.sin(2 * np.pi * cols / RIDGE_PERIOD_PX) * np.cos(2 * np.pi * rows / 11.0)
    frame = np.full((H, W), 10.0)
    if finger:
        frame = np.where(disk, 150.0 + texture, frame)
    return frame.astype(np.uint8)


def _burst(burst_id: int, *, finger: bool = True, shift_px: int = 0, repeat: bool = True,
           frames: bool = True) -> ScanBurst:
    lit = _frame(finger)
    return ScanBurst(burst_id, lit if frames else None, np.full((H, W), 10, np.uint8), 255.0,
                     repeated=lit if repeat else None,
                     repeat=_frame(finger, shift_px) if repeat else None, repeat_led=0,
                     source=f"message {burst_id}")


def _reconstruction(*, residual: float = 0.05, print_error: str | None = None,
                    print_image: np.ndarray | None = None) -> Any:
    """What the verdict looks at: a finger disk, ridged normals, mid-grey frames."""
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    mask = (rows - H / 2) ** 2 + (cols - W / 2) ** 2 < (0.35 * H) ** 2
    slope = 0.3 * np.cos(2 * np.pi * cols / RIDGE_PERIOD_PX)
    normals = np.stack([-slope, np.zeros_like(slope), np.ones_like(slope)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    images = np.full((3, H, W), 120, np.uint8)

    def fingerprint() -> SimpleNamespace:
        if print_error:
            raise RolledPrintError(PrintRejection.TOO_SMALL, print_error)
        return SimpleNamespace(image=np.full((10, 10), 128, np.uint8) if print_image is None
                               else print_image)

    result = SimpleNamespace(mask=mask, normals_ps=normals, residual=residual)
    return SimpleNamespace(result=result, images=images, dark=None, full_scale=255.0,
                           fingerprint=fingerprint)


def _settings(**changes: Any) -> ScanSettings:
    values = {s.name: s.default for s in SCAN_PARAMETERS if s.name in GOAL_PARAMETERS}
    values.update(changes.pop("values", {}))
    fields = {"bursts": 1, "model": "", "timeout_s": 10.0, "values": values,
              "default_timeout_s": 30.0, "presence_period_s": 0.2, **changes}
    return goal_settings(**fields)


class Rig:
    """The sequence with plain functions for the driver and the reconstruction."""

    def __init__(self, bursts: list[ScanBurst], made: list[Any] | None = None) -> None:
        self.bursts: Iterator[ScanBurst] = iter(bursts)
        self.made = iter(made or [])
        self.captures: list[tuple[bool, bool]] = []
        self.reconstructed: list[tuple[Any, ReconstructionOptions]] = []
        self.feedback: list[ScanFeedback] = []
        self.delivered: list[ScanOutcome] = []
        self.clock = FakeClock()
        self.lines: list[tuple[str, str]] = []
        self.cancel = False
        self.sequence = ScanSequence(capture=self.capture, reconstruct=self.reconstruct,
                                     logger=_logger(self.lines), clock=self.clock,
                                     sleep=self.clock.sleep)

    def capture(self, publish: bool, repeat: bool) -> ScanBurst:
        self.captures.append((publish, repeat))
        self.clock.now += 0.1
        return next(self.bursts)

    def reconstruct(self, burst: ScanBurst, options: ReconstructionOptions) -> Any:
        self.reconstructed.append((burst.source, options))
        return next(self.made, None) or _reconstruction()

    def execute(self, settings: ScanSettings) -> Any:
        assert self.sequence.admit(None, calibrated=True) is None
        return self.sequence.execute(lambda: settings, report=self.feedback.append,
                                     cancelled=lambda: self.cancel,
                                     deliver=self.delivered.append)


def test_waits_for_a_finger_captures_a_still_burst_and_judges_it() -> None:
    rig = Rig([_burst(1, finger=False), _burst(2), _burst(3)])
    end = rig.execute(_settings())

    assert end.end is GoalEnd.SUCCEEDED, end.message
    assert end.message == "burst 3: accepted" == end.outcome.message
    assert end.outcome.accepted and end.outcome.reasons == ()
    assert end.outcome.fingerprint.shape == (10, 10)
    assert end.tally == ScanTally(bursts_captured=1, bursts_rejected_motion=0)
    assert rig.delivered == [end.outcome]
    assert rig.captures == [(False, False), (False, False), (True, True)]
    assert rig.reconstructed[0][0] == "message 3"
    assert rig.reconstructed[0][1].model is Model.HK
    states = [(f.state, f.bursts_done, f.progress) for f in rig.feedback]
    assert states == [(ScanState.WAITING_FOR_FINGER, 0, 0.0),
                      (ScanState.WAITING_FOR_FINGER, 0, 0.0), (ScanState.CAPTURING, 0, 0.0),
                      (ScanState.RECONSTRUCTING, 0, 0.0), (ScanState.RECONSTRUCTING, 1, 1.0)]
    assert [f.message for f in rig.feedback][:2] == ["place a finger in view"] * 2
    assert rig.feedback[2].message.startswith("finger at row ")
    assert [f.message for f in rig.feedback][3:] == ["burst 3", "done"]
    assert ScanState.WAITING_FOR_FINGER.name.lower() == "waiting_for_finger"
    assert ("info", "Scan done: burst 3: accepted") in rig.lines
    assert rig.sequence.counts == {"goals": 1, "rejected_goals": 0, "succeeded": 1,
                                   "aborted": 0, "cancelled": 0, "bursts_rejected_motion": 0}
    assert not rig.sequence.busy


def test_the_best_of_several_bursts_is_the_result() -> None:
    made = [_reconstruction(residual=5.0), _reconstruction(residual=0.2),
            _reconstruction(residual=0.1)]
    rig = Rig([_burst(1), _burst(2), _burst(3), _burst(4)], made)
    end = rig.execute(_settings(bursts=3))
    assert end.end is GoalEnd.SUCCEEDED
    assert end.outcome.burst.burst_id == 4  # accepted and the smallest residual
    assert end.outcome.made is made[2]
    assert end.tally.bursts_captured == 3


def test_a_rejected_verdict_and_a_print_that_cannot_be_made() -> None:
    rig = Rig([_burst(1), _burst(2)], [_reconstruction(residual=5.0)])
    end = rig.execute(_settings())
    assert end.end is GoalEnd.SUCCEEDED and not end.outcome.accepted
    assert end.message.startswith("burst 2: rejected: fit residual 5.000 > 0.250")
    status = rig.sequence.status(calibrated=True)
    assert not status.ok and status.message.startswith("rejected: fit residual 5.000")

    rig = Rig([_burst(1), _burst(2)], [_reconstruction(print_error="too little finger")])
    end = rig.execute(_settings())
    assert end.outcome.verdict.accepted and not end.outcome.accepted
    assert end.outcome.reasons == ("fingerprint: too little finger",)
    assert end.message == "burst 2: rejected: fingerprint: too little finger"
    assert end.outcome.fingerprint is None
    assert rig.sequence.status(calibrated=True).ok  # the quality verdict itself accepted


@pytest.fixture(scope="module")
def rig_print() -> np.ndarray:
    return true_rolled_print(3)


def test_the_print_s_nfiq2_is_judged_and_its_records_made_on_request(rig_print) -> None:
    made = _reconstruction(print_image=rig_print)
    end = Rig([_burst(1), _burst(2)], [made]).execute(_settings())
    nfiq2 = end.outcome.verdict.figures.nfiq2
    assert end.outcome.accepted and 0 < nfiq2 <= 100 and end.outcome.records is None
    assert end.message.endswith(f"(NFIQ 2 {nfiq2:.0f})")

    # Above the print's NFIQ 2: rejected, with what to do; the records on request.
    made = _reconstruction(print_image=rig_print)
    end = Rig([_burst(1), _burst(2)], [made]).execute(
        _settings(records=True, values={"min_nfiq2": nfiq2 + 1}))
    assert not end.outcome.accepted
    (reason,) = end.outcome.reasons
    assert reason.startswith(f"print quality NFIQ 2 {nfiq2:.0f} < {nfiq2 + 1:.0f}: ")
    records = end.outcome.records
    assert records is not None and records.nfiq2 == nfiq2
    assert records.wsq[:2] == b"\xff\xa0" and records.iso_template[:4] == b"FMR\x00"
    assert b"1.009:burst-2" in records.transaction


def test_a_moving_finger_is_retaken_then_aborts() -> None:
    moving = [_burst(i, shift_px=6) for i in range(2, 6)]
    rig = Rig([_burst(1), *moving])
    end = rig.execute(_settings(values={"max_retakes": 2}))
    assert end.end is GoalEnd.ABORTED
    assert end.message.startswith("the finger kept moving: 3 bursts moved more than 2 px "
                                  "(last 5.")
    assert end.message.endswith("px); hold the finger still and try again")
    assert end.tally == ScanTally(bursts_captured=3, bursts_rejected_motion=3)
    assert rig.sequence.counts["bursts_rejected_motion"] == 3
    assert rig.sequence.counts["aborted"] == 1
    retakes = [t for lv, t in rig.lines if "rejected: the finger moved" in t]
    assert len(retakes) == 3 and retakes[0].startswith("burst 2 rejected: the finger moved 5.")
    assert ("warning", f"Scan aborted: {end.message}") in rig.lines
    assert not rig.reconstructed


def test_a_burst_without_a_finger_goes_back_to_waiting() -> None:
    rig = Rig([_burst(1), _burst(2, finger=False), _burst(3), _burst(4)])
    end = rig.execute(_settings())
    assert end.end is GoalEnd.SUCCEEDED and end.outcome.burst.burst_id == 4
    assert rig.captures == [(False, False), (True, True), (False, False), (True, True)]
    assert end.tally.bursts_captured == 2


def test_timeout_says_what_was_missing() -> None:
    rig = Rig([_burst(i, finger=False) for i in range(100)])
    end = rig.execute(_settings(timeout_s=1.0))
    assert end.end is GoalEnd.ABORTED
    assert end.message == ("timed out after 1 s: no finger in view (0 bursts captured, 0 "
                           "retaken for motion)")
    assert rig.clock.now >= 101.0


def test_timeout_while_capturing() -> None:
    rig = Rig([_burst(1)] + [_burst(i, shift_px=6) for i in range(2, 100)])
    end = rig.execute(_settings(timeout_s=0.5, values={"max_retakes": 100}))
    assert end.end is GoalEnd.ABORTED
    assert end.message.startswith("timed out after 0.5 s: only 0 of 1 bursts reconstructed (")
    assert f"({end.tally.bursts_captured} bursts captured, " in end.message


def test_cancel_is_honoured_between_steps() -> None:
    rig = Rig([_burst(1, finger=False)] * 3)
    original = rig.capture

    def capture_then_cancel(publish: bool, repeat: bool) -> ScanBurst:
        rig.cancel = True
        return original(publish, repeat)

    rig.sequence._capture = capture_then_cancel
    end = rig.execute(_settings())
    assert end.end is GoalEnd.CANCELLED and end.message == "cancelled; the LEDs are off"
    assert len(rig.captures) == 1 and rig.sequence.counts["cancelled"] == 1
    assert not rig.delivered


@pytest.mark.parametrize(("burst", "message"), [
    (_burst(2, frames=False), "the driver sent a burst without frames"),
    (_burst(2, repeat=False), "the driver sent no repeat frame: update driver_node (it needs "
                              "CaptureBurst.repeat_first_led)"),
    (ScanBurst(2, _frame(True), None, 255.0, repeat=_frame(True), repeat_led=3),
     "the burst has no frame of LED 3, which it repeated"),
])
def test_bad_bursts_abort_with_the_reason(burst: ScanBurst, message: str) -> None:
    rig = Rig([_burst(1), burst])
    end = rig.execute(_settings())
    assert (end.end, end.message) == (GoalEnd.ABORTED, message)


def test_driver_and_deliver_errors_abort() -> None:
    def no_driver(publish: bool, repeat: bool) -> ScanBurst:
        raise ScanAbortedError("no answer from capture_burst within 1 s")

    sequence = ScanSequence(capture=no_driver, reconstruct=lambda b, o: None,
                            logger=_logger([]))
    assert sequence.admit(None, calibrated=True) is None
    end = sequence.execute(_settings, report=lambda f: None, cancelled=lambda: False,
                           deliver=lambda o: None)
    assert (end.end, end.message) == (GoalEnd.ABORTED, "no answer from capture_burst within 1 s")

    rig = Rig([_burst(1), _burst(2)])

    def refuse(outcome: ScanOutcome) -> None:
        raise FingerpsError("cannot convert")

    assert rig.sequence.admit(None, calibrated=True) is None
    end = rig.sequence.execute(_settings, report=lambda f: None, cancelled=lambda: False,
                               deliver=refuse)
    assert (end.end, end.message) == (GoalEnd.ABORTED, "cannot convert")


def test_admission_one_goal_at_a_time_and_calibrated() -> None:
    sequence = ScanSequence(capture=lambda p, r: _burst(1), reconstruct=lambda b, o: None,
                            logger=_logger([]))
    assert sequence.admit(None, calibrated=False).startswith("no light calibration yet: ")
    assert sequence.admit("impossible goal: bursts 0: must be 1..20",
                          calibrated=True) == "impossible goal: bursts 0: must be 1..20"
    assert sequence.admit(None, calibrated=True) is None
    assert sequence.busy
    assert sequence.admit(None, calibrated=True) == (
        "a scan is already running (one finger at a time); cancel it or wait for its result")
    assert sequence.counts["goals"] == 1 and sequence.counts["rejected_goals"] == 3
    status = sequence.status(calibrated=False)
    assert status.ok and status.message == "no scan yet"
    assert status.values == {"goals": "1", "rejected_goals": "3", "succeeded": "0",
                             "aborted": "0", "cancelled": "0", "bursts_rejected_motion": "0",
                             "busy": "True", "calibrated": "False"}


def test_status_carries_the_last_figures() -> None:
    rig = Rig([_burst(1), _burst(2)])
    rig.execute(_settings())
    values = rig.sequence.status(calibrated=True).values
    assert list(values)[6:] == ["coverage", "saturated_fraction", "dark_fraction",
                                "ridge_visibility", "motion_px", "motion_correlation",
                                "residual", "nfiq2", "busy", "calibrated"]
    assert values["residual"] == "0.05" and values["busy"] == "False"


def test_goal_settings_from_parameters_and_overrides() -> None:
    settings = _settings(model="lambert", timeout_s=0.0,
                         values={"max_motion_px": 3, "w": 9, "presence_threshold": 0.2})
    assert settings.options.model is Model.LAMBERT and settings.options.w == 9
    assert settings.timeout_s == 30.0 and settings.thresholds.max_motion_px == 3.0
    assert settings.presence_threshold == 0.2 and settings.presence_period_s == 0.2
    assert settings.max_retakes == 5 and settings.bursts == 1

    with pytest.raises(ImpossibleGoalError) as caught:
        _settings(bursts=0, model="phong", timeout_s=-1.0, problems=["override 'x': nope"])
    assert str(caught.value) == (
        f"bursts 0: must be 1..{MAX_BURSTS}; unknown model 'phong': use lambert or hk; "
        "timeout -1.0: must be > 0 seconds (0 = the node's timeout parameter); "
        "override 'x': nope")
    with pytest.raises(FingerpsError, match="min_coverage"):
        _settings(values={"min_coverage": -1.0})


def test_the_parameter_table() -> None:
    names = [s.name for s in SCAN_PARAMETERS]
    assert len(names) == len(set(names)) == 25 - 2  # + use_sim_time, start_type_description
    assert set(GOAL_PARAMETERS) <= set(names)
    for spec in SCAN_PARAMETERS:
        if spec.min_value is not None:
            assert spec.min_value <= spec.default <= spec.max_value, spec.name
