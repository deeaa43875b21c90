"""Root exception of fingerps_calib."""


class FingerpsCalibError(Exception):
    """Base of every error fingerps_calib raises; the message says what to do."""
