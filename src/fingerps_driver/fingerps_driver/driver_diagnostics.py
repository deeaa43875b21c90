"""The driver's /diagnostics: the board, the camera and the bursts, from the core's state.

Each builder takes the node's name (the statuses are named ``<node>: board`` and so on)
and returns one ``DiagnosticStatus``; the keys and values are what the README and the
tests read.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterable

from diagnostic_msgs.msg import DiagnosticStatus

from fingerps_driver.board.board_connection import BoardConnection, BoardState
from fingerps_driver.driver_core import DriverCore
from fingerps_ros.diagnostics import key_values


def driver_statuses(node_name: str, core: DriverCore,
                    compressed_failures: int) -> list[DiagnosticStatus]:
    """The board's, the camera's and the bursts' statuses, in that order."""
    return [board_status(node_name, core.board),
            camera_status(node_name, core, compressed_failures),
            burst_status(node_name, core)]


def board_status(node_name: str, board: BoardConnection) -> DiagnosticStatus:
    """Connection state, firmware and reconnect counters of the LED board."""
    led_board = board.led_board
    assert led_board is not None
    state = board.state
    status = DiagnosticStatus(name=f"{node_name}: board", hardware_id=led_board.port)
    if state is BoardState.CONNECTED:
        status.level = DiagnosticStatus.OK
        status.message = f"connected ({board.firmware})"
    else:
        status.level = (DiagnosticStatus.ERROR if state is BoardState.DISCONNECTED
                        else DiagnosticStatus.WARN)
        status.message = f"{state.value}: {board.error}; next attempt in {board.wait_s():.1f} s"
    status.values = key_values({
        "state": state.value,
        "port": led_board.port,
        "firmware": board.firmware,
        "resends": str(led_board.resends),
        "disconnects": str(board.disconnects),
        "reconnects": str(board.reconnects),
        "reconnect_attempts": str(board.reconnect_attempts),
        "last_board_error": board.error,
    })
    return status


def camera_status(node_name: str, core: DriverCore, compressed_failures: int) -> DiagnosticStatus:
    """Backend, device, size and failures of the camera; WARN if the last burst failed there."""
    camera, settings = core.camera, core.camera_settings
    assert camera is not None
    backend, device = settings.backend.value, settings.device_name
    status = DiagnosticStatus(name=f"{node_name}: camera", hardware_id=device or backend)
    c = core.counters
    camera_failed_last = c.last_burst_failed and c.camera_error == c.last_error
    status.level = DiagnosticStatus.WARN if camera_failed_last else DiagnosticStatus.OK
    status.message = (f"last burst failed at the camera: {c.camera_error}"
                      if camera_failed_last else "ok")
    status.values = key_values({
        "backend": backend,
        "device": device,
        "size": f"{camera.width}x{camera.height}",
        "encoding": camera.encoding,
        "frames": str(camera.frames_grabbed),
        "refused_settings": ", ".join(camera.refused_settings),
        "compressed_failures": str(compressed_failures),
        "calibration": core.calibration.current.source if core.calibration else "",
        "last_camera_error": c.camera_error,
    })
    return status


def _median_and_max(values: Iterable[float]) -> tuple[str, str]:
    values = list(values)
    if not values:
        return "", ""
    return f"{statistics.median(values):.2f}", f"{max(values):.2f}"


def burst_status(node_name: str, core: DriverCore) -> DiagnosticStatus:
    """Bursts taken and failed, their timing, and whether continuous capture keeps up."""
    c = core.counters
    status = DiagnosticStatus(name=f"{node_name}: bursts",
                              hardware_id=core.board.settings.port)
    status.level = DiagnosticStatus.WARN if c.last_burst_failed else DiagnosticStatus.OK
    status.message = f"last burst failed: {c.last_error}" if c.last_burst_failed else "ok"
    rate = core.capture_rate.report(time.monotonic())
    if rate.behind and not c.last_burst_failed:
        status.level = DiagnosticStatus.WARN
        status.message = (
            f"continuous capture delivers {rate.achieved:.1f} bursts/s of the "
            f"{rate.requested:g} asked for: a burst takes longer than 1/rate (see "
            "burst_ms_median and publish_ms_median); lower rate")
    burst_median, burst_max = _median_and_max(core.burst_ms)
    publish_median, publish_max = _median_and_max(core.publish_ms)
    status.values = key_values({
        "bursts_ok": str(c.ok),
        "bursts_failed": str(c.failed),
        "last_error": c.last_error,
        "last_burst_ms": f"{c.last_burst_ms:.1f}",
        "burst_ms_median": burst_median,
        "burst_ms_max": burst_max,
        "last_publish_ms": f"{c.last_publish_ms:.2f}",
        "publish_ms_median": publish_median,
        "publish_ms_max": publish_max,
        "timing_window": str(len(core.publish_ms)),
        "rate_requested": f"{rate.requested:g}",
        "rate_achieved": "" if rate.achieved is None else f"{rate.achieved:.2f}",
    })
    return status
