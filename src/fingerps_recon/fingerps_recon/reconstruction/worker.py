"""recon_node's worker without the node: the calibration in force, the burst queue, the
bursts reconstructed one by one, and the bookkeeping ``/diagnostics`` reports.

:class:`ReconstructionWorker` is a plain class: the node's subscriptions hand it messages
(``on_lights``, ``on_flat``, ``on_camera_info``, ``on_burst``), the node's worker thread runs
:meth:`ReconstructionWorker.run`, and the node publishes the messages the worker builds
from a burst (the print included) through the ``publish`` callable it gives. The bursts go
through two stages on two threads: the worker reconstructs burst n + 1 while an output
thread builds and publishes burst n's messages (the print too;
serial code only, so numba's parallel kernels stay on the worker's thread), in order, at
most one burst waiting between them. The queue is bounded and drops the oldest burst (counted). A
light calibration or flat field that cannot determine normals is refused on arrival (the
previous one stays in force); anything a burst raises, expected or not, is logged in one
line naming the burst and counted, and the worker goes on with the next burst. The health
level is ERROR when all of the last ``health_window`` bursts failed, WARN while one of them
failed or was degraded (or a refused calibration was not replaced), OK otherwise.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from sensor_msgs.msg import CameraInfo

from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_recon.errors import (
    IncompleteBurstError,
    NoFingerError,
    RolledPrintError,
)
from fingerps_recon.photometric.kernel_warm_up import warm_up_kernels
from fingerps_recon.photometric.pipeline import ReconstructionOptions
from fingerps_recon.reconstruction.burst_intake import BurstLimits, check_burst_size
from fingerps_recon.reconstruction.burst_reconstruction import (
    BurstReconstruction,
    reconstruct_burst,
)
from fingerps_recon.reconstruction.calibration_in_force import (
    FLAT_FIELD,
    LIGHTS,
    CalibrationInForce,
)
from fingerps_recon.reconstruction.outputs import (
    OUTPUT_TOPICS,
    Output,
    fingerprint_output,
    output_messages,
)
from fingerps_recon.reconstruction.problem_log import LogGate, one_line
from fingerps_recon.surface.rolled_print import RolledPrint
from fingerps_ros.errors import FingerpsError
from fingerps_ros.log import Log
from fingerps_ros.time_conversion import time_nanoseconds

_T = TypeVar("_T")

# Outcome of a burst, for the health level.
_OK, _WARN, _BAD = 0, 1, 2


@dataclass(frozen=True)
class ReconSettings:
    """The parameters a burst is reconstructed with, and the outputs it is to give, as they
    are now: ``wanted`` the topics of ``outputs.output_messages`` someone watches,
    ``fingerprint`` whether to make the rolled print."""

    options: ReconstructionOptions
    limits: BurstLimits
    mono16_full_scale: float
    wanted: tuple[str, ...] = OUTPUT_TOPICS
    fingerprint: bool = False


@dataclass(frozen=True)
class _Made:
    """A burst reconstructed, on its way to the output stage."""

    burst: Burst
    arrival_ns: int
    start_ns: int
    made: BurstReconstruction
    outcome: int
    settings: ReconSettings  # read once for the burst: its outputs are those it asked for


class StageTimes:
    """Where the recent bursts' time went, from the burst's stamp (its capture) to the
    outputs' publication: arrival here, waiting in the queue, reconstruction, publishing."""

    KEYS = ("capture_to_arrival_ms", "queue_wait_ms", "reconstruction_ms", "publish_ms",
            "capture_to_published_ms")

    def __init__(self, keep: int = 50) -> None:
        self._rows: deque[tuple[float, ...]] = deque(maxlen=keep)

    def add(self, stamp_ns: int, arrival_ns: int, start_ns: int, compute_ms: float,
            published_ns: int) -> None:
        """One burst: its stamp, arrival, start of work, reconstruction time and the moment
        its last output was published (wall-clock ns)."""
        ms = 1e-6
        work_ms = (published_ns - start_ns) * ms
        self._rows.append(((arrival_ns - stamp_ns) * ms, (start_ns - arrival_ns) * ms,
                           compute_ms, work_ms - compute_ms, (published_ns - stamp_ns) * ms))

    def medians(self) -> dict[str, float]:
        """Median of each stage over the recent bursts, ms (empty before the first)."""
        if not self._rows:
            return {}
        return dict(zip(self.KEYS, np.median(np.array(self._rows), axis=0), strict=True))


class ReconstructionWorker:
    """Reconstructs every queued burst with the calibration in force and counts the outcome.

    Parameters
    ----------
    settings : Callable[[], ReconSettings]
        The parameters now (read at every message and burst, so a change applies at once).
    publish : Callable[[Iterable[Output]], None]
        Publishes a burst's outputs (``outputs.Output``: topic, message, the array of a
        compressed companion), each as it comes: the worker builds them, the print included.
    logger : Log
        The node's logger.
    queue_depth, health_window : int
        Bursts waiting at most (the oldest is dropped beyond); recent bursts judged.
    """

    def __init__(self, settings: Callable[[], ReconSettings],
                 publish: Callable[[Iterable[Output]], None], logger: Log, *,
                 queue_depth: int, health_window: int) -> None:
        self._settings = settings
        self._publish = publish
        self._log = logger
        # (burst, arrival time ns) waiting for the worker
        self._queue: deque[tuple[Burst, int]] = deque(maxlen=queue_depth)
        self._cv = threading.Condition()
        self._stop = False
        self.stages = StageTimes()
        self.dropped = self.done = self.failed = self.incomplete = self.rejected = 0
        self.unexpected = self.flat_unused = 0
        self.prints_made = self.prints_rejected = 0
        self.last_error = self.last_problem = self.last_print_problem = ""
        self.print_ms: deque[float] = deque(maxlen=50)
        # outcome of each recent burst: OK, WARN (no finger, flat field not used) or BAD
        self._outcomes: deque[int] = deque(maxlen=health_window)
        self._log_gate = LogGate()
        self.calibration = CalibrationInForce()
        self._camera: CameraInfo | None = None
        self.ready = False
        self._count_lock = threading.Lock()  # the two stages count failures
        # Reconstructed bursts for the output thread (None: stop); at most one waits.
        self._handoff: queue.Queue[_Made | None] = queue.Queue(maxsize=1)

    def guarded(self, what: str, callback: Callable[..., None]) -> Callable[..., None]:
        """``callback`` that logs and counts what it raises instead of ending the node."""
        def run(*args: object) -> None:
            try:
                callback(*args)
            except Exception as exc:  # a callback must never end the node
                self.unexpected += 1
                self.last_problem = f"{what}: unexpected {one_line(exc)}"
                self._log.error(self.last_problem, throttle_duration_sec=2.0)
        return run

    # ------------------------------------------------------------------ intake
    def _offer(self, kind: str, offer: Callable[[], object], held: object) -> object | None:
        """Offer a calibration message to the calibration in force: what it put in force,
        or None once it is refused (counted there, logged here, and WARN until one of its
        ``kind`` is accepted); ``held`` is the calibration of that kind in force now."""
        try:
            return offer()
        except FingerpsError as exc:
            self.last_problem = f"{kind} refused: {exc}"
            self._log.error(f"{self.last_problem}; "
                            + ("the previous one stays in force" if held is not None
                               else "none is in force"))
            return None

    def on_lights(self, msg: LightCalibration) -> None:
        """A light calibration: in force from the next burst on, unless it is refused."""
        calibration = self.calibration
        if self._offer(LIGHTS, lambda: calibration.offer_lights(msg),
                       calibration.lights) is not None:
            self._log.info(f"light calibration received: {len(msg.directions)} LEDs")

    def on_flat(self, msg: FlatField) -> None:
        """A flat field: in force from the next burst on, unless it is refused."""
        calibration = self.calibration
        maps = self._offer(FLAT_FIELD,
                           lambda: calibration.offer_flat(msg, self._settings().limits),
                           calibration.flat_maps)
        if isinstance(maps, np.ndarray):
            self._log.info(f"flat field received: {maps.shape[0]} maps {maps.shape[1:]}")

    def on_camera_info(self, msg: CameraInfo) -> None:
        """Kept so that the calibration is prepared for the camera before its first burst."""
        self._camera = msg

    def on_burst(self, msg: Burst) -> None:
        """Queue a burst for the worker; one beyond the size bounds is refused first."""
        try:  # refused before it takes a place in the queue
            check_burst_size(msg, self._settings().limits)
        except FingerpsError as exc:
            self.rejected += 1
            self._note(_BAD, msg, exc)
            return
        with self._cv:
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
                self._log.warning(
                    f"reconstruction is behind: dropped the oldest burst ({self.dropped} so "
                    "far)", throttle_duration_sec=5.0)
            self._queue.append((msg, time.time_ns()))
            self._cv.notify()

    # ------------------------------------------------------------------ work
    def run(self) -> None:
        """The worker thread: warm the kernels, then reconstruct the queued bursts (and
        prepare the calibration ahead while idle) until :meth:`stop`, handing each to the
        output thread it starts (and joins before it returns)."""
        output = threading.Thread(target=self._output_stage, name="recon_output")
        output.start()
        try:
            self._reconstruct_stage()
        finally:
            self._handoff.put(None)
            output.join()

    def _reconstruct_stage(self) -> None:
        self._warm_up()
        while True:
            with self._cv:
                if not self._queue and not self._stop:
                    self._cv.wait(timeout=0.5)
                if self._stop:
                    return
                if not self._queue:
                    idle = True
                else:
                    idle = False
                    burst, arrival_ns = self._queue.popleft()
            if idle:
                try:
                    self.prepare_ahead()
                except Exception as exc:  # the worker must never die
                    self.unexpected += 1
                    self._log.error(f"preparing the calibration: unexpected {one_line(exc)}",
                                    throttle_duration_sec=10.0)
                continue
            made = self._attempt(burst, self._reconstruct, burst, arrival_ns)
            if made is not None:
                self._handoff.put(made)  # waits while the output stage is a burst behind

    def _output_stage(self) -> None:
        """The output thread: publish the reconstructed bursts in order until None."""
        while (made := self._handoff.get()) is not None:
            self._attempt(made.burst, self._deliver, made)

    def stop(self) -> None:
        """Make :meth:`run` return once the burst in hand is done."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()

    def _warm_up(self) -> None:
        """Compile or load the kernels before the first burst (bursts wait meanwhile)."""
        self._log.info("warming up the reconstruction kernels")
        try:
            warm = warm_up_kernels()
        except Exception as exc:  # the worker must never die: the first burst compiles them
            self.unexpected += 1
            self._log.error(f"warming up the kernels failed: {one_line(exc)}; the "
                            "first bursts compile them instead")
            return
        self.ready = True
        self._log.info(f"reconstruction ready: {warm.summary}")

    def process(self, burst: Burst, arrival_ns: int) -> None:
        """Reconstruct and publish one burst in the calling thread (both stages); whatever
        it raises is counted and logged."""
        made = self._attempt(burst, self._reconstruct, burst, arrival_ns)
        if made is not None:
            self._attempt(burst, self._deliver, made)

    def _attempt(self, burst: Burst, step: Callable[..., _T], *args: object) -> _T | None:
        """``step(*args)`` of a burst's stage; None once what it raised is counted and
        logged."""
        try:
            return step(*args)
        except Exception as exc:  # the worker must never die
            with self._count_lock:
                if isinstance(exc, IncompleteBurstError):
                    self.incomplete += 1
                    self._note(_BAD, burst, exc)
                elif isinstance(exc, NoFingerError):
                    self.failed += 1
                    self._note(_WARN, burst, exc)
                elif isinstance(exc, FingerpsError):
                    self.failed += 1
                    self._note(_BAD, burst, exc)
                else:
                    self.failed += 1
                    self.unexpected += 1
                    self._note(_BAD, burst, exc, unexpected=True)
            return None

    def prepare_ahead(self) -> None:
        """While idle: prepare the calibration in force for the camera seen on camera_info
        (so that its first burst does not pay for it); the bursts prepare it otherwise."""
        lights, camera = self.calibration.lights, self._camera
        if lights is None or camera is None or not camera.k[0] > 0:
            return
        shape = (int(camera.height), int(camera.width))
        settings = self._settings()
        limits = settings.limits
        if not (1 <= shape[0] <= limits.max_height and 1 <= shape[1] <= limits.max_width):
            return  # a camera_info of no size or beyond the bounds: its bursts will say so
        prepared = self.calibration.prepared
        try:
            count = prepared.count
            _, flat_used = self.calibration.prepare(
                lights, np.asarray(camera.k, dtype=np.float64).reshape(3, 3), shape,
                settings.options)
            if prepared.count != count:
                self._log.info(
                    f"calibration prepared for the {shape[1]}x{shape[0]} camera in "
                    f"{prepared.seconds * 1e3:.0f} ms"
                    + ("" if flat_used else " (no flat field)"))
        except FingerpsError as exc:  # the first burst will say it again, counted
            self._log.warning(f"calibration not prepared: {exc}", throttle_duration_sec=10.0)

    def _note(self, outcome: int, burst: Burst, exc: Exception, *,
              unexpected: bool = False) -> None:
        """One burst not reconstructed: remembered for the health level, logged in one
        line naming the burst and the problem (no traceback)."""
        problem = f"unexpected {one_line(exc)}" if unexpected else str(exc)
        self.last_error = f"burst {burst.burst_id}: {problem}"
        self.last_problem = self.last_error
        self._outcomes.append(outcome)
        if self._log_gate.opens(problem):
            self._log.error(self.last_error)

    def _reconstruct(self, burst: Burst, arrival_ns: int) -> _Made:
        """The first stage: the burst reconstructed with the calibration in force."""
        start_ns = time.time_ns()
        maps = self.calibration.flat_maps
        settings = self._settings()
        made = reconstruct_burst(
            burst, self.calibration, options=settings.options,
            mono16_full_scale=settings.mono16_full_scale, limits=settings.limits)
        outcome = _OK
        if maps is not None and not made.flat_field_used:
            outcome = _WARN
            self.flat_unused += 1
            self.last_problem = (f"burst {burst.burst_id}: flat field {maps.shape} does not "
                                 f"fit the images {made.images.shape}; not used")
            self._log.warning(self.last_problem, throttle_duration_sec=10.0)
        return _Made(burst, arrival_ns, start_ns, made, outcome, settings)

    def _deliver(self, item: _Made) -> None:
        """The second stage: a reconstructed burst's outputs built and handed to
        ``publish`` one by one (each published before the next is built), timed, counted,
        logged; a print that could not be made degrades the burst."""
        burst, made, outcome = item.burst, item.made, item.outcome
        unprinted: list[Burst] = []
        self._publish(self._outputs(made, burst, item.settings, unprinted))
        if unprinted:
            outcome = _WARN
        result = made.result
        self.stages.add(time_nanoseconds(burst.header.stamp), item.arrival_ns, item.start_ns,
                        result.timings_ms["total"], time.time_ns())
        with self._count_lock:
            self.done += 1
        self.last_error = ""
        self._outcomes.append(outcome)
        stages = ", ".join(f"{k} {v:.0f}" for k, v in result.timings_ms.items() if k != "total")
        self._log.info(
            f"burst {burst.burst_id}: {result.mask.sum()} px, "
            f"{result.timings_ms['total']:.0f} ms ({stages} ms)", throttle_duration_sec=2.0)

    def _outputs(self, made: BurstReconstruction, burst: Burst, settings: ReconSettings,
                 unprinted: list[Burst]) -> Iterator[Output]:
        """A burst's outputs, built as they are asked for: those of ``settings.wanted``,
        then the print if ``settings.fingerprint`` (``burst`` added to ``unprinted`` when it
        cannot be made)."""
        yield from output_messages(made.result, burst.header, settings.wanted)
        if settings.fingerprint:
            made_print = self.fingerprint(made, burst)
            if made_print is None:
                unprinted.append(burst)
            else:
                yield fingerprint_output(made_print.image, burst.header.stamp)

    def fingerprint(self, made: BurstReconstruction, burst: Burst) -> RolledPrint | None:
        """The burst's rolled print, timed and counted; None (logged, counted) when it
        cannot be made."""
        start = time.perf_counter()
        try:
            made_print = made.fingerprint()
        except RolledPrintError as exc:
            self.prints_rejected += 1
            self.last_print_problem = f"burst {burst.burst_id}: no fingerprint: {exc}"
            self.last_problem = self.last_print_problem
            self._log.warning(self.last_print_problem, throttle_duration_sec=5.0)
            return None
        self.print_ms.append((time.perf_counter() - start) * 1e3)
        self.prints_made += 1
        return made_print

    # ------------------------------------------------------------------ health
    def health(self) -> tuple[bytes, str]:
        """The diagnostic level and message: ERROR when every one of the last
        ``health_window`` bursts failed, WARN while one of them failed or did without the
        flat field, or a refused calibration was not replaced; OK otherwise."""
        outcomes = list(self._outcomes)
        bad = outcomes.count(_BAD)
        if outcomes and bad == len(outcomes) == self._outcomes.maxlen:
            return DiagnosticStatus.ERROR, (
                f"the last {bad} bursts all failed; last: {self.last_problem}")
        if self.calibration.refused:
            return DiagnosticStatus.WARN, "; ".join(
                f"{kind} refused: {reason}"
                for kind, reason in self.calibration.refused.items())
        if self.last_error:
            return DiagnosticStatus.WARN, self.last_error
        if any(o != _OK for o in outcomes):
            return DiagnosticStatus.WARN, (
                f"{len(outcomes) - outcomes.count(_OK)} of the last {len(outcomes)} bursts "
                f"failed or were degraded; last: {self.last_problem}")
        return DiagnosticStatus.OK, (
            "ok" if self.ready else "warming up: compiling or loading the solver kernels")
