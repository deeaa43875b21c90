"""Root exception of fingerps_driver."""


class FingerpsDriverError(Exception):
    """Base of every error fingerps_driver raises; the message says what to do."""
