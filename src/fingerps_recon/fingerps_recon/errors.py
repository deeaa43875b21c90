"""Root exception of fingerps_recon."""


class FingerpsReconError(Exception):
    """Base of every error fingerps_recon raises; the message says what to do."""
