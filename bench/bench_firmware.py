"""The LED board's firmware under simavr (ATmega328P at 16 MHz): reply times, the camera
trigger, bursts/s through it, flash and RAM.

Needs ``make firmware`` (``fingerps_driver.board.firmware_sim``). Figures:

- ``firmware.reply_us.<cmd>.median`` / ``.max``: from the request's last byte into the chip
  (its ``\\n`` on the simulated UART's receive line) to the reply's first byte (``!`` on
  its transmit line), in simulated time from the harness's trace, 40 requests of each
  command; the spec allows 10 ms.
- ``firmware.host_ms.<cmd>.median``: the same commands' round trips as the host sees them
  (``LedBoard``, wall clock: the pty, the simulated UART's bytes at 115200 baud, Python).
- ``firmware.trigger_delay_us`` / ``firmware.trigger_width_us``: after ``TRIG,100,50``,
  from each acknowledged LED switch to the trigger's rise, and the pulse's width (medians
  over 20 switches, simulated time).
- ``firmware.bursts_per_s``, ``firmware.burst_ms.median``: ``capture_burst`` of the
  simulated rig's 7 LEDs through the firmware (the simulated camera renders the mask the
  board acknowledged), 15 bursts back to back after a warm-up.
- ``firmware.flash_bytes``, ``firmware.ram_bytes``: ``avr-size`` of the firmware (of
  32 768 and 2 048).

Usage (tools/ros_env.sh sourced, after ``make firmware``): ``python bench/bench_firmware.py``.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fingerps_driver.board.firmware_sim import FirmwareSim, find_firmware
from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.simulation import RigConfig, SimulatedRig

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from bench_driver import timed_bursts
from board_trace import Trace, stopped_trace  # the tests' reader of the trace

REQUESTS = 40
SWITCHES = 20
BURSTS = 15
TRIGGER = (100, 50)  # delay, width (us)


COMMANDS = ("ping", "info", "leds", "level", "state", "off", "trig")


def _command(board: LedBoard, name: str) -> Callable[[int], object]:
    """Request number i of command ``name`` through ``board``."""
    return {
        "ping": lambda i: board.ping(),
        "info": lambda i: board.info(),
        "leds": lambda i: board.set_leds(1 << (i % 7)),
        "level": lambda i: board.set_level(i % 7, 255),
        "state": lambda i: board.state(),
        "off": lambda i: board.all_off(),
        "trig": lambda i: board.trigger(0, 0),
    }[name]


def _replies(trace: Trace, count: int) -> list[float]:
    """Microseconds from each of the trace's last ``count`` requests' end to its reply."""
    ends = trace.byte_times("uart_rx", ord("\n"))[-count:]
    starts = trace.byte_times("uart_tx", ord("!"))
    out = []
    for end in ends:
        following = [t for t in starts if t > end]
        out.append((following[0] - end) / 1e3)
    return out


def run() -> dict[str, float]:
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        # Reply times per command, each command in a trace of its own (simulated time).
        for name in COMMANDS:
            sim = FirmwareSim(str(Path(tmp) / "board"), vcd=str(Path(tmp) / f"{name}.vcd"))
            sim.start()
            host = []
            with LedBoard(sim.port) as board:
                command = _command(board, name)
                for i in range(REQUESTS):
                    t0 = time.perf_counter()
                    command(i)
                    host.append((time.perf_counter() - t0) * 1e3)
            chip = _replies(stopped_trace(sim), REQUESTS)
            figures[f"firmware.reply_us.{name}.median"] = float(np.median(chip))
            figures[f"firmware.reply_us.{name}.max"] = float(np.max(chip))
            figures[f"firmware.host_ms.{name}.median"] = float(np.median(host))
        # The trigger after each switch.
        sim = FirmwareSim(str(Path(tmp) / "board"), vcd=str(Path(tmp) / "trig.vcd"))
        sim.start()
        with LedBoard(sim.port) as board:
            board.trigger(*TRIGGER)
            for i in range(SWITCHES):
                board.set_leds(1 << (i % 7))
                time.sleep(0.002)  # longer than the pulse: one pulse a switch
            board.all_off()
        trace = stopped_trace(sim)
        switches = [t for t, _ in trace.switches()[1:-1]]  # after power-up, before OFF
        rises, falls = trace.edges("trig", 1), trace.edges("trig", 0)
        delays = [min(r for r in rises if r > s) - s for s in switches]
        widths = [min(f for f in falls if f > r) - r for r in rises]
        figures["firmware.trigger_delay_us"] = float(np.median(delays)) / 1e3
        figures["firmware.trigger_width_us"] = float(np.median(widths)) / 1e3
        # Bursts through the firmware with the simulated camera.
        rig = SimulatedRig(RigConfig())
        with FirmwareSim(str(Path(tmp) / "board")) as sim, LedBoard(sim.port) as board:
            durations, elapsed = timed_bursts(
                board, lambda: [k for k in range(rig.led_count)
                                if (board.acknowledged_mask or 0) >> k & 1],
                rig, np.random.default_rng(0), BURSTS)
        figures["firmware.bursts_per_s"] = BURSTS / elapsed
        figures["firmware.burst_ms.median"] = float(np.median(durations))
    size = subprocess.run(["avr-size", "--format=avr", "--mcu=atmega328p",
                           str(find_firmware().firmware)], capture_output=True, text=True,
                          check=True).stdout
    for line in size.splitlines():
        if line.startswith(("Program:", "Data:")):
            key = "firmware.flash_bytes" if line.startswith("Program:") else "firmware.ram_bytes"
            figures[key] = float(line.split()[1])
    return figures


if __name__ == "__main__":
    for key, value in run().items():
        print(f"  {key:<40} {value:10.3f}")
