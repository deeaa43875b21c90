"""Tests of fingerps_recon.sessions.message_definition and fingerps_recon.sessions.session_bag.

Bags are written in tmp_path from real serialized messages and read back by readers that
share no code with the writer: the ``mcap`` reader, ``mcap_ros2``'s decoder (decodes from the
schema text alone) and ``rosbags`` (reads the bag directory through metadata.yaml).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
import yaml
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Vector3
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from fingerps_msgs.msg import Burst, LightCalibration, TaggedFrame
from fingerps_recon.errors import FingerpsReconError, MessageDefinitionError, SessionBagError
from fingerps_recon.sessions.bag_metadata import INT64_MAX
from fingerps_recon.sessions.message_definition import (
    SEPARATOR,
    load_message_definition,
    message_definition,
    type_description_hash,
)
from fingerps_recon.sessions.rosbag2_qos import QosProfileFields, qos_profiles_yaml
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_ros import qos

T0 = 1_700_000_000_000_000_000
BURST_TYPE = "fingerps_msgs/msg/Burst"
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
LIGHTS_TYPE = "fingerps_msgs/msg/LightCalibration"


# ---------------------------------------------------------------- messages


def _header(ns: int) -> Header:
    return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="camera_optical")


def _burst(burst_id: int) -> Burst:
    frames = []
    for led in range(2):
        image = Image(header=_header(T0 + led), height=2, width=3, encoding="mono8", step=3,
                      data=bytes(range(10 * led, 10 * led + 6)))
        frames.append(TaggedFrame(header=_header(T0 + led), burst_id=burst_id, led_index=led,
                                  led_count=2, exposure_time=0.01, led_intensity=0.5,
                                  image=image))
    info = CameraInfo(header=_header(T0), height=2, width=3, distortion_model="plumb_bob",
                      d=[0.1, 0.0, 0.0, 0.0, 0.0], k=[800.0, 0, 1.5, 0, 800.0, 1.0, 0, 0, 1])
    return Burst(header=_header(T0 + 2), burst_id=burst_id, frames=frames,
                 has_dark_frame=False, camera_info=info)


def _cloud() -> PointCloud2:
    fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
              for i, n in enumerate(("x", "y", "z", "intensity"))]
    points = [(0.001, -0.002, 0.09, 0.5), (0.002, 0.001, 0.091, 0.75)]
    data = b"".join(struct.pack("<4f", *p) for p in points)
    return PointCloud2(header=_header(T0), height=1, width=2, fields=fields,
                       is_bigendian=False, point_step=16, row_step=32, data=data,
                       is_dense=True)


def _lights() -> LightCalibration:
    return LightCalibration(
        header=_header(T0), camera_name="fingerps_camera",
        directions=[Vector3(x=0.1, y=0.2, z=-0.97), Vector3(x=-0.1, y=0.2, z=-0.97)],
        relative_intensities=[1.0, 0.93], residuals=[0.2, 0.3], sphere_radius=0.005,
        sphere_center=Point(x=0.0, y=0.0, z=0.09), edge_fit_residual=0.4)


def _msg_file(type_name: str) -> str:
    package, _, name = type_name.split("/")
    from ament_index_python.packages import get_package_share_directory
    return (Path(get_package_share_directory(package)) / "msg" / f"{name}.msg").read_text()


def _sections(text: str) -> tuple[str, list[tuple[str, str]]]:
    """Split a full definition into (root text, [(header line, text), ...])."""
    parts = text.split("\n" + SEPARATOR + "\n")
    nested = []
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        nested.append((head, body))
    return parts[0], nested


# ---------------------------------------------------------------- message definitions


def test_burst_definition_has_every_nested_type_once_depth_first() -> None:
    root, nested = _sections(message_definition(BURST_TYPE))
    assert root == _msg_file(BURST_TYPE)
    # Dependencies of each file in sorted order, depth first, each type once (rosbag2).
    assert [head for head, _ in nested] == [
        "MSG: fingerps_msgs/TaggedFrame",
        "MSG: sensor_msgs/Image",
        "MSG: std_msgs/Header",
        "MSG: builtin_interfaces/Time",
        "MSG: sensor_msgs/CameraInfo",
        "MSG: sensor_msgs/RegionOfInterest",
    ]
    for head, body in nested:
        package, name = head.removeprefix("MSG: ").split("/")
        assert body == _msg_file(f"{package}/msg/{name}")
    assert "uint8 LED_DARK = 255" in message_definition(BURST_TYPE)  # constants kept


def test_definition_accepts_both_name_forms_and_hash_is_read() -> None:
    assert message_definition("fingerps_msgs/Burst") == message_definition(BURST_TYPE)
    assert load_message_definition(CLOUD_TYPE).encoding == "ros2msg"
    digest = type_description_hash(BURST_TYPE)
    assert digest.startswith("RIHS01_") and len(digest) == 7 + 64


@pytest.mark.parametrize("name", ["Burst", "fingerps_msgs/srv/CaptureBurst", "a/b/c/d"])
def test_bad_type_names_are_refused(name: str) -> None:
    with pytest.raises(MessageDefinitionError, match="package/msg/Type"):
        message_definition(name)


def test_unknown_package_says_what_to_do() -> None:
    with pytest.raises(MessageDefinitionError, match="ament index"):
        message_definition("no_such_msgs/msg/Thing")
    assert issubclass(MessageDefinitionError, FingerpsReconError)


@pytest.fixture
def fake_prefix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An ament prefix with the test interfaces of rosbag2's own definition tests."""
    prefix = tmp_path / "prefix"
    index = prefix / "share" / "ament_index" / "resource_index" / "packages"
    index.mkdir(parents=True)
    (index / "defs").write_text("")
    msg = prefix / "share" / "defs" / "msg"
    msg.mkdir(parents=True)
    (msg / "BasicMsg.msg").write_text("float32 c\n")
    (msg / "ComplexMsg.msg").write_text("defs/BasicMsg b\n")
    (msg / "Multi.msg").write_text(
        "# comment naming defs/Ignored\nZeta z\nBasicMsg[<=3] b\nint32 X = 4\n"
        "defs/Zeta[2] again\nstring<=5 short\n")
    (msg / "Zeta.msg").write_text("BasicMsg inner\n")
    (msg / "BasicIdl.idl").write_text(
        "module defs {\n  module msg {\n    struct BasicIdl {\n        float x;\n    };\n"
        "  };\n};\n")
    (msg / "ComplexIdl.idl").write_text(
        '#include "defs/msg/BasicIdl.idl"\n\nmodule defs {\n  module msg {\n'
        "    struct ComplexIdl {\n      defs::msg::BasicIdl a;\n    };\n  };\n};\n")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    return prefix


def test_msg_format_matches_rosbag2(fake_prefix: Path) -> None:
    # Expected text of rosbag2 jazzy test_local_message_definition_source.cpp can_find_msg_deps.
    assert message_definition("defs/msg/ComplexMsg") == (
        "defs/BasicMsg b\n"
        "\n"
        "================================================================================\n"
        "MSG: defs/BasicMsg\n"
        "float32 c\n")


def test_package_less_names_dedup_and_sorted_order(fake_prefix: Path) -> None:
    text = message_definition("defs/msg/Multi")
    root, nested = _sections(text)
    assert root == (fake_prefix / "share/defs/msg/Multi.msg").read_text()
    # BasicMsg before Zeta (sorted), each once although used twice; comments are no fields.
    assert [head for head, _ in nested] == ["MSG: defs/BasicMsg", "MSG: defs/Zeta"]


def test_idl_fallback_matches_rosbag2(fake_prefix: Path) -> None:
    definition = load_message_definition("defs/msg/ComplexIdl")
    assert definition.encoding == "ros2idl"
    idl = fake_prefix / "share/defs/msg"
    assert definition.text == (
        SEPARATOR + "\nIDL: defs/msg/ComplexIdl\n" + (idl / "ComplexIdl.idl").read_text()
        + "\n" + SEPARATOR + "\nIDL: defs/msg/BasicIdl\n" + (idl / "BasicIdl.idl").read_text())
    assert type_description_hash("defs/msg/ComplexIdl") == ""  # no .json: unknown hash


# ---------------------------------------------------------------- QoS YAML


def test_qos_yaml_is_rosbag2_version_9() -> None:
    expected = (
        "- history: keep_last\n  depth: 1\n  reliability: reliable\n"
        "  durability: transient_local\n  deadline:\n    sec: 0\n    nsec: 0\n"
        "  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: system_default\n"
        "  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
        "  avoid_ros_namespace_conventions: false")
    assert qos_profiles_yaml(qos.CALIBRATION_QOS) == expected
    assert qos_profiles_yaml([QosProfileFields.from_profile(qos.CALIBRATION_QOS)]) == expected
    assert qos_profiles_yaml([]) == "[]"
    infinite = QosProfileFields(history="unknown", depth=0, deadline_ns=INT64_MAX)
    node = yaml.safe_load(qos_profiles_yaml([infinite, QosProfileFields()]))
    assert len(node) == 2
    assert node[0]["deadline"] == {"sec": 9223372036, "nsec": 854775807}
    assert node[0]["history"] == "unknown" and node[1]["history"] == "keep_last"


def test_qos_policy_names_are_checked() -> None:
    with pytest.raises(SessionBagError, match="reliability"):
        qos_profiles_yaml(QosProfileFields(reliability="sometimes"))


# ---------------------------------------------------------------- bag round trip


@pytest.fixture
def session(tmp_path: Path) -> dict:
    """A finished bag with bursts, a point cloud and a light calibration."""
    burst_qos = qos_profiles_yaml(qos.BURST_QOS)
    originals = {
        "/fingerps/burst": [_burst(7), _burst(8)],
        "/fingerps/points": [_cloud()],
        "/fingerps/calibration/lights": [_lights()],
    }
    bag = SessionBagWriter(tmp_path / "bags" / "session_a", custom_data={"rig": "sim"})
    bag.start()
    bag.add_topic("/fingerps/calibration/lights", LIGHTS_TYPE,
                  offered_qos_yaml=qos_profiles_yaml(qos.CALIBRATION_QOS))
    bag.add_topic("/fingerps/burst", BURST_TYPE, offered_qos_yaml=burst_qos)
    bag.add_topic("/fingerps/points", CLOUD_TYPE,
                  offered_qos_yaml=qos_profiles_yaml(qos.OUTPUT_QOS))
    bag.add_metadata("fingerps.software", {"package": "fingerps_recon", "version": "0.1.0"})
    # CDR padding bytes are not defined: compare with the bytes written, not a new serialization.
    written = {t: [serialize_message(m) for m in ms] for t, ms in originals.items()}
    bag.write("/fingerps/calibration/lights", written["/fingerps/calibration/lights"][0],
              log_time_ns=T0, publish_time_ns=T0 - 5)
    for i, data in enumerate(written["/fingerps/burst"]):
        bag.write("/fingerps/burst", data, log_time_ns=T0 + 10 + i, publish_time_ns=T0 + 9 + i)
    bag.write("/fingerps/points", written["/fingerps/points"][0], log_time_ns=T0 + 100,
              publish_time_ns=T0 + 99)
    summary = bag.finish()
    return {"bag": bag, "summary": summary, "originals": originals, "written": written,
            "burst_qos": burst_qos}


def test_bag_directory_is_laid_out_as_rosbag2(session: dict) -> None:
    bag = session["bag"]
    assert sorted(p.name for p in bag.path.iterdir()) == ["metadata.yaml", "session_a_0.mcap"]
    assert bag.mcap_path == bag.path / "session_a_0.mcap"
    summary = session["summary"]
    assert summary.message_counts == {"/fingerps/calibration/lights": 1, "/fingerps/burst": 2,
                                      "/fingerps/points": 1}
    assert summary.message_count == 4
    assert summary.starting_time_ns == T0 and summary.duration_ns == 100


def test_mcap_reader_sees_ros2_profile_schemas_channels_and_summary(session: dict) -> None:
    with open(session["bag"].mcap_path, "rb") as stream:
        reader = make_reader(stream)
        header = reader.get_header()
        assert header.profile == "ros2"
        assert "fingerps_recon" in header.library
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 4
        assert summary.statistics.message_start_time == T0
        assert summary.statistics.message_end_time == T0 + 100
        schemas = {s.name: s for s in summary.schemas.values()}
        assert set(schemas) == {BURST_TYPE, CLOUD_TYPE, LIGHTS_TYPE}
        for name, schema in schemas.items():
            assert schema.encoding == "ros2msg"
            assert schema.data.decode() == message_definition(name)
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == set(session["originals"])
        for topic, channel in channels.items():
            assert channel.message_encoding == "cdr"
            assert set(channel.metadata) == {"offered_qos_profiles", "topic_type_hash"}
            assert isinstance(yaml.safe_load(channel.metadata["offered_qos_profiles"]), list)
            assert channel.metadata["topic_type_hash"] == type_description_hash(
                summary.schemas[channel.schema_id].name)
            assert summary.statistics.channel_message_counts[channel.id] == len(
                session["originals"][topic])
        assert channels["/fingerps/burst"].metadata["offered_qos_profiles"] == \
            session["burst_qos"]
        assert summary.chunk_indexes and all(c.compression == "zstd"
                                             for c in summary.chunk_indexes)
        assert all(c.message_index_offsets for c in summary.chunk_indexes)  # message index
        records = {m.name: m.metadata for m in reader.iter_metadata()}
        assert records["fingerps.software"] == {"package": "fingerps_recon", "version": "0.1.0"}
        embedded = yaml.safe_load(records["rosbag2"]["serialized_metadata"])
        assert embedded["version"] == 9 and embedded["message_count"] == 4
        times = [(m.log_time, m.publish_time) for _, _, m in reader.iter_messages()]
        assert times[0] == (T0, T0 - 5)


def test_mcap_ros2_decodes_custom_types_from_schema_text_alone(session: dict) -> None:
    decoded: dict[str, list] = {}
    with open(session["bag"].mcap_path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, message, value in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append((message, value))
            index = len(decoded[channel.topic]) - 1
            assert message.data == session["written"][channel.topic][index]  # bytes as given
    bursts = [v for _, v in decoded["/fingerps/burst"]]
    assert [b.burst_id for b in bursts] == [7, 8]
    assert [f.led_index for f in bursts[0].frames] == [0, 1]
    assert bytes(bursts[0].frames[1].image.data) == bytes(range(10, 16))
    assert bursts[0].frames[1].image.header.stamp.nanosec == (T0 + 1) % 10**9
    assert list(bursts[0].camera_info.k) == [800.0, 0, 1.5, 0, 800.0, 1.0, 0, 0, 1]
    cloud = decoded["/fingerps/points"][0][1]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity"]
    assert struct.unpack("<4f", bytes(cloud.data)[:16])[2] == pytest.approx(0.09)
    lights = decoded["/fingerps/calibration/lights"][0][1]
    assert lights.camera_name == "fingerps_camera"
    assert [d.z for d in lights.directions] == pytest.approx([-0.97, -0.97])
    assert lights.sphere_center.z == pytest.approx(0.09)


def test_rosbags_reads_the_directory_and_the_messages(session: dict) -> None:
    originals = session["originals"]
    store = get_typestore(Stores.ROS2_JAZZY)
    with RosbagsReader(session["bag"].path) as reader:
        assert reader.message_count == 4
        assert reader.start_time == T0
        connections = {c.topic: c for c in reader.connections}
        assert {t: c.msgcount for t, c in connections.items()} == {
            t: len(m) for t, m in originals.items()}
        assert connections["/fingerps/burst"].msgtype == BURST_TYPE
        assert connections["/fingerps/burst"].digest == type_description_hash(BURST_TYPE)
        lights_qos = connections["/fingerps/calibration/lights"].ext.offered_qos_profiles
        assert lights_qos[0].durability.name == "TRANSIENT_LOCAL" and lights_qos[0].depth == 1
        for connection in reader.connections:
            store.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
        seen: dict[str, int] = {}
        for connection, timestamp, raw in reader.messages():
            index = seen.get(connection.topic, 0)
            seen[connection.topic] = index + 1
            original = originals[connection.topic][index]
            assert raw == session["written"][connection.topic][index]
            value = store.deserialize_cdr(raw, connection.msgtype)
            if connection.topic == "/fingerps/burst":
                assert value.burst_id == original.burst_id
                assert value.frames[1].image.data.tobytes() == bytes(range(10, 16))
                assert timestamp == T0 + 10 + index
        assert seen == {t: len(m) for t, m in originals.items()}


def test_metadata_yaml_is_version_9(session: dict) -> None:
    text = (session["bag"].path / "metadata.yaml").read_text()
    info = yaml.safe_load(text)["rosbag2_bagfile_information"]
    assert list(info) == [
        "version", "storage_identifier", "duration", "starting_time", "message_count",
        "topics_with_message_count", "compression_format", "compression_mode",
        "relative_file_paths", "files", "custom_data", "ros_distro"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["duration"] == {"nanoseconds": 100}
    assert info["starting_time"] == {"nanoseconds_since_epoch": T0}
    assert info["message_count"] == 4
    assert info["compression_format"] == "" and info["compression_mode"] == ""
    assert info["relative_file_paths"] == ["session_a_0.mcap"]
    assert info["files"] == [{"path": "session_a_0.mcap",
                              "starting_time": {"nanoseconds_since_epoch": T0},
                              "duration": {"nanoseconds": 100}, "message_count": 4}]
    assert info["custom_data"] == {"rig": "sim"} and info["ros_distro"] == "jazzy"
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    burst = topics["/fingerps/burst"]
    assert burst["message_count"] == 2
    assert list(burst["topic_metadata"]) == [
        "name", "type", "serialization_format", "offered_qos_profiles",
        "type_description_hash"]
    assert burst["topic_metadata"]["type"] == BURST_TYPE
    assert burst["topic_metadata"]["serialization_format"] == "cdr"
    # Version 9: the profiles are a YAML list (not a string), policies by name.
    assert burst["topic_metadata"]["offered_qos_profiles"] == yaml.safe_load(
        session["burst_qos"])
    assert burst["topic_metadata"]["type_description_hash"] == type_description_hash(
        BURST_TYPE)
    assert "\n    - topic_metadata:\n        name: " in text  # yaml-cpp's indentation


def test_messages_deserialize_with_rclpy_after_the_round_trip(session: dict) -> None:
    with open(session["bag"].mcap_path, "rb") as stream:
        reader = make_reader(stream)
        bursts = [deserialize_message(m.data, Burst)
                  for _, c, m in reader.iter_messages(topics=["/fingerps/burst"])]
    assert bursts == session["originals"]["/fingerps/burst"]


# ---------------------------------------------------------------- lifecycle and errors


def test_finish_twice_is_safe_and_writing_after_is_refused(tmp_path: Path) -> None:
    bag = SessionBagWriter(tmp_path / "twice")
    bag.start()
    bag.add_topic("/fingerps/points", CLOUD_TYPE, offered_qos_yaml="")
    first = bag.finish()
    assert bag.finish() is first
    assert first.message_count == 0 and first.starting_time_ns == INT64_MAX
    with pytest.raises(SessionBagError, match="finished"):
        bag.write("/fingerps/points", b"", log_time_ns=1, publish_time_ns=1)
    with RosbagsReader(bag.path) as reader:  # an empty bag is still a valid bag
        assert reader.message_count == 0
    assert SessionBagWriter(tmp_path / "never").finish().message_count == 0
    assert not (tmp_path / "never").exists()


def test_context_manager_finishes_even_on_error(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError), SessionBagWriter(tmp_path / "ctx") as bag:
        bag.add_topic("/fingerps/points", CLOUD_TYPE, offered_qos_yaml="[]")
        bag.write("/fingerps/points", serialize_message(_cloud()), log_time_ns=5,
                  publish_time_ns=5)
        raise RuntimeError("boom")
    assert (tmp_path / "ctx" / "metadata.yaml").exists()
    with RosbagsReader(tmp_path / "ctx") as reader:
        assert reader.message_count == 1


def test_existing_directory_is_refused(tmp_path: Path) -> None:
    (tmp_path / "taken").mkdir()
    with pytest.raises(SessionBagError, match="already exists"):
        SessionBagWriter(tmp_path / "taken").start()


def test_uncreatable_directory_is_refused(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")
    with pytest.raises(SessionBagError, match="cannot create bag directory"):
        SessionBagWriter(tmp_path / "a_file" / "session").start()
    assert issubclass(SessionBagError, FingerpsReconError)


def test_misuse_is_refused_with_a_reason(tmp_path: Path) -> None:
    bag = SessionBagWriter(tmp_path / "misuse")
    with pytest.raises(SessionBagError, match="not started"):
        bag.add_metadata("x", {"a": "b"})
    bag.start()
    with pytest.raises(SessionBagError, match="add_topic"):
        bag.write("/nowhere", b"\0", log_time_ns=1, publish_time_ns=1)
    with pytest.raises(SessionBagError, match="no_such_msgs"):
        bag.add_topic("/x", "no_such_msgs/msg/Thing", offered_qos_yaml="[]")
    with pytest.raises(SessionBagError, match="list of QoS"):
        bag.add_topic("/x", CLOUD_TYPE, offered_qos_yaml="reliability: reliable")
    bag.add_topic("/x", CLOUD_TYPE, offered_qos_yaml="[]")
    with pytest.raises(SessionBagError, match="already added"):
        bag.add_topic("/x", CLOUD_TYPE, offered_qos_yaml="[]")
    with pytest.raises(SessionBagError, match="reserved"):
        bag.add_metadata("rosbag2", {"a": "b"})
    with pytest.raises(SessionBagError, match="strings"):
        bag.add_metadata("numbers", {"a": 1})  # type: ignore[dict-item]
    with pytest.raises(SessionBagError, match="already started"):
        bag.start()
    bag.finish()


def _messages_on_disk(path: Path) -> int:
    """Messages a reader gets from a file that was never finished (no summary, no footer)."""
    count = 0
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream, skip_magic=False).records:
                count += isinstance(record, Message)
        except (McapError, struct.error, EOFError):
            pass  # the file just ends: what a killed process leaves
    return count


def test_a_killed_writer_loses_at_most_the_open_chunk(tmp_path: Path) -> None:
    bag = SessionBagWriter(tmp_path / "killed", chunk_size=64 * 1024)
    bag.start()
    bag.add_topic("/fingerps/burst", BURST_TYPE, offered_qos_yaml="[]")
    data = serialize_message(_burst(1)) + bytes(30_000)  # bytes only: CDR not checked
    for i in range(10):  # 10 x ~30 kB: the 64 kB chunks close by themselves
        bag.write("/fingerps/burst", data, log_time_ns=T0 + i, publish_time_ns=T0 + i)
    on_disk = _messages_on_disk(bag.mcap_path)
    assert 10 - on_disk <= 64 * 1024 // len(data) + 1 and on_disk > 0
    bag.write("/fingerps/burst", data, log_time_ns=T0 + 10, publish_time_ns=T0 + 10)
    bag.flush()  # closes the open chunk early
    assert _messages_on_disk(bag.mcap_path) == 11
    bag.finish()


def test_the_chunks_are_zstd_level_1_as_ros2_bag_record_writes_them(tmp_path: Path) -> None:
    """The mcap Python writer's chunks at zstd level 1 (sessions/zstd_level.py), not its
    library default 3: each chunk's bytes are level 1's compression of its content."""
    import zstandard
    from mcap.records import Chunk

    bag = SessionBagWriter(tmp_path / "levels", chunk_size=256 * 1024)
    bag.start()
    bag.add_topic("/fingerps/burst", BURST_TYPE, offered_qos_yaml="[]")
    rng = np.random.default_rng(5)
    for i in range(4):  # image-like bytes: a smooth ramp with noise, compressible
        ramp = (np.arange(200_000) // 700 + rng.integers(0, 6, 200_000)) % 256
        bag.write("/fingerps/burst", serialize_message(_burst(i)) + ramp.astype(np.uint8).tobytes(),
                  log_time_ns=T0 + i, publish_time_ns=T0 + i)
    bag.finish()
    chunks = []
    with open(bag.mcap_path, "rb") as stream:
        chunks = [r for r in StreamReader(stream, skip_magic=False, emit_chunks=True).records
                  if isinstance(r, Chunk)]
    assert chunks and all(c.compression == "zstd" for c in chunks)
    for chunk in chunks:
        content = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size)
        assert len(content) == chunk.uncompressed_size
        level_1 = zstandard.ZstdCompressor(level=1).compress(content)
        assert chunk.data == level_1
        assert zstandard.ZstdCompressor(level=3).compress(content) != level_1
