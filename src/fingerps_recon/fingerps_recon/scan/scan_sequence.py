"""The Scan action's sequence: wait for a finger, capture still bursts, reconstruct, judge.

`ScanSequence` is what scan_node calls; the node passes in its ROS calls as plain
callables (capture a burst, reconstruct one), so the whole sequence runs in tests with
plain functions. One goal at a time (`ScanSequence.admit`). A goal runs through three
states, reported as feedback (`ScanFeedback`):

1. waiting for a finger: bursts with a dark frame, not published, each checked by
   `finger_presence.detect_finger` (its first LED's frame minus the dark frame) until a
   finger covers ``presence_min_coverage`` of the image;
2. capturing: a burst with a dark frame and the first LED repeated at its end, published
   (so the recorder records it); `burst_motion.estimate_motion` compares the repeated LED's
   frame with its repeat, and a burst in which the finger moved more than ``max_motion_px``
   is rejected, counted and retaken (at most ``max_retakes`` times); a burst without a
   finger goes back to 1;
3. reconstructing: the node's reconstruction, then `quality.quality_figures` and
   `quality.judge_quality`.

After ``bursts`` reconstructions the best (accepted before rejected, then fewer reasons,
then the smaller residual) is the outcome, with its verdict and its rolled print (a print
that cannot be made rejects the scan with its reason). A cancel is honoured between steps
(a burst in progress finishes). The overall timeout ends a goal that found no finger, or no
still one, in time (aborted, with the reason).

No ROS here.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import Enum, IntEnum
from typing import Any, Protocol

import numpy as np

from fingerps_recon.errors import RecordError, RolledPrintError, ScanAbortedError
from fingerps_recon.photometric.pipeline import ReconstructionOptions
from fingerps_recon.records.print_minutiae import PrintMinutiae, find_minutiae
from fingerps_recon.records.print_records import PrintRecords, make_print_records
from fingerps_recon.scan.burst_motion import BurstMotion, estimate_motion
from fingerps_recon.scan.finger_presence import FingerPresence, detect_finger
from fingerps_recon.scan.quality import QualityVerdict, judge_quality, quality_figures
from fingerps_recon.scan.scan_settings import ScanSettings
from fingerps_ros.errors import FingerpsError


class ScanState(IntEnum):
    """The feedback's states, numbered as ``Scan.Feedback``'s constants."""

    WAITING_FOR_FINGER = 0
    CAPTURING = 1
    RECONSTRUCTING = 2


class ScanCancelledError(Exception):
    """The client cancelled the goal."""


class GoalEnd(Enum):
    """How a goal ended."""

    SUCCEEDED = "succeeded"
    ABORTED = "aborted"
    CANCELLED = "cancelled"


@dataclass(frozen=True)
class ScanBurst:
    """A captured burst as the sequence looks at it: arrays, and the message they came from.

    ``lit`` is None for a burst without frames; ``repeat`` is None when the burst has no
    repeat frame, ``repeated`` when it has no frame of the repeated LED (``repeat_led``).
    """

    burst_id: int
    lit: np.ndarray | None
    """(H, W) the first frame."""
    dark: np.ndarray | None
    full_scale: float
    repeated: np.ndarray | None = None
    """(H, W) the frame of the LED repeated at the end of the burst."""
    repeat: np.ndarray | None = None
    """(H, W) its repeat."""
    repeat_led: int = -1
    source: Any = None
    """The burst as captured (the node's message), handed back to ``reconstruct``."""


class Reconstruction(Protocol):
    """What the node's reconstruction of a burst gives (``BurstReconstruction``)."""

    result: Any  # has mask, normals_ps, residual
    images: np.ndarray
    dark: np.ndarray | None
    full_scale: float

    def fingerprint(self) -> Any:
        """The rolled print (``.image``, mono8); raises ``RolledPrintError``."""


@dataclass(frozen=True)
class ScanFeedback:
    """What a goal reports while it runs."""

    state: ScanState
    progress: float
    """0..1 over the goal's bursts."""
    bursts_done: int
    message: str


@dataclass
class ScanTally:
    """Bursts of the running goal, counted as they are taken."""

    bursts_captured: int = 0
    bursts_rejected_motion: int = 0


@dataclass(frozen=True)
class ScanOutcome:
    """The best reconstruction of a goal, judged, with its print."""

    burst: ScanBurst
    made: Reconstruction
    verdict: QualityVerdict
    accepted: bool
    """The verdict's, false too when no print could be made."""
    reasons: tuple[str, ...]
    message: str
    fingerprint: np.ndarray | None
    """(H, W) uint8 the 500 ppi rolled print; None when it cannot be made (see reasons)."""
    records: PrintRecords | None = None
    """The print's exchange records when the goal asked for them (``ScanSettings.records``)
    and the print was made."""


@dataclass(frozen=True)
class ScanEnd:
    """How a goal ended, what to tell the client, and its bursts."""

    end: GoalEnd
    message: str
    tally: ScanTally
    outcome: ScanOutcome | None = None


@dataclass(frozen=True)
class ScanStatus:
    """The sequence's state for /diagnostics (``ok`` false: the last verdict rejected)."""

    ok: bool
    message: str
    values: dict[str, str]


@dataclass
class _Best:
    made: Reconstruction
    burst: ScanBurst
    verdict: QualityVerdict

    def rank(self) -> tuple:
        residual = self.verdict.figures.residual
        return (not self.verdict.accepted, len(self.verdict.reasons),
                residual if math.isfinite(residual) else math.inf)


Capture = Callable[[bool, bool], ScanBurst]
"""``capture(publish, repeat_first_led)``: one burst with a dark frame."""
Reconstruct = Callable[[ScanBurst, ReconstructionOptions], Reconstruction]


class ScanSequence:
    """Runs Scan goals one at a time and keeps what /diagnostics shows of them.

    Parameters
    ----------
    capture : Capture
        Takes a burst; raises `ScanAbortedError` when the driver does not answer.
    reconstruct : Reconstruct
        Reconstructs a burst with the options of the goal.
    logger : Any
        The node's logger (``info``, ``warning``).
    clock, sleep : Callable
        Monotonic seconds and sleeping (replaceable in tests).
    """

    def __init__(self, *, capture: Capture, reconstruct: Reconstruct, logger: Any,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self._capture = capture
        self._reconstruct = reconstruct
        self._log = logger
        self._clock = clock
        self._sleep = sleep
        self._lock = threading.Lock()
        self._busy = False
        self.last_verdict: QualityVerdict | None = None
        self.counts = {"goals": 0, "rejected_goals": 0, "succeeded": 0, "aborted": 0,
                       "cancelled": 0, "bursts_rejected_motion": 0}

    @property
    def busy(self) -> bool:
        """A goal is running."""
        return self._busy

    def admit(self, problem: str | None, *, calibrated: bool) -> str | None:
        """Accept a goal (the sequence is busy from now on) or say why it is rejected.

        ``problem`` is what is impossible about the goal, if anything.
        """
        reason = problem
        if reason is None and not calibrated:
            reason = ("no light calibration yet: calibrate the lights (calibrate_lights) or "
                      "start calib_node with a saved calibration")
        if reason is None:
            with self._lock:
                if self._busy:
                    reason = "a scan is already running (one finger at a time); cancel it or " \
                             "wait for its result"
                else:
                    self._busy = True
        self.counts["rejected_goals" if reason is not None else "goals"] += 1
        return reason

    def execute(self, settings: Callable[[], ScanSettings], *,
                report: Callable[[ScanFeedback], None], cancelled: Callable[[], bool],
                deliver: Callable[[ScanOutcome], None]) -> ScanEnd:
        """Run an admitted goal to its end; never raises for the goal's own problems.

        ``deliver`` gets the outcome before the goal ends (an error it raises aborts it).
        """
        tally = ScanTally()
        try:
            outcome = self.run(settings(), tally, report=report, cancelled=cancelled)
            self._log.info(f"Scan done: {outcome.message}")
            self.last_verdict = outcome.verdict
            deliver(outcome)
        except ScanCancelledError:
            self.counts["cancelled"] += 1
            return ScanEnd(GoalEnd.CANCELLED, "cancelled; the LEDs are off", tally)
        except FingerpsError as exc:  # ScanAbortedError among them
            self.counts["aborted"] += 1
            self._log.warning(f"Scan aborted: {exc}")
            return ScanEnd(GoalEnd.ABORTED, str(exc), tally)
        finally:
            with self._lock:
                self._busy = False
        self.counts["succeeded"] += 1
        return ScanEnd(GoalEnd.SUCCEEDED, outcome.message, tally, outcome)

    def run(self, settings: ScanSettings, tally: ScanTally, *,
            report: Callable[[ScanFeedback], None],
            cancelled: Callable[[], bool]) -> ScanOutcome:
        """The goal's states until ``settings.bursts`` reconstructions; the best of them.

        Raises
        ------
        ScanCancelledError, ScanAbortedError
            Cancelled; timed out, the finger kept moving, the driver failed.
        """
        deadline = self._clock() + settings.timeout_s
        best: _Best | None = None
        done = 0
        state = ScanState.WAITING_FOR_FINGER
        presence: FingerPresence | None = None

        def tell(new_state: ScanState, message: str) -> None:
            report(ScanFeedback(new_state, float(done) / settings.bursts, done, message))

        while done < settings.bursts:
            if cancelled():
                raise ScanCancelledError
            if self._clock() > deadline:
                what = ("no finger in view" if state == ScanState.WAITING_FOR_FINGER
                        else f"only {done} of {settings.bursts} bursts reconstructed")
                raise ScanAbortedError(f"timed out after {settings.timeout_s:g} s: {what} "
                                       f"({tally.bursts_captured} bursts captured, "
                                       f"{tally.bursts_rejected_motion} retaken for motion)")
            if state == ScanState.WAITING_FOR_FINGER:
                tell(state, "place a finger in view")
                presence = _presence(self._capture(False, False), settings)
                if presence.present:
                    state = ScanState.CAPTURING
                else:
                    self._sleep(settings.presence_period_s)
                continue
            tell(ScanState.CAPTURING, presence.describe() if presence else "")
            burst = self._capture(True, True)
            tally.bursts_captured += 1
            presence = _presence(burst, settings)
            if not presence.present:
                state = ScanState.WAITING_FOR_FINGER
                continue
            motion = _motion(burst)
            if motion.magnitude_px > settings.thresholds.max_motion_px:
                self._retake(burst, motion, settings, tally)
                continue
            tell(ScanState.RECONSTRUCTING, f"burst {burst.burst_id}")
            made = self._reconstruct(burst, settings.options)
            done += 1
            candidate = _Best(made, burst, _judge(made, motion, settings))
            if best is None or candidate.rank() < best.rank():
                best = candidate
        assert best is not None
        tell(ScanState.RECONSTRUCTING, "done")
        return _outcome(best, settings)

    def _retake(self, burst: ScanBurst, motion: BurstMotion, settings: ScanSettings,
                tally: ScanTally) -> None:
        """Count a burst the finger moved in; abort after ``max_retakes`` of them."""
        limit = settings.thresholds.max_motion_px
        tally.bursts_rejected_motion += 1
        self.counts["bursts_rejected_motion"] += 1
        self._log.info(f"burst {burst.burst_id} rejected: the finger moved "
                       f"{motion.magnitude_px:.2f} px > {limit:g} px; retaking")
        if tally.bursts_rejected_motion > settings.max_retakes:
            raise ScanAbortedError(
                f"the finger kept moving: {tally.bursts_rejected_motion} bursts moved "
                f"more than {limit:g} px (last {motion.magnitude_px:.2f} px); hold the finger "
                "still and try again")

    def status(self, *, calibrated: bool) -> ScanStatus:
        """The counts, the last verdict and its figures, whether busy and calibrated."""
        verdict = self.last_verdict
        if verdict is None:
            ok, message, figures = True, "no scan yet", {}
        else:
            ok = verdict.accepted
            message = "accepted" if verdict.accepted else "rejected: " + "; ".join(
                verdict.reasons)
            figures = {k: f"{v:.4g}" for k, v in vars(verdict.figures).items()}
        values = {k: str(v) for k, v in self.counts.items()}
        values.update(figures)
        values.update(busy=str(self._busy), calibrated=str(calibrated))
        return ScanStatus(ok, message, values)


def _presence(burst: ScanBurst, settings: ScanSettings) -> FingerPresence:
    if burst.lit is None:
        raise ScanAbortedError("the driver sent a burst without frames")
    return detect_finger(burst.lit, dark=burst.dark, full_scale=burst.full_scale,
                         threshold=settings.presence_threshold,
                         min_coverage=settings.presence_min_coverage)


def _motion(burst: ScanBurst) -> BurstMotion:
    """Shift between the repeated LED's frame in the burst and its repeat."""
    if burst.repeat is None:
        raise ScanAbortedError("the driver sent no repeat frame: update driver_node (it needs "
                               "CaptureBurst.repeat_first_led)")
    if burst.repeated is None:
        raise ScanAbortedError(f"the burst has no frame of LED {burst.repeat_led}, which it "
                               "repeated")
    return estimate_motion(burst.repeated, burst.repeat)


def _judge(made: Reconstruction, motion: BurstMotion, settings: ScanSettings) -> QualityVerdict:
    residual = made.result.residual
    figures = quality_figures(
        made.images, mask=made.result.mask, normals_ps=made.result.normals_ps,
        full_scale=made.full_scale, dark=made.dark,
        shadow_fraction=settings.options.shadow_fraction,
        saturation_fraction=settings.options.saturation_fraction,
        motion_px=motion.magnitude_px, motion_correlation=motion.correlation,
        residual=math.nan if residual is None else residual)
    return judge_quality(figures, settings.thresholds)


def _outcome(best: _Best, settings: ScanSettings) -> ScanOutcome:
    """The best burst's verdict with its print, judged again with the print's NFIQ 2, and the
    print's records if the goal asked for them; no print rejects it (never a garbage print
    passed as good)."""
    verdict = best.verdict
    records = None
    try:
        fingerprint = best.made.fingerprint().image
    except RolledPrintError as exc:
        fingerprint, print_problem = None, f"fingerprint: {exc}"
    else:
        print_problem = ""
        minutiae = _minutiae(fingerprint)
        nfiq2 = math.nan if minutiae is None or minutiae.nfiq2 is None else minutiae.nfiq2
        verdict = judge_quality(replace(verdict.figures, nfiq2=float(nfiq2)),
                                settings.thresholds)
        if settings.records:
            records = make_print_records(fingerprint, minutiae=minutiae,
                                         transaction_control=f"burst-{best.burst.burst_id}")
    accepted = verdict.accepted and fingerprint is not None
    reasons = (*verdict.reasons, print_problem) if print_problem else verdict.reasons
    nfiq2 = verdict.figures.nfiq2
    message = (f"burst {best.burst.burst_id}: "
               + ("accepted" if accepted else "rejected: " + "; ".join(reasons))
               + ("" if math.isnan(nfiq2) else f" (NFIQ 2 {nfiq2:.0f})"))
    return ScanOutcome(best.burst, best.made, verdict, accepted, tuple(reasons), message,
                       fingerprint, records)


def _minutiae(fingerprint: np.ndarray) -> PrintMinutiae | None:
    """NBIS's minutiae and NFIQ 2 of the print; None when NBIS cannot process it."""
    try:
        return find_minutiae(fingerprint)
    except RecordError:
        return None
