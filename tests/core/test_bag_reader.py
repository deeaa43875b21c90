"""Tests of fingerps_recon.sessions.bag_reader on bags written in tmp_path, intact and damaged."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.reader import make_reader
from rclpy.serialization import serialize_message

from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_recon.errors import BagSchemaError, McapDamageError
from fingerps_recon.sessions.bag_reader import SessionBagReader
from fingerps_recon.sessions.message_definition import MessageDefinition, load_message_definition
from fingerps_recon.sessions.session_bag import SessionBagWriter

T0 = 1_700_000_000_000_000_000
BURST = "/fingerps/burst"
LIGHTS = "/fingerps/calibration/lights"


def _bag(path: Path, *, bursts: int = 4, definition: MessageDefinition | None = None) -> list[int]:
    sizes = []
    with SessionBagWriter(path) as bag:
        bag.add_topic(LIGHTS, "fingerps_msgs/msg/LightCalibration", offered_qos_yaml="[]")
        bag.add_topic(BURST, "fingerps_msgs/msg/Burst", offered_qos_yaml="[]",
                      definition=definition)
        bag.write(LIGHTS, serialize_message(LightCalibration(camera_name="a")),
                  log_time_ns=T0, publish_time_ns=T0)
        for i in range(bursts):
            bag.write(BURST, serialize_message(Burst(burst_id=i)), log_time_ns=T0 + i + 1,
                      publish_time_ns=T0 + i)
            bag.flush()
            sizes.append(bag.mcap_path.stat().st_size)
    return sizes


def test_messages_by_topic_deserialised(tmp_path: Path) -> None:
    _bag(tmp_path / "bag")
    reader = SessionBagReader(tmp_path / "bag")
    assert reader.topics() == {LIGHTS: "fingerps_msgs/msg/LightCalibration",
                               BURST: "fingerps_msgs/msg/Burst"}
    bursts = [m.deserialize().burst_id for m in reader.messages([BURST])]
    assert bursts == [0, 1, 2, 3]
    assert reader.latest(LIGHTS).camera_name == "a"
    assert reader.latest("/nothing") is None


def test_a_truncated_bag_is_read_up_to_the_named_offset(tmp_path: Path) -> None:
    sizes = _bag(tmp_path / "bag")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((tmp_path / "bag" / "bag_0.mcap").read_bytes()[:sizes[1] + 30])  # 3rd chunk
    seen = []
    with pytest.raises(McapDamageError, match=f"byte offset {sizes[1]} ") as caught:
        for message in SessionBagReader(cut).messages([BURST]):
            seen.append(message.deserialize().burst_id)
    assert seen == [0, 1] and caught.value.offset == sizes[1]


def test_another_version_of_our_messages_is_refused(tmp_path: Path) -> None:
    real = load_message_definition("fingerps_msgs/msg/Burst")
    old = MessageDefinition(real.type_name, real.encoding,
                            real.text.replace("uint32 burst_id", "uint16 burst_id", 1))
    _bag(tmp_path / "old", definition=old)
    with pytest.raises(BagSchemaError, match=r"another version of fingerps_msgs/msg/Burst.*"
                                             r"uint16 burst_id"):
        list(SessionBagReader(tmp_path / "old").messages())
    # Unchecked on request (e.g. to look at the other fields with a matching build).
    assert len(list(SessionBagReader(tmp_path / "old", check_schemas=False).messages())) == 5


def _chunks(mcap_path: Path) -> list[tuple[int, int]]:
    """(start, end) of each chunk record."""
    with open(mcap_path, "rb") as stream:
        indexes = make_reader(stream).get_summary().chunk_indexes
    return sorted((c.chunk_start_offset, c.chunk_start_offset + c.chunk_length)
                  for c in indexes)


def _damaged(tmp_path: Path, offset: int, value: int | None = None) -> Path:
    """A copy of bag/bag_0.mcap with the byte at ``offset`` flipped (or set to ``value``)."""
    data = bytearray((tmp_path / "bag" / "bag_0.mcap").read_bytes())
    data[offset] = data[offset] ^ 0xFF if value is None else value
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    return path


def test_a_damaged_first_chunk_is_skipped_and_reading_goes_on(tmp_path: Path) -> None:
    """The first chunk holds the calibration, burst 0 and every channel definition; a byte
    flipped in it loses those two messages only (channels come from the summary)."""
    _bag(tmp_path / "bag")
    (start, end), *_ = _chunks(tmp_path / "bag" / "bag_0.mcap")
    broken = _damaged(tmp_path, end - 40)  # in chunk 0's compressed records
    seen = []
    with pytest.raises(McapDamageError, match=f"byte offset {start} ") as caught:
        for message in SessionBagReader(broken).messages():
            seen.append((message.topic, message.deserialize().burst_id))
    assert seen == [(BURST, 1), (BURST, 2), (BURST, 3)]
    assert (caught.value.damage[0].start, caught.value.damage[0].end) == (start, end)
    assert "bag_recover" in str(caught.value)
    reader = SessionBagReader(broken, raise_on_damage=False)
    assert len(list(reader.messages([BURST]))) == 3
    assert [(d.start, d.end) for d in reader.damage] == [(start, end)]
    assert reader.topics() == {LIGHTS: "fingerps_msgs/msg/LightCalibration",
                               BURST: "fingerps_msgs/msg/Burst"}


def test_a_corrupted_opcode_is_reported_not_skipped(tmp_path: Path) -> None:
    _bag(tmp_path / "bag")
    starts = [start for start, _ in _chunks(tmp_path / "bag" / "bag_0.mcap")]
    broken = _damaged(tmp_path, starts[2], value=0x86)  # the chunk of burst 2
    seen = []
    with pytest.raises(McapDamageError, match="unknown record opcode 0x86") as caught:
        for message in SessionBagReader(broken).messages([BURST]):
            seen.append(message.deserialize().burst_id)
    assert seen == [0, 1, 3] and caught.value.offset == starts[2]
