"""Serial client of the LED board (pyserial), speaking ``board_protocol``.

Every command is one request/reply transaction. A dropped, late or corrupted reply (and
a ``CRC``/``FRAME`` error from the board) is recovered by discarding the input and
resending the command with a new sequence number, up to ``retries`` times; all commands
are idempotent, so a resend is safe even if the first attempt took effect.
"""

from __future__ import annotations

import errno
import termios
import time
from dataclasses import dataclass

import serial

from fingerps_driver.board.board_protocol import (
    MAX_LEDS,
    MAX_LEVEL,
    MAX_TRIGGER_US,
    REPLY_SIGIL,
    Command,
    ErrorCode,
    Reply,
    Request,
    decode_reply,
    encode_request,
    format_mask,
    next_seq,
    parse_mask,
    parse_uint,
)
from fingerps_driver.board.frame_reader import FrameReader
from fingerps_driver.device import Device
from fingerps_driver.errors import (
    BoardDisconnectedError,
    BoardError,
    BoardNotFoundError,
    BoardProtocolError,
    BoardRejectedError,
    BoardTimeoutError,
    BoardUnsupportedError,
    ProtocolError,
)


@dataclass(frozen=True)
class BoardInfo:
    """Answer to ``INFO``."""

    firmware: str
    led_count: int


@dataclass(frozen=True)
class LedState:
    """Answer to ``STATE``: the mask lit now and the drive level 0..255 of every LED."""

    mask: int
    levels: tuple[int, ...]


class _RetryableError(Exception):
    """One attempt failed in a way a resend may cure."""

    def __init__(self, error: type[BoardError], message: str) -> None:
        super().__init__(message)
        self.error = error


BAUDRATE = 115200
"""The serial line's default speed (the firmware's)."""
TIMEOUT_S = 0.05
"""How long one attempt waits for its reply by default, seconds."""
RETRIES = 2
"""Resends after a lost, late or garbled reply by default."""


class LedBoard(Device):
    """Client of the LED board on a serial port.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``/dev/ttyACM0`` or the emulator's ``/tmp/fingerps_board``.
    baudrate : int
        Line speed (ignored by USB-CDC boards and ptys).
    timeout_s : float
        How long one attempt waits for its reply.
    retries : int
        Resends after the first attempt (so ``1 + retries`` attempts at most).
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = BAUDRATE,
        timeout_s: float = TIMEOUT_S,
        retries: int = RETRIES,
    ) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        self._port = port
        self._baudrate = baudrate
        self._timeout_s = timeout_s
        self._retries = retries
        self._serial: serial.Serial | None = None
        self._reader: FrameReader | None = None
        self._seq = 0
        self._acknowledged: int | None = None
        self.resends = 0
        """Number of resends so far (diagnostics)."""

    @property
    def port(self) -> str:
        return self._port

    @property
    def acknowledged_mask(self) -> int | None:
        """The LED mask the board last acknowledged (``set_leds``/``all_off``); None when
        unknown (not open, just opened, or a switch failed)."""
        return self._acknowledged

    # -- lifecycle (``Device``) ------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def _acquire(self) -> None:
        """Open the port. Raises ``BoardNotFoundError`` if it does not exist."""
        try:
            ser = serial.Serial(
                self._port, baudrate=self._baudrate, timeout=0, write_timeout=self._timeout_s
            )
        except (serial.SerialException, OSError) as exc:
            code = getattr(exc, "errno", None)
            if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
                raise BoardNotFoundError(
                    f"LED board port {self._port} does not exist: plug the board in (or "
                    f"start `board_emulator --link {self._port}`) and check the port "
                    f"parameter"
                ) from exc
            if code in (errno.EACCES, errno.EPERM):
                raise BoardError(
                    f"no permission to open LED board port {self._port}: add the user to "
                    f"the 'dialout' group and log in again"
                ) from exc
            raise BoardDisconnectedError(
                f"cannot open LED board port {self._port} ({exc}); check the cable and "
                f"that no other program holds the port"
            ) from exc
        try:
            ser.reset_input_buffer()
        except (serial.SerialException, OSError, termios.error) as exc:
            ser.close()
            raise BoardDisconnectedError(
                f"LED board port {self._port} failed right after opening ({exc})"
            ) from exc
        self._serial = ser
        self._reader = FrameReader(ser.fileno(), ser.read, REPLY_SIGIL)

    def _release(self) -> None:
        """Close the port; never raises on a vanished port."""
        ser, self._serial, self._reader = self._serial, None, None
        self._acknowledged = None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError, termios.error):
                pass

    # -- commands --------------------------------------------------------------------

    def ping(self) -> float:
        """Round trip a ``PING``; return its duration in seconds (including retries)."""
        start = time.perf_counter()
        self._transact(Command.PING)
        return time.perf_counter() - start

    def info(self) -> BoardInfo:
        """Firmware token and LED count."""
        reply = self._transact(Command.INFO)
        if len(reply.values) != 2:
            raise BoardProtocolError(f"INFO reply {reply.values} is not <firmware>,<count>")
        return BoardInfo(reply.values[0], self._uint(reply.values[1], MAX_LEDS))

    def state(self) -> LedState:
        """Mask lit now and every LED's level."""
        reply = self._transact(Command.STATE)
        if not reply.values:
            raise BoardProtocolError("STATE reply holds no mask")
        levels = tuple(self._uint(v, MAX_LEVEL) for v in reply.values[1:])
        return LedState(self._mask(reply.values[0]), levels)

    def set_leds(self, mask: int) -> int:
        """Light exactly the LEDs in ``mask``; return the mask the board acknowledged.

        Raises ``BoardProtocolError`` if the acknowledged mask differs from ``mask``.
        """
        format_mask(mask)  # ValueError on a programming error
        self._acknowledged = None
        reply = self._transact(Command.LEDS, (mask,))
        acked = self._single_mask(reply)
        self._acknowledged = acked
        if acked != mask:
            raise BoardProtocolError(
                f"board lit LED mask {format_mask(acked)} instead of {format_mask(mask)}"
            )
        return acked

    def all_off(self) -> None:
        """Switch every LED off (acknowledged mask must be 0)."""
        self._acknowledged = None
        acked = self._single_mask(self._transact(Command.OFF))
        self._acknowledged = acked
        if acked != 0:
            raise BoardProtocolError(f"board reports LED mask {format_mask(acked)} after OFF")

    def set_level(self, index: int, level: int) -> None:
        """Set the drive level 0..255 of LED ``index`` (0-based)."""
        if not 0 <= level <= MAX_LEVEL:
            raise ValueError(f"level {level} outside 0..{MAX_LEVEL}")
        if not 0 <= index <= MAX_LEVEL:
            raise ValueError(f"LED index {index} outside 0..{MAX_LEVEL}")
        self._transact(Command.LEVEL, (index, level))

    def trigger(self, delay_us: int, width_us: int) -> None:
        """Set the camera trigger: after every ``set_leds`` the board's trigger output rises
        ``delay_us`` after the LEDs switched and stays high ``width_us`` (each 0..65535;
        the board may round them up to its timer's step). ``width_us`` 0 switches it off.

        Raises ``BoardUnsupportedError`` if the board's firmware has no trigger (it answers
        ``ERR,CMD``).
        """
        for name, value in (("delay_us", delay_us), ("width_us", width_us)):
            if not 0 <= value <= MAX_TRIGGER_US:
                raise ValueError(f"{name} {value} outside 0..{MAX_TRIGGER_US}")
        try:
            self._transact(Command.TRIG, (delay_us, width_us))
        except BoardRejectedError as exc:
            if exc.code is not ErrorCode.UNKNOWN_COMMAND:
                raise
            raise BoardUnsupportedError(
                f"the LED board on {self._port} has no camera trigger (it answered "
                f"TRIG with ERR,CMD: {exc}); flash the fingerps firmware "
                f"(docs/board_firmware.md) or leave the trigger off (width 0)",
                exc.code) from None

    # -- transport -------------------------------------------------------------------

    def _transact(self, command: Command, args: tuple[int, ...] = ()) -> Reply:
        ser, reader = self._serial, self._reader
        if ser is None or reader is None:
            raise BoardError(f"LED board port {self._port} is not open; call open() first")
        failure: _RetryableError | None = None
        for attempt in range(1 + self._retries):
            if attempt:
                self.resends += 1
            self._seq = next_seq(self._seq)
            request = Request(self._seq, command, args)
            try:
                reply = self._attempt(ser, reader, request)
            except _RetryableError as exc:
                failure = exc
                continue
            if reply.ok:
                return reply
            assert reply.error is not None
            if reply.error.retryable:
                failure = _RetryableError(
                    BoardProtocolError, f"board reported {reply.error.value}: {reply.message}"
                )
                continue
            raise BoardRejectedError(
                f"LED board rejected {command.value}{list(args) if args else ''}: "
                f"{reply.error.value} {reply.message}",
                reply.error,
            )
        assert failure is not None
        raise failure.error(
            f"LED board on {self._port} failed {command.value} after {1 + self._retries} "
            f"attempt(s), last: {failure}; check the cable and the board's power"
        )

    def _attempt(self, ser: serial.Serial, reader: FrameReader, request: Request) -> Reply:
        """Send once and wait for the matching reply; ``_RetryableError`` if a resend may help."""
        deadline = time.monotonic() + self._timeout_s
        try:
            ser.reset_input_buffer()
            reader.reset()
            ser.write(encode_request(request))
            for line in reader.lines(deadline=deadline):
                try:
                    reply = decode_reply(line)
                except ProtocolError as exc:
                    raise _RetryableError(BoardProtocolError, f"garbled reply: {exc}") from None
                if reply.seq == request.seq:
                    return reply
                # else: stale reply to an earlier attempt, keep waiting
            raise _RetryableError(BoardTimeoutError, f"no reply within {self._timeout_s} s")
        except serial.SerialTimeoutException as exc:
            raise _RetryableError(BoardTimeoutError, f"write timed out ({exc})") from None
        except (serial.SerialException, OSError, termios.error, ValueError) as exc:
            self.close()
            raise BoardDisconnectedError(
                f"LED board port {self._port} vanished ({_describe(exc)}); reconnect the "
                f"board, then open() again"
            ) from exc

    @staticmethod
    def _uint(token: str, maximum: int) -> int:
        try:
            return parse_uint(token, maximum=maximum)
        except ProtocolError as exc:
            raise BoardProtocolError(f"bad value in reply: {exc}") from None

    @staticmethod
    def _mask(token: str) -> int:
        try:
            return parse_mask(token)
        except ProtocolError as exc:
            raise BoardProtocolError(f"bad mask in reply: {exc}") from None

    def _single_mask(self, reply: Reply) -> int:
        if len(reply.values) != 1:
            raise BoardProtocolError(f"expected one mask in the reply, got {reply.values}")
        return self._mask(reply.values[0])


def _describe(exc: BaseException) -> str:
    """Readable text of an I/O exception (``termios.error`` prints as a bare tuple)."""
    if isinstance(exc, termios.error) and len(exc.args) == 2:
        return f"[Errno {exc.args[0]}] {exc.args[1]}"
    return str(exc) or type(exc).__name__
