"""Root exception of every fingerps package, and the one of the shared ROS plumbing.

``FingerpsReconError``, ``FingerpsCalibError`` and ``FingerpsDriverError`` derive from
`FingerpsError`, so a node that calls the science and converts messages catches one class.
"""


class FingerpsError(Exception):
    """Root of every fingerps exception; messages say what is wrong and what to do."""


class MessageError(FingerpsError, ValueError):
    """A ROS message that cannot be converted (size, encoding, fields), or an array that
    cannot become one."""
