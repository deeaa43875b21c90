"""fingerps_driver.capture.capture_rate: whether continuous capture keeps the rate asked for."""

from __future__ import annotations

import pytest

from fingerps_driver.capture.capture_rate import CaptureRate


def _run(rate: float, period: float, seconds: float) -> CaptureRate:
    """A capture asked for ``rate`` bursts/s that delivers one every ``period`` s."""
    tracker = CaptureRate(window_s=5.0)
    tracker.set_rate(rate, 0.0)
    t = period
    while t <= seconds:
        tracker.captured(t)
        t += period
    return tracker


def test_a_capture_that_keeps_up_is_not_behind() -> None:
    report = _run(10.0, 0.1, 12.0).report(12.0)
    assert report.achieved == pytest.approx(10.0, abs=0.2) and not report.behind


def test_a_capture_slower_than_asked_is_reported() -> None:
    # Asked for 30 bursts/s, one burst every 60 ms (16.7/s): as the issue measured.
    report = _run(30.0, 0.06, 12.0).report(12.0)
    assert report.requested == 30.0
    assert report.achieved == pytest.approx(16.7, abs=0.3) and report.behind


def test_no_verdict_before_a_full_window_and_a_new_rate_restarts_it() -> None:
    tracker = _run(30.0, 0.06, 3.0)
    assert tracker.report(3.0).achieved is None and not tracker.report(3.0).behind
    tracker = _run(30.0, 0.06, 12.0)
    tracker.set_rate(5.0, 12.0)
    assert tracker.report(13.0).achieved is None
    tracker.set_rate(0.0, 20.0)  # continuous capture off: never behind
    assert not tracker.report(40.0).behind


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="window_s"):
        CaptureRate(window_s=0.0)
