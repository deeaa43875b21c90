"""Root exception of fingerps_recon."""

from fingerps_ros.errors import FingerpsError


class FingerpsReconError(FingerpsError):
    """Base of every error fingerps_recon raises; the message says what to do."""
