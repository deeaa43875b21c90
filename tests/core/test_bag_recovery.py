"""Tests of fingerps_recon.mcap_records and fingerps_recon.bag_recovery on files written in
tmp_path: finished, cut mid-chunk, corrupted mid-file, cut at a chunk boundary (a kill)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader

from fingerps_msgs.msg import Burst, LightCalibration
from fingerps_recon.bag_recover import main as bag_recover_main
from fingerps_recon.bag_recovery import BagRecoveryError, recover_bag
from fingerps_recon.mcap_records import McapDamageError, scan_records
from fingerps_recon.session_bag import SessionBagWriter

T0 = 1_700_000_000_000_000_000
BURST = "/fingerps/burst"
LIGHTS = "/fingerps/calibration/lights"
CHUNKS = 6
PER_CHUNK = 3


def _write_bag(path: Path) -> tuple[Path, list[int]]:
    """A bag of CHUNKS chunks of PER_CHUNK bursts each (plus the calibration in the first);
    returns the MCAP path and the file size after each flushed chunk."""
    sizes = []
    with SessionBagWriter(path, chunk_size=1 << 20) as bag:
        bag.add_metadata("fingerps.software", {"package": "fingerps_recon"})
        bag.add_topic(LIGHTS, "fingerps_msgs/msg/LightCalibration", offered_qos_yaml="[]")
        bag.add_topic(BURST, "fingerps_msgs/msg/Burst", offered_qos_yaml="[]")
        bag.write(LIGHTS, serialize_message(LightCalibration(camera_name="cut")),
                  log_time_ns=T0, publish_time_ns=T0)
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
    assert report.message_count == 1 + 2 * PER_CHUNK
    assert report.lost_messages == (CHUNKS - 2) * PER_CHUNK  # the summary says how many
    assert _burst_ids(tmp_path / "fixed") == list(range(2 * PER_CHUNK))


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
