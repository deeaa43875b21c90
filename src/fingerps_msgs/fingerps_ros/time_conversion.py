"""Integer nanoseconds ↔ ``builtin_interfaces/Time`` (the cores keep times as int ns, as mcap
does; messages carry ``sec`` + ``nanosec``)."""

from __future__ import annotations

from builtin_interfaces.msg import Time

NS_PER_S = 1_000_000_000


def time_message(ns: int) -> Time:
    """A ``builtin_interfaces/Time`` of ``ns`` integer nanoseconds since the epoch (>= 0)."""
    sec, nanosec = divmod(int(ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def time_nanoseconds(stamp: Time) -> int:
    """``stamp`` (a ``builtin_interfaces/Time``) as integer nanoseconds since the epoch."""
    return stamp.sec * NS_PER_S + stamp.nanosec
