"""Tests of sessions.mcap_records and sessions.bag_recovery on files written in
tmp_path: finished, cut mid-chunk, corrupted mid-file, cut at a chunk boundary (a kill), and
damaged bags with known contents (flipped bytes, corrupted opcodes and lengths, cuts, lost
summaries, a seeded sweep): every message of an intact chunk is kept, the rest reported."""

from __future__ import annotations

import io
import json
import shutil
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import breakup_chunk
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader

from fingerps_msgs.msg import Burst, FlatField, LightCalibration
from fingerps_recon.errors import BagRecoveryError, McapDamageError
from fingerps_recon.sessions.bag_recover import main as bag_recover_main
from fingerps_recon.sessions.bag_recovery import recover_bag
from fingerps_recon.sessions.mcap_records import scan_records
from fingerps_recon.sessions.session_bag import SessionBagWriter

T0 = 1_700_000_000_000_000_000
BURST = "/fingerps/burst"
LIGHTS = "/fingerps/calibration/lights"
CHUNKS = 6
PER_CHUNK = 3


def _begin_session(bag: SessionBagWriter, camera_name: str) -> None:
    """The software record, the calibration and burst topics, and one calibration at T0."""
    bag.add_metadata("fingerps.software", {"package": "fingerps_recon"})
    bag.add_topic(LIGHTS, "fingerps_msgs/msg/LightCalibration", offered_qos_yaml="[]")
    bag.add_topic(BURST, "fingerps_msgs/msg/Burst", offered_qos_yaml="[]")
    bag.write(LIGHTS, serialize_message(LightCalibration(camera_name=camera_name)),
              log_time_ns=T0, publish_time_ns=T0)


def _write_bag(path: Path) -> tuple[Path, list[int]]:
    """A bag of CHUNKS chunks of PER_CHUNK bursts each (plus the calibration in the first);
    returns the MCAP path and the file size after each flushed chunk."""
    sizes = []
    with SessionBagWriter(path, chunk_size=1 << 20) as bag:
        _begin_session(bag, "cut")
        for chunk in range(CHUNKS):
            for i in range(PER_CHUNK):
                n = chunk * PER_CHUNK + i
                bag.write(BURST, serialize_message(Burst(burst_id=n)) + bytes(2000),
                          log_time_ns=T0 + n + 1, publish_time_ns=T0 + n)
            bag.flush()
            sizes.append(bag.mcap_path.stat().st_size)
    return bag.mcap_path, sizes


def _truncated_copy(mcap_path: Path, size: int, tmp_path: Path) -> Path:
    target = tmp_path / "cut" / "cut_0.mcap"
    target.parent.mkdir()
    target.write_bytes(mcap_path.read_bytes()[:size])
    return target


def _burst_ids(bag_dir: Path) -> list[int]:
    with RosbagsReader(bag_dir) as bag:
        return [deserialize_message(raw, Burst).burst_id
                for conn, _, raw in bag.messages() if conn.topic == BURST]


def test_a_finished_bag_scans_to_its_end(tmp_path: Path) -> None:
    mcap_path, _ = _write_bag(tmp_path / "ok")
    records = scan_records(mcap_path)
    count = 0
    try:
        while True:
            count += type(next(records).record).__name__ == "Message"
    except StopIteration as stop:
        assert stop.value.finished
    assert count == 1 + CHUNKS * PER_CHUNK


def test_a_bag_cut_mid_chunk_is_recovered_up_to_the_named_offset(tmp_path: Path,
                                                                 capsys) -> None:
    mcap_path, sizes = _write_bag(tmp_path / "ok")
    cut = sizes[3] + (sizes[4] - sizes[3]) // 2  # half of the fifth chunk written
    source = _truncated_copy(mcap_path, cut, tmp_path)

    with pytest.raises(McapDamageError) as caught:
        for _ in scan_records(source):
            pass
    assert caught.value.offset == sizes[3]
    assert f"byte offset {sizes[3]}" in str(caught.value)

    assert bag_recover_main([str(source.parent), "-o", str(tmp_path / "fixed")]) == 0
    out = capsys.readouterr().out
    assert f"at byte offset {sizes[3]}" in out and "cut short" in out
    assert f"{cut - sizes[3]} bytes" in out
    assert "kept   : 13 messages" in out  # calibration + 4 chunks of 3 bursts
    assert _burst_ids(tmp_path / "fixed") == list(range(4 * PER_CHUNK))
    with open(tmp_path / "fixed" / "fixed_0.mcap", "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_summary().statistics.message_count == 1 + 4 * PER_CHUNK
        records = {m.name: m.metadata for m in reader.iter_metadata()}
    assert records["fingerps.software"] == {"package": "fingerps_recon"}
    assert records["fingerps.recovery"]["damage_offset"] == str(sizes[3])


def test_corruption_mid_file_names_the_offset_and_counts_what_was_lost(tmp_path: Path) -> None:
    mcap_path, sizes = _write_bag(tmp_path / "ok")
    data = bytearray(mcap_path.read_bytes())
    data[sizes[1] + 60] ^= 0xFF  # inside the third chunk's compressed records
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    report = recover_bag(broken, tmp_path / "fixed")
    assert report.damage_offset == sizes[1]
    assert "CHUNK record does not parse" in report.damage_reason
    assert report.message_count == 1 + (CHUNKS - 1) * PER_CHUNK  # reading went on after it
    assert report.lost_messages == PER_CHUNK and report.lost_exact  # the summary says so
    assert report.lost_counts == {BURST: PER_CHUNK}
    assert sizes[1] < report.damage[0].end < sizes[2]  # the chunk; its indexes were read
    assert list(report.damage[0].lost_by_channel.values()) == [PER_CHUNK]
    assert _burst_ids(tmp_path / "fixed") == [n for n in range(CHUNKS * PER_CHUNK)
                                              if not 2 * PER_CHUNK <= n < 3 * PER_CHUNK]


def test_a_file_ending_between_chunks_loses_nothing_it_holds(tmp_path: Path) -> None:
    mcap_path, sizes = _write_bag(tmp_path / "ok")
    source = _truncated_copy(mcap_path, sizes[2], tmp_path)  # as a SIGKILL leaves it
    report = recover_bag(source.parent, tmp_path / "fixed")
    assert report.damage_offset is None and not report.finished
    assert report.lost_bytes == 0 and report.message_count == 1 + 3 * PER_CHUNK
    assert "killed between chunks" in report.describe()


def test_bad_input_is_refused_with_a_reason(tmp_path: Path, capsys) -> None:
    (tmp_path / "text.mcap").write_text("not a bag")
    assert bag_recover_main([str(tmp_path / "text.mcap")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    assert not (tmp_path / "text_recovered").exists()
    with pytest.raises(BagRecoveryError, match="does not exist"):
        recover_bag(tmp_path / "missing", tmp_path / "out")
    mcap_path, _ = _write_bag(tmp_path / "ok")
    shutil.copytree(tmp_path / "ok", tmp_path / "taken")
    with pytest.raises(BagRecoveryError, match="already exists"):
        recover_bag(mcap_path, tmp_path / "taken")


# ---- damaged bags with known contents ---------------------------------------------------------

FLAT = "/fingerps/calibration/flat_field"


@dataclass(frozen=True)
class ChunkLayout:
    """One chunk of a pristine bag: its record's byte range and what it holds."""

    start: int
    end: int
    data_start: int
    messages: frozenset[int]  # log times
    defines: frozenset[str]  # topics whose Channel record is in this chunk


@dataclass(frozen=True)
class Layout:
    mcap: Path
    chunks: tuple[ChunkLayout, ...]
    messages: dict[int, tuple[str, bytes]]  # log time -> (topic, data)
    data_end: int
    channel_ids: dict[str, int]


def _layered_bag(path: Path, *, seed: int = 0) -> Layout:
    """10 chunks: chunk 0 defines the calibration and burst channels and holds one
    calibration; chunks 1-9 hold 4 bursts each; the flat-field channel is defined in chunk 4
    and has one message in each of chunks 4-9 (43 messages)."""
    rng = np.random.default_rng(seed)
    n = 0
    with SessionBagWriter(path, chunk_size=1 << 20) as bag:
        _begin_session(bag, "layered")
        bag.flush()
        for chunk in range(1, 10):
            if chunk == 4:
                bag.add_topic(FLAT, "fingerps_msgs/msg/FlatField", offered_qos_yaml="[]")
            if chunk >= 4:
                n += 1
                bag.write(FLAT, serialize_message(FlatField()) + rng.bytes(64),
                          log_time_ns=T0 + 1000 + n, publish_time_ns=T0)
            for _ in range(4):
                n += 1
                bag.write(BURST, serialize_message(Burst(burst_id=n)) + rng.bytes(300),
                          log_time_ns=T0 + n, publish_time_ns=T0 + n)
            bag.flush()
    return _layout(bag.mcap_path)


def _layout(mcap_path: Path) -> Layout:
    """Ground truth read with the mcap library from the pristine file."""
    raw = mcap_path.read_bytes()
    with open(mcap_path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    topics = {cid: ch.topic for cid, ch in summary.channels.items()}
    chunks = []
    messages: dict[int, tuple[str, bytes]] = {}
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        start = index.chunk_start_offset
        body = io.BytesIO(raw[start + 9:start + index.chunk_length])
        chunk = Chunk.read(ReadDataStream(body))
        logged, defines = set(), set()
        for record in breakup_chunk(chunk, validate_crc=True):
            if isinstance(record, Message):
                logged.add(record.log_time)
                messages[record.log_time] = (topics[record.channel_id], record.data)
            elif isinstance(record, Channel):
                defines.add(record.topic)
        data_start = start + 9 + 8 + 8 + 8 + 4 + 4 + len(chunk.compression) + 8
        chunks.append(ChunkLayout(start, start + index.chunk_length, data_start,
                                  frozenset(logged), frozenset(defines)))
    data_end = raw.rindex(b"\x0f\x04\x00\x00\x00\x00\x00\x00\x00")
    return Layout(mcap_path, tuple(chunks), messages, data_end,
                  {topic: cid for cid, topic in topics.items()})


def _damaged_copy(layout: Layout, target: Path, edits: list[tuple[int, bytes]],
                  *, cut: int | None = None) -> Path:
    """A copy of the bag with bytes replaced at offsets, optionally cut at ``cut``."""
    data = bytearray(layout.mcap.read_bytes())
    for offset, new in edits:
        data[offset:offset + len(new)] = new
    target.mkdir(parents=True)
    path = target / f"{target.name}_0.mcap"
    path.write_bytes(bytes(data[:cut]))
    return path


def _flip(data: bytes, offset: int) -> tuple[int, bytes]:
    return offset, bytes([data[offset] ^ 0xFF])


def _kept(bag_dir: Path) -> dict[int, tuple[str, bytes]]:
    """log time -> (topic, data) of every message in a recovered bag (read by mcap)."""
    mcap_path = next(bag_dir.glob("*.mcap"))
    with open(mcap_path, "rb") as stream:
        return {message.log_time: (channel.topic, message.data)
                for _, channel, message in make_reader(stream).iter_messages()}


def _expected(layout: Layout, touched: set[int], *, summary: bool) -> set[int]:
    """Log times that must survive when the chunks ``touched`` are damaged: every message
    of an intact chunk whose channel is defined in the summary or in an intact chunk."""
    defined = {LIGHTS, BURST, FLAT} if summary else set().union(
        *(c.defines for i, c in enumerate(layout.chunks) if i not in touched))
    return {t for i, chunk in enumerate(layout.chunks) if i not in touched
            for t in chunk.messages if layout.messages[t][0] in defined}


def _lost_by_topic(layout: Layout, kept: set[int]) -> dict[str, int]:
    lost: dict[str, int] = {}
    for t, (topic, _) in layout.messages.items():
        if t not in kept:
            lost[topic] = lost.get(topic, 0) + 1
    return lost


def test_one_flipped_byte_in_the_first_chunk_loses_only_that_chunk(tmp_path: Path,
                                                                    capsys) -> None:
    layout = _layered_bag(tmp_path / "ok")
    first = layout.chunks[0]
    data = layout.mcap.read_bytes()
    source = _damaged_copy(layout, tmp_path / "flip",
                           [_flip(data, (first.data_start + first.end) // 2)])
    assert bag_recover_main([str(source.parent), "-o", str(tmp_path / "fixed")]) == 0
    out = capsys.readouterr().out
    kept = _kept(tmp_path / "fixed")
    assert sorted(kept) == sorted(_expected(layout, {0}, summary=True))
    assert len(kept) == 42  # of 43: every burst and flat field, only the calibration lost
    assert all(kept[t] == layout.messages[t] for t in kept)  # byte for byte
    assert f"at byte offset {first.start} (to {first.end}" in out
    assert "1 damaged range(s), 1 chunk(s) lost" in out
    assert f"lost   : 1 messages ({LIGHTS}: 1; exact" in out
    assert BURST in out.split("note   :")[1]  # its channel came from the summary
    with RosbagsReader(tmp_path / "fixed") as bag:  # a valid rosbag2 bag
        assert {c.topic: c.msgcount for c in bag.connections} == {BURST: 36, FLAT: 6}
    with open(tmp_path / "fixed" / "fixed_0.mcap", "rb") as stream:
        records = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    assert json.loads(records["fingerps.recovery"]["damaged_ranges"]) == [
        [first.start, first.end, records["fingerps.recovery"]["damage_reason"]]]
    assert json.loads(records["fingerps.recovery"]["lost_by_topic"]) == {LIGHTS: 1}


def test_a_corrupted_opcode_is_damage_and_its_channels_come_from_the_summary(
        tmp_path: Path) -> None:
    layout = _layered_bag(tmp_path / "ok")
    fourth = layout.chunks[4]  # defines the flat-field channel
    source = _damaged_copy(layout, tmp_path / "opcode", [(fourth.start, b"\x86")])
    report = recover_bag(source, tmp_path / "fixed")
    kept = _kept(tmp_path / "fixed")
    assert set(kept) == _expected(layout, {4}, summary=True)
    assert len(kept) == 43 - 5  # chunk 4: one flat field, four bursts
    assert [(d.start, d.end) for d in report.damage] == [(fourth.start, fourth.end)]
    assert "unknown record opcode 0x86" in report.damage_reason
    assert report.lost_exact and report.lost_counts == {FLAT: 1, BURST: 4}
    assert report.chunks_lost == 1 and report.chunks_kept == 9
    assert report.definitions_from_summary == (FLAT,)
    assert "damage : none" not in report.describe()


@pytest.mark.parametrize("length", [0, 17, 2**40, -1])
def test_a_corrupted_chunk_length_loses_that_chunk_only(tmp_path: Path, length: int) -> None:
    layout = _layered_bag(tmp_path / "ok")
    third = layout.chunks[2]
    true_length = third.end - third.start - 9
    value = true_length + 1000 if length == -1 else length
    source = _damaged_copy(layout, tmp_path / "length",
                           [(third.start + 1, struct.pack("<Q", value))])
    report = recover_bag(source, tmp_path / "fixed")
    assert set(_kept(tmp_path / "fixed")) == _expected(layout, {2}, summary=True)
    assert [(d.start, d.end) for d in report.damage] == [(third.start, third.end)]
    assert report.lost_counts == {BURST: 4} and report.lost_exact
    assert report.damage[0].lost_by_channel  # the message indexes after it were read


def test_a_bag_cut_mid_chunk_without_summary_names_what_it_lost(tmp_path: Path) -> None:
    layout = _layered_bag(tmp_path / "ok")
    sixth = layout.chunks[6]
    cut = (sixth.data_start + sixth.end) // 2
    source = _damaged_copy(layout, tmp_path / "cut", [], cut=cut)
    report = recover_bag(source.parent, tmp_path / "fixed")
    kept = _kept(tmp_path / "fixed")
    assert set(kept) == _expected(layout, set(range(6, 10)), summary=False)
    assert len(kept) == 1 + 4 * 5 + 2
    assert [(d.start, d.end) for d in report.damage] == [(sixth.start, cut)]
    assert "past the end of the file" in report.damage_reason
    assert not report.lost_exact and report.chunks_lost == 1  # what is knowable
    assert "at least" in report.describe()


def test_a_damaged_chunk_of_a_bag_without_summary_counts_undecodable_messages(
        tmp_path: Path) -> None:
    """Killed recorder (no summary) and chunk 0 damaged: the burst channel is defined
    nowhere readable, so the bursts of intact chunks cannot be decoded; they are counted
    as lost on their channel, not dropped silently."""
    layout = _layered_bag(tmp_path / "ok")
    data = layout.mcap.read_bytes()
    first = layout.chunks[0]
    source = _damaged_copy(layout, tmp_path / "killed",
                           [_flip(data, (first.data_start + first.end) // 2)],
                           cut=layout.data_end)
    report = recover_bag(source, tmp_path / "fixed")
    kept = _kept(tmp_path / "fixed")
    assert set(kept) == _expected(layout, {0}, summary=False)
    assert {topic for topic, _ in kept.values()} == {FLAT}
    assert not report.lost_exact
    ids = layout.channel_ids  # no topic names: their Channel records are lost
    assert report.lost_counts == {f"channel {ids[LIGHTS]}": 1, f"channel {ids[BURST]}": 36}
    assert report.undecodable == {f"channel {ids[BURST]}": 36}
    assert f"36 intact messages of channel {ids[BURST]} could not be kept" in report.describe()


def test_a_deleted_footer_still_gives_the_summary_after_data_end(tmp_path: Path) -> None:
    layout = _layered_bag(tmp_path / "ok")
    data = layout.mcap.read_bytes()
    first = layout.chunks[0]
    size = len(data)
    source = _damaged_copy(layout, tmp_path / "nofooter",
                           [_flip(data, (first.data_start + first.end) // 2)],
                           cut=size - 8 - 29)  # footer and closing magic gone
    report = recover_bag(source, tmp_path / "fixed")
    assert set(_kept(tmp_path / "fixed")) == _expected(layout, {0}, summary=True)
    assert report.summary_source == "after DataEnd"
    assert report.lost_exact and report.lost_counts == {LIGHTS: 1}


def _random_damage(layout: Layout, data: bytes, rng: np.random.Generator,
                   ) -> tuple[list[tuple[int, bytes]], int | None, set[int]]:
    """1-3 damages (flipped byte of the compressed records, of the opcode, of the length or
    of the CRC; or a zeroed span from inside a chunk into the next records), and in one case
    of five a cut; returns the edits, the cut and the indexes of the chunks touched."""
    edits: list[tuple[int, bytes]] = []
    touched: set[int] = set()
    for _ in range(int(rng.integers(1, 4))):
        i = int(rng.integers(len(layout.chunks)))
        chunk = layout.chunks[i]
        kind = int(rng.integers(5))
        if kind == 4:
            offset = int(rng.integers(chunk.data_start, chunk.end))
            span = min(int(rng.integers(1, 2 * (chunk.end - chunk.start))),
                       layout.data_end - offset)
            edits.append((offset, bytes(span)))
            touched |= {j for j, c in enumerate(layout.chunks)
                        if c.start < offset + span and offset < c.end}
            continue
        offset = (int(rng.integers(chunk.data_start, chunk.end)) if kind == 0
                  else chunk.start if kind == 1
                  else chunk.start + 1 + int(rng.integers(8)) if kind == 2
                  else chunk.start + 9 + 24 + int(rng.integers(4)))  # the CRC
        edits.append(_flip(data, offset))
        touched.add(i)
    cut = None
    if rng.random() < 0.2:
        i = int(rng.integers(len(layout.chunks)))
        cut = int(rng.integers(layout.chunks[i].start + 1, layout.chunks[i].end))
        touched |= set(range(i, len(layout.chunks)))
    return edits, cut, touched


SWEEP_SEED = 11
SWEEP_COPIES = 30


def test_randomised_damage_keeps_every_message_of_untouched_chunks(tmp_path: Path) -> None:
    """30 damaged copies (seeded); kept == the messages of untouched chunks (whose channel
    is defined somewhere readable), byte for byte, and the losses counted exactly whenever
    the summary survived."""
    layout = _layered_bag(tmp_path / "ok")
    data = layout.mcap.read_bytes()
    rng = np.random.default_rng(SWEEP_SEED)
    total_kept = total_possible = 0
    for copy in range(SWEEP_COPIES):
        edits, cut, touched = _random_damage(layout, data, rng)
        source = _damaged_copy(layout, tmp_path / f"copy{copy}", edits, cut=cut)
        report = recover_bag(source, tmp_path / f"fixed{copy}")
        kept = _kept(tmp_path / f"fixed{copy}")
        expected = _expected(layout, touched, summary=cut is None)
        assert set(kept) == expected, (copy, edits, cut)
        assert all(kept[t] == layout.messages[t] for t in kept)
        assert report.damage, (copy, "damage must never be 'none'")
        if cut is None:
            assert report.lost_exact
            assert report.lost_counts == _lost_by_topic(layout, set(kept))
        total_kept += len(kept)
        total_possible += len(expected)
    assert total_kept == total_possible
    print(f"sweep: kept {total_kept} of {total_possible} messages in untouched chunks")
