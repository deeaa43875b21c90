"""Tests of fingerps_calib.calib_diagnostics: calib_node's call counts and its status."""

from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticStatus

from fingerps_calib.calib_diagnostics import ServiceCalls, calibration_status, one_line


def _values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_counts_and_levels():
    calls = ServiceCalls()
    status = calibration_status("calib", calls.snapshot(), lights_date="", flat_field_date="")
    assert (status.name, status.level, status.message) == ("calib: calibration",
                                                           DiagnosticStatus.OK, "ok")
    assert _values(status) == {
        "calls_ok": "0", "calls_refused": "0", "calls_failed_unexpectedly": "0",
        "last_error": "", "lights_in_force": "", "flat_field_in_force": ""}

    calls.count("calibrate_lights", "")
    calls.count("calibrate_flat_field", "frames are 4x4 px;\nsend full frames")
    status = calibration_status("calib", calls.snapshot(), lights_date="2025-05-01T09:30:12Z",
                                flat_field_date="")
    assert status.level == DiagnosticStatus.WARN
    assert status.message == "calibrate_flat_field: frames are 4x4 px; send full frames"
    values = _values(status)
    assert (values["calls_ok"], values["calls_refused"]) == ("1", "1")
    assert values["lights_in_force"] == "2025-05-01T09:30:12Z"

    calls.count("calibrate_lights", "calibrate_lights failed unexpectedly", unexpected=True)
    snapshot = calls.snapshot()
    assert snapshot["unexpected"] == 1 and snapshot["last_unexpected"]
    assert calibration_status("calib", snapshot, lights_date="",
                              flat_field_date="").level == DiagnosticStatus.ERROR

    calls.count("calibrate_lights", "")
    status = calibration_status("calib", calls.snapshot(), lights_date="", flat_field_date="")
    assert status.level == DiagnosticStatus.OK and status.message == "ok"
    assert _values(status)["last_error"] == (
        "calibrate_lights: calibrate_lights failed unexpectedly")  # the last one is kept


def test_one_line():
    assert one_line("a\nb  c\t d") == "a b c d"
    long = one_line("x" * 600)
    assert len(long) == 500 and long.endswith("...")
