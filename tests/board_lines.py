"""Raw request lines to an LED board on a pty, and the replies they are owed, for the board
tests (the emulator's and the firmware's).

``RawBoard`` writes bytes exactly as given (good lines, garbled ones, noise) and reads back
as many replies as ``board_protocol`` says the board owes for them: the receiver frames
lines out of the bytes as ``LineFramer`` does (state kept from one write to the next), and
every framed line that ``decode_request`` can give a seq (accepted, or refused with a seq)
gets exactly one reply; a line without a readable seq gets none. A reply missing is a
``readline`` that times out (an empty or partial line the test sees); a reply too many is
found by ``quiet()``, a sentinel ``PING`` whose reply must come next.
"""

from __future__ import annotations

from typing import Self

import serial

from fingerps_driver.board.board_protocol import (
    REQUEST_SIGIL,
    ErrorCode,
    LineFramer,
    crc8,
    decode_request,
)
from fingerps_driver.errors import ProtocolError


def request_line(body: str, *, crc: int | None = None, end: bytes = b"\n") -> bytes:
    """``#<body>*<crc><end>``: the checksum of ``body`` unless ``crc`` is given."""
    raw = body.encode("latin-1")
    value = crc8(raw) if crc is None else crc
    return b"#" + raw + f"*{value:02X}".encode("ascii") + end


BAD_LINES = [  # (request line, error code of the board's reply), seq 9 each: every error
    (request_line("9,PING", crc=crc8(b"9,PING") ^ 0x01), ErrorCode.BAD_CHECKSUM),
    (request_line("9,LEDS,05", crc=crc8(b"9,LEDS,05") ^ 0x80), ErrorCode.BAD_CHECKSUM),
    (b"#9,PING*\n", ErrorCode.BAD_FRAME),  # no checksum after the star
    (b"#9,PING*5\n", ErrorCode.BAD_FRAME),  # one digit
    (request_line("9,"), ErrorCode.BAD_FRAME),  # empty command
    (request_line("9,LEDS,,"), ErrorCode.BAD_FRAME),
    (request_line("9,LEDS,\x7f"), ErrorCode.BAD_FRAME),  # not printable
    (request_line("9,BLINK"), ErrorCode.UNKNOWN_COMMAND),
    (request_line("9,ping"), ErrorCode.UNKNOWN_COMMAND),
    (request_line("9,PING,1"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEDS"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEDS,XY"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEDS,123456789"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEVEL,1,256"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEVEL,1,-5"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEVEL,1,00000000000"), ErrorCode.BAD_ARGUMENT),  # 11 digits
    (request_line("9,TRIG,1"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,TRIG,70000,1"), ErrorCode.BAD_ARGUMENT),
    (request_line("9,LEDS,80"), ErrorCode.OUT_OF_RANGE),
    (request_line("9,LEDS,FFFFFFFF"), ErrorCode.OUT_OF_RANGE),
    (request_line("9,LEVEL,7,10"), ErrorCode.OUT_OF_RANGE),
]


def owes_reply(line: bytes) -> bool:
    """Whether a framed request line (sigil, no newline) is owed a reply."""
    try:
        decode_request(line)
    except ProtocolError as exc:
        return exc.seq is not None
    return True


class RawBoard:
    """Raw bytes to a board's port, the owed replies back (see the module docstring).

    Parameters
    ----------
    port : str
        The board's pty (or its link).
    timeout_s : float
        How long one reply is waited for; a generous bound, only reached on a failure.
    """

    SENTINEL_SEQ = 123
    NOISE_BYTE_S = 100e-6
    """A generous byte time at 115200 baud (the simulated UART takes 93.5 us)."""

    def __init__(self, port: str, *, timeout_s: float = 2.0) -> None:
        self._timeout_s = timeout_s
        self._noise_s = 0.0  # noise sent since the last reply was read
        self._serial = serial.Serial(port, 115200, timeout=timeout_s)
        self._serial.reset_input_buffer()
        self._framer = LineFramer(REQUEST_SIGIL)
        self.lines_sent = 0
        """Framed lines sent so far (what the board received as lines)."""
        self.lines_unanswered = 0
        """Those of them owed no reply."""

    def close(self) -> None:
        self._serial.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def framed(self, data: bytes) -> list[bytes]:
        """The lines the board frames out of ``data`` next (advances the framer)."""
        lines = self._framer.feed(data)
        self.lines_sent += len(lines)
        return lines

    def send(self, data: bytes) -> list[tuple[bytes, bytes]]:
        """Write ``data``; return (request line, reply line) for every line owed a reply,
        the reply with its newline (short or empty if it did not come in time)."""
        lines = self.framed(data)
        owed = [line for line in lines if owes_reply(line)]
        self.lines_unanswered += len(lines) - len(owed)
        self._serial.write(data)
        self._serial.flush()
        return [(line, self._readline()) for line in owed]

    def _readline(self) -> bytes:
        """One reply line; the wait also covers noise still on its way to the board."""
        self._serial.timeout = self._timeout_s + self._noise_s
        self._noise_s = 0.0
        return self._serial.readline()

    def noise(self, count: int) -> None:
        """Write ``count`` bytes that are no line (no sigil): the board drops them, after
        taking ``count`` byte times to receive them. A wait in the board's own time."""
        self.framed(b"~" * count)
        self._serial.write(b"~" * count)
        self._serial.flush()
        self._noise_s += count * self.NOISE_BYTE_S

    def quiet(self) -> bytes:
        """Send a sentinel ``PING``; return the next reply line (its reply if no other
        reply was pending)."""
        line = request_line(f"{self.SENTINEL_SEQ},PING")
        self.framed(line)
        self._serial.write(line)
        self._serial.flush()
        return self._readline()

    @classmethod
    def sentinel_reply(cls) -> bytes:
        body = f"{cls.SENTINEL_SEQ},OK".encode("ascii")
        return b"!" + body + f"*{crc8(body):02X}\n".encode("ascii")
