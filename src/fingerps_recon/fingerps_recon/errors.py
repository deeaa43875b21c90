"""The errors of fingerps_recon: one root, `FingerpsReconError`, and what derives from it.

``except FingerpsReconError`` catches every error the package raises (and
``fingerps_ros.errors.FingerpsError`` those of every fingerps package); the classes below
let a caller tell the cases apart. Each message says what is wrong and what to do.

No ROS here: the science rooms (photometric, surface, scan) import this module.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from fingerps_ros.errors import FingerpsError

if TYPE_CHECKING:
    from fingerps_recon.sessions.mcap_records import DamagedRange
    from fingerps_recon.surface.rolled_print import PrintRejection


class FingerpsReconError(FingerpsError):
    """Base of every error fingerps_recon raises; the message says what to do."""


# --- reconstruction (photometric.pipeline, reconstruction/) ---------------------------------


class NoFingerError(FingerpsReconError):
    """The burst shows nothing to reconstruct (the finger mask selects nothing); raised by
    ``photometric.pipeline.reconstruct`` and ``reconstruct_prepared``."""


class IncompleteBurstError(FingerpsReconError):
    """A burst lacks a frame of some LED (it is never reconstructed); raised by
    ``reconstruction.burst_intake.burst_images``."""


class EmptyReconstructionError(FingerpsReconError):
    """A burst whose reconstruction has no valid normal or no point: not a done burst;
    raised by ``reconstruction.burst_reconstruction.reconstruct_burst``."""


# --- surface/ -------------------------------------------------------------------------------


class UnrollingError(FingerpsReconError):
    """The surface cannot be unrolled (too few nodes, no valid depth, bad options); raised
    by ``surface.surface_unrolling.unroll_surface`` and ``SurfaceUnrolling``."""


class RolledPrintError(FingerpsReconError):
    """No trustworthy print from this reconstruction; raised by
    ``surface.rolled_print.rolled_print``.

    Attributes
    ----------
    reason : PrintRejection
        Why: too small, too strained or too noisy.
    """

    def __init__(self, reason: PrintRejection, message: str) -> None:
        super().__init__(message)
        self.reason = reason


# --- records/ -------------------------------------------------------------------------------


class WsqError(FingerpsReconError):
    """A print that cannot be written as, or read from, a WSQ file; raised by
    ``records.wsq_image``."""


class RecordError(FingerpsReconError):
    """A print whose minutiae or exchange records cannot be made; raised by ``records``."""


# --- scan/ ----------------------------------------------------------------------------------


class ImpossibleGoalError(FingerpsReconError):
    """A Scan goal's values cannot be run; the message names each and what is allowed.
    Raised by ``scan.scan_settings.goal_settings``."""


class ScanAbortedError(FingerpsReconError):
    """A Scan goal cannot go on (timeout, no driver answer, a burst without the frames the
    scan needs); the message says why and what to do. Raised by ``scan.scan_sequence`` and
    the scan node's capture calls; the goal ends aborted."""


# --- sessions/ (bags) -----------------------------------------------------------------------


class RecorderError(FingerpsReconError):
    """The recorder cannot start with the parameters given (an unknown topic, no topic);
    raised by ``sessions.session_topics.choose_topics``."""


class MessageDefinitionError(FingerpsReconError):
    """A message type's full definition could not be found or assembled (a bad type name,
    a package not in the ament index, a type nesting itself); raised by
    ``sessions.message_definition``."""


class SessionBagError(FingerpsReconError):
    """A bag could not be created, written or finished; raised by
    ``sessions.session_bag.SessionBagWriter``."""


class BagSchemaError(FingerpsReconError):
    """The bag was recorded with another definition of one of our message types (or one
    not installed); raised by ``sessions.bag_reader.check_schema`` (``SessionBagReader``,
    before any message of that type is yielded)."""


class BagRecoveryError(FingerpsReconError):
    """A bag cannot be recovered or its pieces not listed (no MCAP file, a piece missing,
    destination taken, nothing readable); raised by ``sessions.bag_recovery.recover_bag``
    and ``bag_pieces`` (which ``SessionBagReader`` uses too)."""


class McapDamageError(FingerpsReconError):
    """The file is damaged; every intact record was read, ``offset`` is the first damage.
    Raised by ``sessions.mcap_records`` and ``sessions.bag_reader.SessionBagReader`` after
    the last intact message.

    Attributes
    ----------
    path : Path
        The file.
    offset : int
        Byte offset of the first damaged record (or of the bad magic: 0).
    reason : str
        What is wrong there.
    file_size : int
        Size of the file in bytes.
    damage : tuple[DamagedRange, ...]
        Every damaged range (empty for a file that is no MCAP at all); the first one's
        ``span_ns`` is the log-time range of the first damaged chunk when its header could
        still be read.
    """

    def __init__(self, path: Path, offset: int, reason: str, file_size: int,
                 damage: tuple[DamagedRange, ...] = ()) -> None:
        self.path = Path(path)
        self.offset = offset
        self.reason = reason
        self.file_size = file_size
        self.damage = damage
        more = ""
        if len(damage) > 1:
            more = f" (and {len(damage) - 1} more damaged ranges: " + "; ".join(
                d.describe() for d in damage[1:4]) + ("; ..." if len(damage) > 4 else "") + ")"
        what = ("every intact chunk was read" if damage
                else f"the records before offset {offset} are intact")
        super().__init__(
            f"{self.path}: damaged at byte offset {offset} of {file_size}: {reason}{more}; "
            f"{what} - 'bag_recover {self.path}' saves them into a valid bag and reports "
            "what was lost")
