"""Root exception of fingerps_driver."""

from fingerps_ros.errors import FingerpsError


class FingerpsDriverError(FingerpsError):
    """Base of every error fingerps_driver raises; the message says what to do."""
