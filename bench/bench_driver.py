"""Burst capture on the simulated rig through the serial path (board emulator on a pty).

Median and worst burst capture time over 30 bursts (after a warm-up that fills the
simulated rig's render cache), and the sustained rate of back-to-back bursts. No ROS:
this is the capture path the driver node calls; publishing is measured end to end. Its
parts: the median ``set_leds`` round trip over the pty (``driver.set_leds_ms.median``, 300
switches) and the median render of one frame from the filled cache
(``driver.render_ms.median``, 35 frames).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np

from fingerps_driver.board.board_emulator import BoardEmulator
from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.cameras.camera import SimulatedCamera
from fingerps_driver.capture.burst import capture_burst
from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig

BURSTS = 30
SWITCHES = 300
RENDERS = 35


def timed_bursts(board: LedBoard, lit_leds: Callable[[], Sequence[int]], rig: SimulatedRig,
                 rng: np.random.Generator, bursts: int = BURSTS) -> tuple[list[float], float]:
    """``capture_burst`` of the rig's LEDs through ``board`` with the simulated camera
    (rendering the LEDs ``lit_leds()`` says are lit), after a warm-up that fills the render
    cache: each burst's duration (ms) and the seconds the ``bursts`` took back to back."""
    camera = SimulatedCamera(lambda lit: rig.render(Scene.FINGER, list(lit), rng=rng),
                             lit_leds, width=rig.camera.width, height=rig.camera.height)
    camera.open()
    try:
        kwargs = dict(led_order=range(rig.led_count), exposures_s=0.01, levels=1.0,
                      expected_shape=(rig.camera.height, rig.camera.width))
        capture_burst(board, camera, burst_id=0, **kwargs)  # warm-up: fills the cache
        durations = []
        start = time.perf_counter()
        for i in range(bursts):
            result = capture_burst(board, camera, burst_id=i + 1, **kwargs)
            if not result.ok:
                raise RuntimeError(result.reason)
            durations.append(result.duration_s * 1e3)
        return durations, time.perf_counter() - start
    finally:
        camera.close()


def run() -> dict[str, float]:
    rig = SimulatedRig(RigConfig())
    rng = np.random.default_rng(0)
    with BoardEmulator(rig.led_count) as emulator, LedBoard(emulator.port) as board:
        durations, elapsed = timed_bursts(board, emulator.lit_leds, rig, rng)
        switches = []
        for i in range(SWITCHES):
            t0 = time.perf_counter()
            board.set_leds(1 << (i % rig.led_count))
            switches.append((time.perf_counter() - t0) * 1e3)
        board.all_off()
    renders = []
    for i in range(RENDERS):
        t0 = time.perf_counter()
        rig.render(Scene.FINGER, [i % rig.led_count], rng=rng)
        renders.append((time.perf_counter() - t0) * 1e3)
    return {
        "driver.burst_ms.median": float(np.median(durations)),
        "driver.burst_ms.max": float(np.max(durations)),
        "driver.bursts_per_s": BURSTS / elapsed,
        "driver.set_leds_ms.median": float(np.median(switches)),
        "driver.render_ms.median": float(np.median(renders)),
    }
