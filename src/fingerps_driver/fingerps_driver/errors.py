"""The errors of fingerps_driver: one root, `FingerpsDriverError`, and what derives from it.

``except FingerpsDriverError`` catches every error the package raises (and
``fingerps_ros.errors.FingerpsError`` those of every fingerps package); the classes below
let a caller tell the cases apart. Each message says what is wrong and what to do.

No ROS here: the science rooms (board, cameras, capture, simulation) import this module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fingerps_ros.errors import FingerpsError

if TYPE_CHECKING:
    from fingerps_driver.board.board_protocol import ErrorCode


class FingerpsDriverError(FingerpsError):
    """Base of every error fingerps_driver raises; the message says what to do."""


# --- board/: the LED board, its protocol and its emulator -----------------------------------


class ProtocolError(FingerpsDriverError):
    """A line that is not a valid protocol message; raised by ``board.board_protocol``'s
    decoders (the client and the emulator answer it, it rarely reaches a caller).

    Attributes
    ----------
    code : ErrorCode
        What is wrong, as the board would report it.
    seq : int or None
        The sequence number read from the line, if it could be read at all.
    """

    def __init__(self, code: ErrorCode, message: str, *, seq: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.seq = seq


class BoardError(FingerpsDriverError):
    """Root of the LED board's errors (``board.led_board.LedBoard``,
    ``board.board_connection.BoardConnection``): catch it for any of those below."""


class BoardNotFoundError(BoardError):
    """The serial port does not exist (``LedBoard.open``)."""


class BoardDisconnectedError(BoardError):
    """The port vanished or failed while in use (cable pulled, board reset)."""


class BoardTimeoutError(BoardError):
    """No valid reply within the timeout, on every attempt."""


class BoardProtocolError(BoardError):
    """Replies were garbled on every attempt, or a reply made no sense."""


class BoardRejectedError(BoardError):
    """The board answered ERR (unknown command, bad argument, LED out of range).

    Attributes
    ----------
    code : ErrorCode
        The board's error code.
    """

    def __init__(self, message: str, code: ErrorCode) -> None:
        super().__init__(message)
        self.code = code


class BoardUnsupportedError(BoardRejectedError):
    """The board does not know a command (it answered ``ERR,CMD``): an older firmware, e.g.
    one without the camera trigger (``LedBoard.trigger``)."""


class WrongBoardError(BoardError):
    """The board answers but does not fit the configuration (too few LEDs); raised when
    ``board.board_connection.BoardConnection`` opens it (never waited for)."""


class BoardEmulatorError(FingerpsDriverError):
    """The board emulator (``board.board_emulator``) cannot do what was asked: started
    twice or not started, its link path or socket path taken, a control socket it cannot
    serve or reach, a control command refused."""


class FirmwareNotBuiltError(BoardEmulatorError):
    """The LED board's firmware or its simavr harness (``board.firmware_sim``) is not built:
    run ``make firmware``."""


# --- cameras/ -------------------------------------------------------------------------------


class CameraError(FingerpsDriverError):
    """The camera delivered no frame, or a frame of the wrong size or type; or it could not
    be opened or set up (``cameras.camera.Camera`` and its backends)."""


# --- the commands (demo, bringup) -----------------------------------------------------------


class DemoError(FingerpsDriverError):
    """The demo could not complete; the message says which step and what to do. Raised by
    ``demo``'s steps; its ``main`` prints it and exits 1."""


class BringupError(FingerpsDriverError):
    """Bringup cannot start (a missing or malformed parameter file, a node not built); the
    message names the problem and what to do. ``bringup``'s ``main`` prints it and exits 2."""
