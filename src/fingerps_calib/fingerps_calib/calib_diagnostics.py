"""calib_node's ``/diagnostics``: the service calls answered, and the calibration in force.

`ServiceCalls` counts the calls answered ok, refused and failed unexpectedly (with the last
error); `calibration_status` makes the DiagnosticStatus of the counts: level WARN while the
latest call was refused, ERROR if it failed unexpectedly, else OK.
"""

from __future__ import annotations

import threading

from diagnostic_msgs.msg import DiagnosticStatus

from fingerps_ros.diagnostics import key_values


def one_line(text: str) -> str:
    """``text`` on one line (exception texts can hold newlines), at most 500 characters."""
    line = " ".join(str(text).split())
    return line if len(line) <= 500 else line[:497] + "..."


class ServiceCalls:
    """Counts of the service calls answered (thread-safe), for /diagnostics."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._ok = self._refused = self._unexpected = 0
        self._last_error = ""
        self._last_refused = self._last_unexpected = False

    def count(self, service: str, error: str, *, unexpected: bool = False) -> None:
        """Count one answer; ``error`` empty for success."""
        with self._lock:
            if unexpected:
                self._unexpected += 1
            elif error:
                self._refused += 1
            else:
                self._ok += 1
            if error:
                self._last_error = f"{service}: {error}"
            self._last_refused = bool(error)
            self._last_unexpected = unexpected

    def snapshot(self) -> dict:
        """The counts now: ok, refused, unexpected, last_error, last_refused,
        last_unexpected."""
        with self._lock:
            return {"ok": self._ok, "refused": self._refused, "unexpected": self._unexpected,
                    "last_error": self._last_error, "last_refused": self._last_refused,
                    "last_unexpected": self._last_unexpected}


def calibration_status(name: str, calls: dict, *, lights_date: str,
                       flat_field_date: str) -> DiagnosticStatus:
    """The status ``<node>: calibration`` of ``calls`` (a `ServiceCalls.snapshot`) and the
    dates of the calibration in force ('' for none)."""
    status = DiagnosticStatus(name=f"{name}: calibration")
    if calls["last_unexpected"]:
        status.level = DiagnosticStatus.ERROR
    elif calls["last_refused"]:
        status.level = DiagnosticStatus.WARN
    else:
        status.level = DiagnosticStatus.OK
    status.message = (one_line(calls["last_error"]) if status.level != DiagnosticStatus.OK
                      else "ok")
    status.values = key_values({
        "calls_ok": str(calls["ok"]),
        "calls_refused": str(calls["refused"]),
        "calls_failed_unexpectedly": str(calls["unexpected"]),
        "last_error": one_line(calls["last_error"]),
        "lights_in_force": lights_date,
        "flat_field_in_force": flat_field_date,
    })
    return status
