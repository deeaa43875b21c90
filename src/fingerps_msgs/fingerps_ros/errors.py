"""Root exception of every fingerps package, and the errors of the shared ROS plumbing.

``FingerpsReconError``, ``FingerpsCalibError`` and ``FingerpsDriverError`` (each in its
package's ``errors.py``) derive from `FingerpsError`, so a node that calls the science and
converts messages catches one class.

No ROS here: the science rooms import it through their package's ``errors``.
"""


class FingerpsError(Exception):
    """Root of every fingerps exception; messages say what is wrong and what to do."""


class MessageError(FingerpsError, ValueError):
    """A ROS message that cannot be converted (size, encoding, fields), or an array that
    cannot become one."""


class PrivacySettingError(FingerpsError, ValueError):
    """FINGERPS_UMASK holds something that is not an octal umask; raised by
    ``fingerps_ros.privacy.apply_private_umask`` (a node or a tool then exits 2)."""
