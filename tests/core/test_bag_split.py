"""Bags at kiosk scale: splitting into pieces (rosbag2's max_bagfile_size/duration), reading
and recovering split bags, keeping bags_dir under a size limit, and counting messages lost
before the recorder took them.

Split bags are read back by readers that share no code with the writer: the ``mcap`` reader
(each piece alone) and ``rosbags`` (the bag directory through metadata.yaml).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader
from std_msgs.msg import String

from fingerps_recon.errors import BagRecoveryError, SessionBagError
from fingerps_recon.sessions.bag_reader import SessionBagReader
from fingerps_recon.sessions.bag_recovery import bag_pieces, recover_bag
from fingerps_recon.sessions.rosbag2_qos import qos_profiles_yaml
from fingerps_recon.sessions.sequence_gaps import SequenceGaps
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_recon.sessions.session_retention import enforce_limit, stored_sessions
from fingerps_ros import qos
from fingerps_ros.time_conversion import NS_PER_S

T0 = 1_700_000_000_000_000_000
TOPIC = "/fingerps/chatter"
OTHER = "/fingerps/other"
TYPE = "std_msgs/msg/String"


def _payload(i: int, size: int = 20_000) -> bytes:
    # Incompressible enough that the pieces grow (zstd) as the sizes say.
    return serialize_message(String(data=os.urandom(size // 2).hex()[:size - 8] + f"{i:08d}"))


def _write_bag(path: Path, count: int, *, step_ns: int = 1000, finish: bool = True,
               **limits: int) -> SessionBagWriter:
    bag = SessionBagWriter(path, chunk_size=64 * 1024, **limits)
    bag.start()
    bag.add_topic(TOPIC, TYPE, offered_qos_yaml=qos_profiles_yaml(qos.BURST_QOS))
    bag.add_topic(OTHER, TYPE, offered_qos_yaml=qos_profiles_yaml(qos.OUTPUT_QOS))
    bag.add_metadata("fingerps.software", {"package": "fingerps_recon"})
    for i in range(count):
        bag.write(TOPIC if i % 3 else OTHER, _payload(i), log_time_ns=T0 + i * step_ns,
                  publish_time_ns=T0 + i * step_ns - 1)
    if finish:
        bag.finish()
    return bag


def _metadata(bag_dir: Path) -> dict:
    return yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]


def test_size_limit_splits_into_complete_pieces_listed_in_metadata(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "split", 120, max_bagfile_size=300_000)
    summary = bag.finish()
    names = [p.path.name for p in summary.pieces]
    assert len(names) >= 4
    assert names == [f"split_{i}.mcap" for i in range(len(names))]
    assert sorted(p.name for p in bag.path.iterdir()) == sorted([*names, "metadata.yaml"])
    for piece in summary.pieces:
        # Each piece ends at most one chunk (64 KiB + record overhead) past the limit.
        assert piece.size_bytes == piece.path.stat().st_size <= 300_000 + 80_000
        with open(piece.path, "rb") as stream:  # every piece is a complete MCAP on its own
            reader = make_reader(stream)
            mcap_summary = reader.get_summary()
            assert mcap_summary is not None
            assert mcap_summary.statistics.message_count == piece.message_count
            assert {c.topic for c in mcap_summary.channels.values()} == {TOPIC, OTHER}
            records = {m.name for m in reader.iter_metadata()}
            assert {"fingerps.software", "rosbag2"} <= records
    meta = _metadata(bag.path)
    assert meta["relative_file_paths"] == names
    assert [f["path"] for f in meta["files"]] == names
    assert [f["message_count"] for f in meta["files"]] == [p.message_count for p in summary.pieces]
    assert sum(f["message_count"] for f in meta["files"]) == meta["message_count"] == 120

    with RosbagsReader(bag.path) as reader:  # an independent reader of split bags
        assert reader.message_count == 120
        times = [t for _, t, _ in reader.messages()]
    assert sorted(times) == [T0 + i * 1000 for i in range(120)]
    ours = list(SessionBagReader(bag.path).messages())
    assert [m.log_time_ns for m in ours] == [T0 + i * 1000 for i in range(120)]
    assert SessionBagReader(bag.path).topics() == {TOPIC: TYPE, OTHER: TYPE}


def test_duration_limit_splits_by_log_time(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "timed", 30, step_ns=NS_PER_S,
                     max_bagfile_duration_ns=10 * NS_PER_S)
    pieces = bag.finish().pieces
    assert [p.message_count for p in pieces] == [10, 10, 10]
    assert all(p.duration_ns == 9 * NS_PER_S for p in pieces)
    assert [p.starting_time_ns for p in pieces] == [T0, T0 + 10 * NS_PER_S, T0 + 20 * NS_PER_S]


def test_no_limit_keeps_one_file(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "one", 60)
    assert [p.path.name for p in bag.finish().pieces] == ["one_0.mcap"]


def test_negative_limits_are_refused(tmp_path: Path) -> None:
    with pytest.raises(SessionBagError, match="max_bagfile_size"):
        SessionBagWriter(tmp_path / "bad", max_bagfile_size=-1)


def test_killed_split_recording_is_read_and_recovered_in_piece_order(tmp_path: Path) -> None:
    # A recorder killed while writing piece n: pieces 0..n-1 are complete, piece n has no
    # summary, and there is no metadata.yaml. With 11 pieces or more, sorting the names as
    # text would put _10 before _2.
    bag = _write_bag(tmp_path / "killed", 400, finish=False, max_bagfile_size=150_000)
    bag.flush()  # the open chunk reaches the file, as the recorder's flush_period does
    written = sum(bag.message_counts.values())
    assert len(bag.pieces) >= 11
    assert not (bag.path / "metadata.yaml").exists()
    files = bag_pieces(bag.path)
    assert [f.name for f in files] == [f"killed_{i}.mcap" for i in range(len(files))]

    reader = SessionBagReader(bag.path, raise_on_damage=False)
    times = [m.log_time_ns for m in reader.messages()]
    assert times == [T0 + i * 1000 for i in range(written)]
    assert reader.damage == ()

    report = recover_bag(bag.path, tmp_path / "recovered")
    assert report.message_count == written == 400
    assert report.lost_messages == 0 and report.damage == ()
    assert not report.finished  # the last piece had no summary
    with RosbagsReader(tmp_path / "recovered") as recovered:
        assert recovered.message_count == 400


def test_damage_in_one_piece_is_reported_with_its_name(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "damaged", 120, max_bagfile_size=300_000)
    pieces = bag.finish().pieces
    target = pieces[1].path
    data = bytearray(target.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(64)
    target.write_bytes(bytes(data))
    report = recover_bag(bag.path, tmp_path / "recovered")
    assert report.damage and all(d.reason.startswith("damaged_1.mcap: ") for d in report.damage)
    assert 0 < report.lost_messages < pieces[1].message_count + 1
    assert report.message_count + report.lost_messages == 120
    assert report.lost_exact  # the damaged piece's summary survived


def test_a_missing_listed_piece_is_named(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "gone", 120, max_bagfile_size=300_000)
    bag.pieces[1].path.unlink()
    with pytest.raises(BagRecoveryError, match=r"gone_1\.mcap, which is missing"):
        SessionBagReader(bag.path)


# ---------------------------------------------------------------- bags_dir limit


def _session(bags: Path, name: str, size: int, age_s: int, *, bag: bool = True) -> Path:
    directory = bags / name
    directory.mkdir(parents=True)
    data = directory / (f"{name}_0.mcap" if bag else "notes.txt")
    data.write_bytes(bytes(size))
    stamp = 1_800_000_000 - age_s
    os.utime(data, (stamp, stamp))
    return directory


def test_oldest_sessions_are_removed_first_and_the_current_one_never(tmp_path: Path) -> None:
    bags = tmp_path / "bags"
    oldest = _session(bags, "zz_oldest", 400, age_s=300)  # name sorts last: age decides
    middle = _session(bags, "aa_middle", 400, age_s=200)
    newest = _session(bags, "mm_newest", 400, age_s=100)
    current = _session(bags, "current", 500, age_s=1000)  # being recorded: kept although old
    other = _session(bags, "not_a_bag", 10_000, age_s=5000, bag=False)
    (bags / "loose.mcap").write_bytes(bytes(10_000))  # a file, not a session: untouched

    assert [s.path.name for s in stored_sessions(bags)] == [
        "current", "zz_oldest", "aa_middle", "mm_newest"]
    result = enforce_limit(bags, 1000, keep=current)
    assert [s.path for s in result.removed] == [oldest, middle]
    assert result.total_bytes == 900
    assert newest.exists() and current.exists() and other.exists()
    assert (bags / "loose.mcap").exists()

    # The current session alone over the limit: everything else goes, the current one stays.
    result = enforce_limit(bags, 100, keep=current)
    assert [s.path for s in result.removed] == [newest]
    assert result.total_bytes == 500 > 100 and current.exists()


def test_no_limit_removes_nothing(tmp_path: Path) -> None:
    bags = tmp_path / "bags"
    _session(bags, "a", 400, age_s=10)
    assert enforce_limit(bags, 0).removed == ()
    assert enforce_limit(tmp_path / "missing", 10).total_bytes == 0


# ---------------------------------------------------------------- sequence gaps


def test_sequence_gaps_count_skipped_messages_of_a_single_publisher() -> None:
    gaps = SequenceGaps()
    assert [gaps.observe("/a", n, 1) for n in (5, 6, 9, 10, 14)] == [0, 0, 2, 0, 3]
    assert gaps.lost == {"/a": 5}
    assert gaps.observe("/a", 1, 1) == 0  # a restarted publisher starts over
    assert gaps.observe("/a", 3, 1) == 1
    assert gaps.observe("/b", 7, 2) == 0 and gaps.observe("/b", 20, 2) == 0  # two: not counted
    assert gaps.observe("/c", None, 1) == 0 and gaps.observe("/c", 0, 1) == 0
    assert gaps.lost == {"/a": 6}
