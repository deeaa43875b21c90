"""The errors of fingerps_calib: one root, `FingerpsCalibError`.

Every error the package raises is a ``FingerpsCalibError`` whose message says what is wrong
and what to do (a failed calibration check, a bad saved file, a bad camera_info URL); no
subclass needs telling apart. ``fingerps_ros.errors.FingerpsError`` catches those of every
fingerps package.
"""

from fingerps_ros.errors import FingerpsError


class FingerpsCalibError(FingerpsError):
    """Base of every error fingerps_calib raises; the message says what to do."""
