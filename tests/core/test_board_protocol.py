"""LED board wire protocol: encoding, decoding, checksum, framing (no I/O)."""

import pytest

from fingerps_driver.board.board_protocol import (
    MAX_LINE_BYTES,
    REPLY_SIGIL,
    REQUEST_SIGIL,
    Command,
    ErrorCode,
    LineFramer,
    Reply,
    Request,
    crc8,
    decode_reply,
    decode_request,
    encode_reply,
    encode_request,
    format_mask,
    indices_to_mask,
    mask_to_indices,
    next_seq,
    parse_mask,
)
from fingerps_driver.errors import ProtocolError


def _line(sigil: bytes, body: str, *, crc: int | None = None) -> bytes:
    """A wire line with a correct checksum unless ``crc`` is given."""
    raw = body.encode("ascii")
    value = crc8(raw) if crc is None else crc
    return sigil + raw + f"*{value:02X}\n".encode("ascii")


def test_crc8_is_smbus_with_standard_check_value():
    assert crc8(b"123456789") == 0xF4
    assert crc8(b"") == 0


def test_request_wire_format_is_as_specified():
    line = encode_request(Request(5, Command.LEDS, (0x04,)))
    assert line == _line(b"#", "5,LEDS,04")
    assert line.startswith(b"#5,LEDS,04*") and line.endswith(b"\n")
    assert encode_request(Request(255, Command.LEVEL, (6, 200))) == _line(b"#", "255,LEVEL,6,200")


@pytest.mark.parametrize(
    "request_",
    [
        Request(0, Command.PING),
        Request(1, Command.INFO),
        Request(2, Command.LEDS, (0x7F,)),
        Request(3, Command.LEDS, (0,)),
        Request(4, Command.OFF),
        Request(254, Command.LEVEL, (3, 0)),
        Request(255, Command.STATE),
        Request(6, Command.TRIG, (0, 0)),
        Request(7, Command.TRIG, (65535, 100)),
    ],
)
def test_request_round_trip(request_):
    assert decode_request(encode_request(request_)) == request_


@pytest.mark.parametrize(
    "reply",
    [
        Reply(0),
        Reply(17, ("fingerps-emu-1.0", "7")),
        Reply(18, ("7F",)),
        Reply(19, ("05", "255", "0", "12", "255", "255", "255", "255")),
        Reply(20, error=ErrorCode.OUT_OF_RANGE, message="LED 9 does not exist"),
        Reply(255, error=ErrorCode.BAD_CHECKSUM, message="checksum mismatch"),
    ],
)
def test_reply_round_trip(reply):
    assert decode_reply(encode_reply(reply)) == reply


def test_error_reply_wire_format():
    line = encode_reply(Reply(9, error=ErrorCode.UNKNOWN_COMMAND, message="unknown BLINK"))
    assert line == _line(b"!", "9,ERR,CMD,unknown BLINK")
    assert not decode_reply(line).ok


def test_every_single_bit_flip_is_detected_or_harmless():
    # the only undetected flips are upper/lower case of a checksum hex digit: same value
    lines = [
        encode_request(Request(37, Command.LEDS, (0x10,))),
        encode_reply(Reply(37, ("10",))),
        encode_reply(Reply(200, ("05", "255", "0", "12"))),
    ]
    for line in lines:
        decode = decode_request if line.startswith(REQUEST_SIGIL) else decode_reply
        for pos in range(1, len(line) - 1):  # everything but the sigil and the newline
            for bit in range(8):
                garbled = bytearray(line)
                garbled[pos] ^= 1 << bit
                try:
                    decoded = decode(bytes(garbled))
                except ProtocolError:
                    continue
                assert decoded == decode(line)
                assert bytes(garbled).upper() == line.upper() and pos >= len(line) - 3


def test_flipped_payload_byte_reports_bad_checksum_with_seq():
    line = bytearray(encode_request(Request(42, Command.LEDS, (0x04,))))
    line[line.index(b"LEDS")] ^= 0x01  # 'L' -> 'M'
    with pytest.raises(ProtocolError) as info:
        decode_request(bytes(line))
    assert info.value.code is ErrorCode.BAD_CHECKSUM
    assert info.value.seq == 42


def test_seq_wraps_and_is_bounded():
    assert next_seq(0) == 1
    assert next_seq(254) == 255
    assert next_seq(255) == 0
    with pytest.raises(ValueError):
        Request(256, Command.PING)
    with pytest.raises(ValueError):
        Reply(-1)
    with pytest.raises(ProtocolError) as info:
        decode_request(_line(b"#", "256,PING"))
    assert info.value.code is ErrorCode.BAD_FRAME
    assert info.value.seq is None
    with pytest.raises(ProtocolError):
        decode_request(_line(b"#", "0007,PING"))  # more than 3 digits


BAD_REQUESTS = {  # request bodies (seq 3) by the error code they must carry
    ErrorCode.UNKNOWN_COMMAND: ["3,BLINK", "3,ping"],
    ErrorCode.BAD_ARGUMENT: ["3,LEDS", "3,LEDS,1,2", "3,LEDS,XY", "3,LEDS,123456789", "3,PING,1",
                             "3,LEVEL,1", "3,LEVEL,1,256", "3,LEVEL,1,-5", "3,LEVEL,256,5",
                             "3,TRIG", "3,TRIG,1", "3,TRIG,1,2,3", "3,TRIG,65536,1",
                             "3,TRIG,1,65536", "3,TRIG,-1,1", "3,TRIG,1,0x10"],
    ErrorCode.BAD_FRAME: ["3,", "3,LEDS,,"],
}


@pytest.mark.parametrize(
    ("body", "code"), [(body, code) for code, bodies in BAD_REQUESTS.items() for body in bodies])
def test_bad_requests_carry_code_and_seq(body, code):
    with pytest.raises(ProtocolError) as info:
        decode_request(_line(b"#", body))
    assert info.value.code is code
    assert info.value.seq == 3


@pytest.mark.parametrize(
    "line",
    [
        b"",
        b"\n",
        b"#1,PING\n",  # no checksum
        b"#1,PING*G0\n",  # checksum not hex
        b"#1,PING*123\n",  # checksum too long
        b"!1,OK*00\n",  # reply sigil on a request
        b"#1,P\xc3\x9cNG*00\n",  # non-ASCII
        b"#" + b"1,LEDS," + b"0" * MAX_LINE_BYTES + b"*00\n",  # too long
    ],
)
def test_malformed_requests_raise(line):
    with pytest.raises(ProtocolError):
        decode_request(line)


@pytest.mark.parametrize(
    "body",
    ["4,MAYBE", "4,ERR,CRC", "4,ERR,NOPE,text", "4,ERR,CRC,a,b", "4", "x,OK"],
)
def test_malformed_replies_raise(body):
    with pytest.raises(ProtocolError):
        decode_reply(_line(b"!", body))


def test_crlf_and_lower_case_checksum_accepted():
    body = "12,OK,7F"
    line = b"!" + body.encode() + f"*{crc8(body.encode()):02x}\r\n".encode()
    assert decode_reply(line) == Reply(12, ("7F",))
    assert decode_reply(line.rstrip(b"\r\n")) == Reply(12, ("7F",))


def test_trigger_times_go_up_to_65535_us_and_an_older_board_does_not_know_trig():
    assert decode_request(_line(b"#", "9,TRIG,065535,00")) == Request(9, Command.TRIG,
                                                                       (65535, 0))
    with pytest.raises(ProtocolError, match="65536 exceeds 65535") as info:
        decode_request(_line(b"#", "9,TRIG,10,65536"))
    assert info.value.code is ErrorCode.BAD_ARGUMENT
    assert decode_request(_line(b"#", "9,LEVEL,1,255")).args == (1, 255)
    with pytest.raises(ProtocolError, match="256 exceeds 255"):
        decode_request(_line(b"#", "9,LEVEL,1,256"))  # TRIG's maximum is TRIG's only
    older = tuple(c for c in Command if c is not Command.TRIG)
    for body in ("9,TRIG,10,20", "9,TRIG,1"):  # CMD before any argument check
        with pytest.raises(ProtocolError, match="unknown command 'TRIG'") as info:
            decode_request(_line(b"#", body), commands=older)
        assert (info.value.code, info.value.seq) == (ErrorCode.UNKNOWN_COMMAND, 9)
    assert decode_request(_line(b"#", "9,PING"), commands=older) == Request(9, Command.PING)


def test_invalid_messages_are_refused_on_encode():
    with pytest.raises(ValueError):
        Request(1, Command.LEDS)  # missing mask
    with pytest.raises(ValueError):
        Request(1, Command.LEVEL, (0, 256))
    with pytest.raises(ValueError):
        Request(1, Command.LEDS, (-1,))
    with pytest.raises(ValueError, match=r"trigger width 65536 us outside 0\.\.65535"):
        Request(1, Command.TRIG, (0, 65536))
    with pytest.raises(ValueError):
        Reply(1, ("a,b",))  # a comma would split the field
    with pytest.raises(ValueError):
        Reply(1, ("x",), error=ErrorCode.BAD_ARGUMENT, message="m")


def test_failure_reply_sanitises_text():
    reply = Reply.failure(7, ErrorCode.BAD_ARGUMENT, "bad 'x,y*z' \u00e9\n")
    assert reply.message == "bad 'x y z'"
    assert decode_reply(encode_reply(reply)) == reply
    assert ErrorCode.BAD_CHECKSUM.retryable and not ErrorCode.OUT_OF_RANGE.retryable


def test_masks():
    assert format_mask(5) == "05"
    assert format_mask(0x1FF) == "1FF"
    assert parse_mask("7f") == 0x7F
    assert mask_to_indices(0b1010001) == (0, 4, 6)
    assert indices_to_mask([0, 4, 6]) == 0b1010001
    assert mask_to_indices(0) == ()
    with pytest.raises(ValueError):
        format_mask(1 << 32)


def test_line_framer_resynchronises():
    framer = LineFramer(REPLY_SIGIL)
    good = encode_reply(Reply(1, ("04",)))
    # noise before a sigil, a line split over two reads, a truncated line restarted
    assert framer.feed(b"\x00noise" + good[:4]) == []
    assert framer.feed(good[4:]) == [good[:-1]]
    assert framer.feed(b"!2,OK,0" + good) == [good[:-1]]
    assert framer.dropped == len(b"\x00noise") + len(b"!2,OK,0")
    # an overlong line is dropped, the next one is kept
    assert framer.feed(b"!" + b"A" * (MAX_LINE_BYTES + 10) + b"\n" + good) == [good[:-1]]
    framer.feed(b"!partial")
    framer.reset()
    assert framer.feed(b"\n" + good) == [good[:-1]]
