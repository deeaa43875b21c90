"""Root exception of fingerps_calib."""

from fingerps_ros.errors import FingerpsError


class FingerpsCalibError(FingerpsError):
    """Base of every error fingerps_calib raises; the message says what to do."""
