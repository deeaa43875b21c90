"""Wire protocol of the fingerps LED board: pure encoding and decoding, no I/O.

Protocol specification
======================

Transport: a serial line (USB-CDC or UART, 115200 8N1, no flow control). ASCII only,
one message a line, every line ends with ``\\n`` (a ``\\r`` before it is tolerated).
The host sends requests; the board answers each request it could read with exactly one
reply. The board never speaks unasked.

Frames::

    request   #<seq>,<CMD>[,<arg>]...*<crc>\\n
    reply     !<seq>,OK[,<value>]...*<crc>\\n
    error     !<seq>,ERR,<code>,<text>*<crc>\\n

- ``<seq>``: sequence number, decimal 0..255 (no sign, at most 3 digits). The host uses
  a new one for every line it sends, including a resend, counting 255 -> 0; the board
  echoes it. A reply whose seq is not the one the host waits for is stale (the late
  answer to an earlier attempt) and is discarded.
- ``<crc>``: CRC-8/SMBUS (polynomial 0x07, init 0x00, not reflected, no final xor;
  check value 0xF4 for ``123456789``) over the bytes strictly between the sigil
  (``#`` / ``!``) and ``*``, written as two hex digits (sent upper case, either case
  accepted).
- Fields are separated by ``,`` and contain printable ASCII without ``, * # !``.
- Hex masks: bit i set = LED i lit, 1..8 hex digits, sent upper case and at least two
  digits wide (``05``). Other numbers are decimal.
- A line is at most 255 bytes. A receiver drops bytes before a sigil, restarts the line
  when a sigil arrives mid-line, and drops an overlong line.

Commands (all idempotent, so resending one is always safe)::

    request              reply                        effect
    PING                 OK                           none
    INFO                 OK,<firmware>,<led_count>    none
    LEDS,<hexmask>       OK,<hexmask now lit>         exactly the LEDs in the mask on,
                                                      all others off
    OFF                  OK,00                        all LEDs off
    LEVEL,<idx>,<level>  OK                           drive level 0..255 of LED idx
                                                      (0-based; default 255), applies
                                                      at once if the LED is lit
    STATE                OK,<hexmask>,<lvl0>,...      none; the mask lit now and the
                                                      level of every LED
    TRIG,<delay>,<width> OK                           camera trigger pulse after every
                                                      LEDS: delay and width in us,
                                                      0..65535; width 0 = off (default)

The board acknowledges ``LEDS``/``OFF`` only once the LEDs are switched, so the host may
start an exposure as soon as the reply has arrived.

Camera trigger (``TRIG``, an addition: a board without a trigger output answers it
``ERR,CMD``, so the host can tell). After ``TRIG,<delay_us>,<width_us>`` with a width
above 0, every acknowledged ``LEDS`` request (any mask, ``00`` included: a dark frame)
makes the board's trigger output rise ``delay_us`` after the LEDs switched and stay high
``width_us``; the board may round both up to its timer's step (the AVR firmware: whole
16 us PWM periods). A new ``LEDS`` restarts the pulse; ``OFF`` and the host-silence
switch-off (below) cancel one under way, ``LEVEL`` does not. ``TRIG`` itself switches
nothing; sent while a pulse is under way it may change that pulse (the AVR firmware takes
the new width if the pulse has not risen yet). The setting is kept until the next ``TRIG``
or a reset; at power-up and after a reset the trigger is off (width 0, delay 0). The
``LEDS`` reply does not wait for the pulse. Errors as for
``LEVEL``: ``ARG`` for a wrong argument count or a number that is not decimal 0..65535.

Host silence: a board may switch every LED off when no request line it answered has come
for a while, so that a crashed host does not leave an LED burning (the AVR firmware: 2 s;
a host that keeps LEDs lit longer sends ``PING`` or ``STATE`` now and then). The emulator
does not.

Error codes (``ERR,<code>,<text>``; the text is for humans):

- ``CRC``: checksum mismatch. The host resends with a new seq.
- ``FRAME``: malformed line (bad seq, empty field, bad character). The host resends.
- ``CMD``: unknown command.
- ``ARG``: wrong number of arguments or an unparsable/invalid value (level > 255, a
  trigger time > 65535).
- ``RANGE``: LED index or mask bit beyond the board's LED count.

A request the board cannot attribute to a seq (garbled beyond the seq field) gets no
reply; the host times out and resends.

Timeouts: the board answers within 10 ms (a real firmware's budget; the pty emulator
answers in well under 1 ms). The host waits ``timeout_s`` (default 50 ms) per attempt and
makes ``1 + retries`` attempts (default 3): on a timeout, a corrupted reply (bad
checksum or framing) or a ``CRC``/``FRAME`` error it discards its input and resends the
same command with a new seq. ``CMD``, ``ARG`` and ``RANGE`` errors are not retried.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from enum import Enum
from typing import TypeVar

from fingerps_driver.errors import ProtocolError

REQUEST_SIGIL = b"#"
REPLY_SIGIL = b"!"
MAX_LINE_BYTES = 255
MAX_LEDS = 32
LED_COUNT = 7
"""LEDs of the rig's board (the firmware's, the emulator's and the driver's default)."""
SEQ_MODULO = 256
MAX_LEVEL = 255
MAX_TRIGGER_US = 65535
_FORBIDDEN = frozenset(",*#!")
_HEX_DIGITS = frozenset("0123456789abcdefABCDEF")
_E = TypeVar("_E", bound=Enum)


class Command(Enum):
    """Request commands understood by the board."""

    PING = "PING"
    INFO = "INFO"
    LEDS = "LEDS"
    OFF = "OFF"
    LEVEL = "LEVEL"
    STATE = "STATE"
    TRIG = "TRIG"

    @property
    def arg_count(self) -> int:
        """Arguments the command takes: ``LEDS`` a mask, ``LEVEL`` an index and a level,
        ``TRIG`` a delay and a width."""
        return _ARG_COUNT.get(self, 0)

    @property
    def arg_maximum(self) -> int:
        """Largest value of a decimal argument (``LEVEL``: 255, ``TRIG``: 65535 us)."""
        return MAX_TRIGGER_US if self is Command.TRIG else MAX_LEVEL


_ARG_COUNT = {Command.LEDS: 1, Command.LEVEL: 2, Command.TRIG: 2}


class ErrorCode(Enum):
    """Error codes of an ``ERR`` reply (the value is the wire token)."""

    BAD_CHECKSUM = "CRC"
    BAD_FRAME = "FRAME"
    UNKNOWN_COMMAND = "CMD"
    BAD_ARGUMENT = "ARG"
    OUT_OF_RANGE = "RANGE"

    @property
    def retryable(self) -> bool:
        """True if the error means the request was garbled in transit (resend it)."""
        return self in (ErrorCode.BAD_CHECKSUM, ErrorCode.BAD_FRAME)


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS (poly 0x07, init 0x00, no reflection, no final xor) of ``data``."""
    crc = 0
    for byte in data:
        crc = _CRC_TABLE[crc ^ byte]
    return crc


def _make_crc_table() -> tuple[int, ...]:
    table = []
    for value in range(256):
        crc = value
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def next_seq(seq: int) -> int:
    """The sequence number after ``seq`` (255 wraps to 0)."""
    return (seq + 1) % SEQ_MODULO


def format_mask(mask: int) -> str:
    """Hex mask token: upper case, at least two digits (``5`` -> ``"05"``)."""
    if not 0 <= mask < 1 << MAX_LEDS:
        raise ValueError(f"LED mask {mask!r} outside 0..2**{MAX_LEDS}-1")
    return f"{mask:02X}"


def parse_mask(token: str) -> int:
    """Parse a hex mask token; raises ``ProtocolError`` (``ARG``) if it is not one."""
    if not 1 <= len(token) <= MAX_LEDS // 4 or not set(token) <= _HEX_DIGITS:
        raise ProtocolError(ErrorCode.BAD_ARGUMENT, f"bad hex mask {token!r}")
    return int(token, 16)


def parse_uint(token: str, *, maximum: int) -> int:
    """Parse a decimal 0..maximum token; raises ``ProtocolError`` (``ARG``) otherwise."""
    if not 1 <= len(token) <= 10 or not token.isdigit() or not token.isascii():
        raise ProtocolError(ErrorCode.BAD_ARGUMENT, f"bad number {token!r}")
    value = int(token)
    if value > maximum:
        raise ProtocolError(ErrorCode.BAD_ARGUMENT, f"{value} exceeds {maximum}")
    return value


def mask_to_indices(mask: int) -> tuple[int, ...]:
    """Indices of the set bits of ``mask``, ascending (``0b101`` -> ``(0, 2)``)."""
    if mask < 0:
        raise ValueError(f"LED mask {mask} is negative")
    return tuple(i for i in range(mask.bit_length()) if mask >> i & 1)


def indices_to_mask(indices: tuple[int, ...] | list[int]) -> int:
    """Mask with the bits of ``indices`` set (``(0, 2)`` -> ``0b101``)."""
    mask = 0
    for i in indices:
        if not 0 <= i < MAX_LEDS:
            raise ValueError(f"LED index {i} outside 0..{MAX_LEDS - 1}")
        mask |= 1 << i
    return mask


def _check_seq(seq: int) -> None:
    if not isinstance(seq, int) or not 0 <= seq < SEQ_MODULO:
        raise ValueError(f"seq {seq!r} outside 0..{SEQ_MODULO - 1}")


def _check_field(field: str) -> None:
    if not field or not field.isascii() or not field.isprintable() or _FORBIDDEN & set(field):
        raise ValueError(f"field {field!r} is empty or holds a character not allowed on the wire")


def sanitize_text(text: str, *, limit: int = 60) -> str:
    """Make ``text`` a valid error-text field: printable ASCII without ``, * # !``."""
    cleaned = "".join(
        c if c.isascii() and c.isprintable() and c not in _FORBIDDEN else " " for c in text
    ).strip()[:limit]
    return cleaned or "-"


@dataclass(frozen=True)
class Request:
    """One host -> board request.

    ``args`` are integers: ``LEDS`` takes ``(mask,)``, ``LEVEL`` takes ``(index, level)``,
    ``TRIG`` takes ``(delay_us, width_us)``, the others none. Invalid values raise
    ``ValueError`` (a programming error).
    """

    seq: int
    command: Command
    args: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        _check_seq(self.seq)
        if not isinstance(self.command, Command):
            raise ValueError(f"command {self.command!r} is not a Command")
        if len(self.args) != self.command.arg_count:
            raise ValueError(
                f"{self.command.value} takes {self.command.arg_count} argument(s), "
                f"got {len(self.args)}"
            )
        if self.command is Command.LEDS:
            format_mask(self.args[0])
        elif self.command is Command.LEVEL:
            index, level = self.args
            if not 0 <= index <= MAX_LEVEL:
                raise ValueError(f"LED index {index} outside 0..{MAX_LEVEL}")
            if not 0 <= level <= MAX_LEVEL:
                raise ValueError(f"level {level} outside 0..{MAX_LEVEL}")
        elif self.command is Command.TRIG:
            for name, value in zip(("delay", "width"), self.args, strict=True):
                if not 0 <= value <= MAX_TRIGGER_US:
                    raise ValueError(f"trigger {name} {value} us outside 0..{MAX_TRIGGER_US}")


@dataclass(frozen=True)
class Reply:
    """One board -> host reply: ``OK`` with ``values``, or ``ERR`` with ``error``/``message``.

    ``values`` stay strings; their meaning depends on the command (see the module spec).
    """

    seq: int
    values: tuple[str, ...] = ()
    error: ErrorCode | None = None
    message: str = ""

    def __post_init__(self) -> None:
        _check_seq(self.seq)
        for value in self.values:
            _check_field(value)
        if self.error is None:
            if self.message:
                raise ValueError("an OK reply carries no message")
        else:
            if self.values:
                raise ValueError("an ERR reply carries no values")
            _check_field(self.message)

    @property
    def ok(self) -> bool:
        """True for an ``OK`` reply."""
        return self.error is None

    @classmethod
    def failure(cls, seq: int, code: ErrorCode, text: str) -> Reply:
        """An ``ERR`` reply; ``text`` is sanitised to a valid field."""
        return cls(seq, error=code, message=sanitize_text(text))


def _frame(sigil: bytes, body: str) -> bytes:
    raw = body.encode("ascii")
    line = sigil + raw + b"*" + f"{crc8(raw):02X}".encode("ascii") + b"\n"
    if len(line) > MAX_LINE_BYTES:
        raise ValueError(f"message of {len(line)} bytes exceeds {MAX_LINE_BYTES}")
    return line


def encode_request(request: Request) -> bytes:
    """Encode ``request`` as one wire line (with checksum and newline)."""
    fields = [str(request.seq), request.command.value]
    if request.command is Command.LEDS:
        fields.append(format_mask(request.args[0]))
    else:
        fields.extend(str(a) for a in request.args)
    return _frame(REQUEST_SIGIL, ",".join(fields))


def encode_reply(reply: Reply) -> bytes:
    """Encode ``reply`` as one wire line (with checksum and newline)."""
    if reply.error is None:
        fields = [str(reply.seq), "OK", *reply.values]
    else:
        fields = [str(reply.seq), "ERR", reply.error.value, reply.message]
    return _frame(REPLY_SIGIL, ",".join(fields))


def _unframe(line: bytes, sigil: bytes) -> tuple[int, list[str]]:
    """Check sigil, characters and checksum; return (seq, fields after the seq)."""
    if line.endswith(b"\n"):
        line = line[:-1]
    if line.endswith(b"\r"):
        line = line[:-1]
    if len(line) > MAX_LINE_BYTES:
        raise ProtocolError(ErrorCode.BAD_FRAME, f"line of {len(line)} bytes is too long")
    if not line.startswith(sigil):
        raise ProtocolError(ErrorCode.BAD_FRAME, f"line {line[:20]!r} lacks the sigil {sigil!r}")
    try:
        text = line[1:].decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(ErrorCode.BAD_FRAME, f"non-ASCII byte in {line[:40]!r}") from None
    body, star, crc_text = text.rpartition("*")
    fields = body.split(",")
    seq = _read_seq(fields[0])
    if not star or len(crc_text) != 2 or not set(crc_text) <= _HEX_DIGITS:
        raise ProtocolError(ErrorCode.BAD_FRAME, f"no *<crc> at the end of {line!r}", seq=seq)
    if int(crc_text, 16) != crc8(body.encode("ascii")):
        raise ProtocolError(ErrorCode.BAD_CHECKSUM, f"checksum mismatch in {line!r}", seq=seq)
    if seq is None:
        raise ProtocolError(ErrorCode.BAD_FRAME, f"bad sequence number in {line!r}")
    for field in fields[1:]:
        try:
            _check_field(field)
        except ValueError as exc:
            raise ProtocolError(ErrorCode.BAD_FRAME, f"{exc} in {line!r}", seq=seq) from None
    return seq, fields[1:]


def _token(kind: type[_E], token: str, code: ErrorCode, what: str, seq: int) -> _E:
    """The member of ``kind`` spelt ``token``; else ``ProtocolError`` ``code``, "unknown ..."."""
    try:
        return kind(token)
    except ValueError:
        raise ProtocolError(code, f"unknown {what} {token!r}", seq=seq) from None


def _read_seq(token: str) -> int | None:
    if 1 <= len(token) <= 3 and token.isascii() and token.isdigit() and int(token) < SEQ_MODULO:
        return int(token)
    return None


def decode_request(line: bytes, *,
                   commands: Collection[Command] = tuple(Command)) -> Request:
    """Decode one request line (trailing newline optional).

    ``commands`` are those the board knows (default all); any other is ``CMD``, as for an
    older board without ``TRIG``.

    Raises
    ------
    ProtocolError
        With the ``ErrorCode`` the board should answer and, if readable, the seq.
    """
    seq, fields = _unframe(line, REQUEST_SIGIL)
    if not fields:
        raise ProtocolError(ErrorCode.BAD_FRAME, "request without a command", seq=seq)
    command = _token(Command, fields[0], ErrorCode.UNKNOWN_COMMAND, "command", seq)
    if command not in commands:
        raise ProtocolError(ErrorCode.UNKNOWN_COMMAND, f"unknown command {fields[0]!r}",
                            seq=seq)
    tokens = fields[1:]
    if len(tokens) != command.arg_count:
        raise ProtocolError(
            ErrorCode.BAD_ARGUMENT,
            f"{command.value} takes {command.arg_count} argument(s), got {len(tokens)}",
            seq=seq,
        )
    try:
        if command is Command.LEDS:
            args: tuple[int, ...] = (parse_mask(tokens[0]),)
        else:
            args = tuple(parse_uint(t, maximum=command.arg_maximum) for t in tokens)
        return Request(seq, command, args)
    except ProtocolError as exc:
        raise ProtocolError(exc.code, str(exc), seq=seq) from None
    except ValueError as exc:
        raise ProtocolError(ErrorCode.BAD_ARGUMENT, str(exc), seq=seq) from None


def decode_reply(line: bytes) -> Reply:
    """Decode one reply line (trailing newline optional).

    Raises
    ------
    ProtocolError
        If the line is garbled: bad framing, checksum, status or error code.
    """
    seq, fields = _unframe(line, REPLY_SIGIL)
    if fields and fields[0] == "OK":
        return Reply(seq, tuple(fields[1:]))
    if len(fields) == 3 and fields[0] == "ERR":
        code = _token(ErrorCode, fields[1], ErrorCode.BAD_FRAME, "error code", seq)
        return Reply(seq, error=code, message=fields[2])
    raise ProtocolError(ErrorCode.BAD_FRAME, "reply status is not OK or ERR,<code>,<text>", seq=seq)


class LineFramer:
    """Splits a byte stream into protocol lines starting with ``sigil``.

    Bytes before a sigil are dropped, a sigil mid-line restarts the line, a line longer
    than ``MAX_LINE_BYTES`` is dropped. ``feed`` returns the complete lines (sigil included,
    newline excluded); ``dropped`` counts the discarded bytes.
    """

    def __init__(self, sigil: bytes) -> None:
        if len(sigil) != 1:
            raise ValueError("sigil must be one byte")
        self._sigil = sigil[0]
        self._line = bytearray()
        self._in_line = False
        self.dropped = 0

    def reset(self) -> None:
        """Forget any partial line."""
        self.dropped += len(self._line)
        self._line.clear()
        self._in_line = False

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the lines completed by them."""
        lines = []
        for byte in data:
            if byte == self._sigil:
                self.dropped += len(self._line)
                self._line = bytearray((byte,))
                self._in_line = True
            elif not self._in_line:
                self.dropped += 1
            elif byte == 0x0A:
                lines.append(bytes(self._line))
                self._line.clear()
                self._in_line = False
            elif len(self._line) >= MAX_LINE_BYTES:
                self.reset()
                self.dropped += 1
            else:
                self._line.append(byte)
        return lines
