"""The firmware simulator's trace (``board_sim --vcd``, ``traced_firmware_board``) read back,
for the board and driver tests: the LED, trigger and status pins and the UART bytes, each
change with its simulated time in nanoseconds.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from fingerps_driver.board.firmware_sim import FirmwareSim

LED_COUNT = 7
PERIOD_NS = 16_000
"""One PWM period of the firmware, the trigger's step."""


@dataclass(frozen=True)
class Trace:
    """A ``board_sim --vcd`` trace: each signal's changes as (time ns, value or None)."""

    changes: dict[str, list[tuple[int, int | None]]]

    @classmethod
    def read(cls, path: str | Path) -> Trace:
        units = {"s": 10**9, "ms": 10**6, "us": 10**3, "ns": 1}
        names: dict[str, str] = {}
        changes: dict[str, list[tuple[int, int | None]]] = defaultdict(list)
        scale, now = 1, 0
        for line in Path(path).read_text().splitlines():
            words = line.split()
            if not words:
                continue
            if words[0] == "$timescale":
                number = words[1].rstrip("abcdefghijklmnopqrstuvwxyz")
                scale = int(number) * units[words[1][len(number):]]
            elif words[0] == "$var":
                names[words[3]] = words[4]
            elif line[0] == "#":
                now = int(line[1:]) * scale
            elif line[0] == "b" and len(words) == 2 and words[1] in names:
                bits = words[0][1:]
                value = int(bits, 2) if set(bits) <= {"0", "1"} else None
                changes[names[words[1]]].append((now, value))
            elif line[0] in "01xz" and line[1:] in names:
                changes[names[line[1:]]].append((now, int(line[0]) if line[0] in "01" else None))
        return cls(dict(changes))

    def byte_times(self, signal_name: str, byte: int) -> list[int]:
        """When ``byte`` appeared on a UART signal (``uart_tx``, ``uart_rx``)."""
        return [t for t, value in self.changes.get(signal_name, []) if value == byte]

    def edges(self, signal_name: str, level: int) -> list[int]:
        """When a pin went to ``level`` (0 or 1) from another known level."""
        times, before = [], None
        for t, value in self.changes.get(signal_name, []):
            if value == level and before is not None and before != level:
                times.append(t)
            before = value
        return times

    def level_at(self, signal_name: str, t: int) -> int | None:
        value = None
        for when, level in self.changes.get(signal_name, []):
            if when > t:
                break
            value = level
        return value

    def masks(self) -> list[tuple[int, int]]:
        """(time, LED mask) at every change of the LED pins once all are known."""
        events = sorted(((t, led, value) for led in range(LED_COUNT)
                         for t, value in self.changes.get(f"led{led}", [])),
                        key=lambda event: event[0])  # stable: a pin's changes keep their order
        levels: dict[int, int | None] = dict.fromkeys(range(LED_COUNT))
        timeline: list[tuple[int, int]] = []
        for t, led, value in events:
            levels[led] = value
            if None in levels.values():
                continue
            mask = sum(1 << i for i, level in levels.items() if level)
            if timeline and timeline[-1][0] == t:
                timeline[-1] = (t, mask)
            elif not timeline or timeline[-1][1] != mask:
                timeline.append((t, mask))
        return timeline

    def switches(self, settle_ns: int = 2_000) -> list[tuple[int, int]]:
        """(time, mask) of every switch: a mask held ``settle_ns`` at least (the firmware
        writes PORTB, then PORTD 0.4 us later), stamped with the first edge of the switch."""
        timeline = self.masks()
        settled: list[tuple[int, int]] = []
        first_edge = None
        for i, (t, mask) in enumerate(timeline):
            first_edge = t if first_edge is None else first_edge
            end = timeline[i + 1][0] if i + 1 < len(timeline) else None
            if end is None or end - t >= settle_ns:
                if not settled or settled[-1][1] != mask:
                    settled.append((first_edge, mask))
                first_edge = None
        return settled

    def mask_at(self, t: int) -> int | None:
        mask = None
        for when, value in self.masks():
            if when > t:
                break
            mask = value
        return mask


def stopped_trace(sim: FirmwareSim) -> Trace:
    """Stop the simulator (it must exit cleanly: the trace is then complete) and read its
    trace."""
    assert sim.stop() == 0, "the firmware simulator did not stop cleanly"
    assert sim.vcd is not None, "the simulator traced nothing (use traced_firmware_board)"
    return Trace.read(sim.vcd)
