"""The driver's /diagnostics: the board, the camera and the bursts, from the core's state.

Each builder takes the node's name (the statuses are named ``<node>: board`` and so on)
and returns one ``DiagnosticStatus``; the keys and values are what the README and the
tests read.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterable

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from fingerps_driver.board.board_connection import BoardConnection, BoardState
from fingerps_driver.driver_core import DriverCore


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
    status.values = [
        KeyValue(key="state", value=state.value),
        KeyValue(key="port", value=led_board.port),
        KeyValue(key="firmware", value=board.firmware),
        KeyValue(key="resends", value=str(led_board.resends)),
        KeyValue(key="disconnects", value=str(board.disconnects)),
        KeyValue(key="reconnects", value=str(board.reconnects)),
        KeyValue(key="reconnect_attempts", value=str(board.reconnect_attempts)),
        KeyValue(key="last_board_error", value=board.error),
    ]
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
    status.values = [
        KeyValue(key="backend", value=backend),
        KeyValue(key="device", value=device),
        KeyValue(key="size", value=f"{camera.width}x{camera.height}"),
        KeyValue(key="encoding", value=camera.encoding),
        KeyValue(key="frames", value=str(camera.frames_grabbed)),
        KeyValue(key="refused_settings", value=", ".join(camera.refused_settings)),
        KeyValue(key="compressed_failures", value=str(compressed_failures)),
        KeyValue(key="calibration",
                 value=core.calibration.current.source if core.calibration else ""),
        KeyValue(key="last_camera_error", value=c.camera_error),
    ]
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
    status.values = [
        KeyValue(key="bursts_ok", value=str(c.ok)),
        KeyValue(key="bursts_failed", value=str(c.failed)),
        KeyValue(key="last_error", value=c.last_error),
        KeyValue(key="last_burst_ms", value=f"{c.last_burst_ms:.1f}"),
        KeyValue(key="burst_ms_median", value=burst_median),
        KeyValue(key="burst_ms_max", value=burst_max),
        KeyValue(key="last_publish_ms", value=f"{c.last_publish_ms:.2f}"),
        KeyValue(key="publish_ms_median", value=publish_median),
        KeyValue(key="publish_ms_max", value=publish_max),
        KeyValue(key="timing_window", value=str(len(core.publish_ms))),
        KeyValue(key="rate_requested", value=f"{rate.requested:g}"),
        KeyValue(key="rate_achieved",
                 value="" if rate.achieved is None else f"{rate.achieved:.2f}"),
    ]
    return status
