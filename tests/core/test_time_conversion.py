"""Integer nanoseconds ↔ builtin_interfaces/Time."""

from __future__ import annotations

import pytest
from builtin_interfaces.msg import Time

from fingerps_ros.time_conversion import time_message, time_nanoseconds


def test_nanoseconds_split_into_seconds_and_nanoseconds():
    t = time_message(3_000_000_007)
    assert (t.sec, t.nanosec) == (3, 7)


@pytest.mark.parametrize("ns", [0, 999_999_999, 1_000_000_000, 1_764_633_600_123_456_789])
def test_round_trip(ns: int):
    assert time_nanoseconds(time_message(ns)) == ns


def test_a_message_reads_back_as_nanoseconds():
    assert time_nanoseconds(Time(sec=2, nanosec=5)) == 2_000_000_005
