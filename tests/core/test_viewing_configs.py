"""The viewer configs (README "Viewing"): config/foxglove_layout.json (a Foxglove layout) and
config/fingerps.rviz (an rviz2 config) name only topics fingerps publishes, with the QoS it
publishes them with, colour the point cloud by its intensity field (the albedo), use the
driver's frame as the fixed/display frame, and are installed by ``make build``."""

from __future__ import annotations

import filecmp
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy
from std_msgs.msg import Header

from fingerps_recon.sessions.session_topics import TOPIC_TABLE
from fingerps_ros import topics
from fingerps_ros.point_cloud_conversion import points_to_cloud

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "src" / "fingerps_recon" / "config"
INSTALL = ROOT / "install"
INSTALLED_CONFIG = INSTALL / "fingerps_recon" / "share" / "fingerps_recon" / "config"
FILES = ("foxglove_layout.json", "fingerps.rviz")
DRIVER_CONFIG = ROOT / "src" / "fingerps_driver" / "config" / "driver.yaml"

NOT_TOPICS = {"NAMESPACE", "FINGERPRINT_FRAME", "CAPTURE_BURST", "CALIBRATE_LIGHTS",
              "CALIBRATE_FLAT_FIELD"}  # the namespace, a frame_id, services
COMPANIONS = {topics.IMAGE_RAW: "compressed", topics.NORMAL_MAP: "compressed",
              topics.FINGERPRINT: "compressed", topics.DEPTH: "compressedDepth"}
FOXGLOVE_PANELS = {"Image", "3D", "DiagnosticSummary"}
# rviz2's names of the QoS policies (one table each: rclpy's policy enums share values)
RVIZ_RELIABILITY = {ReliabilityPolicy.RELIABLE: "Reliable",
                    ReliabilityPolicy.BEST_EFFORT: "Best Effort"}
RVIZ_DURABILITY = {DurabilityPolicy.VOLATILE: "Volatile",
                   DurabilityPolicy.TRANSIENT_LOCAL: "Transient Local"}
RVIZ_HISTORY = {HistoryPolicy.KEEP_LAST: "Keep Last", HistoryPolicy.KEEP_ALL: "Keep All"}


def absolute(name: str) -> str:
    return name if name.startswith("/") else f"/{topics.NAMESPACE}/{name}"


def published_topics() -> set[str]:
    """Every topic the graph publishes in the default namespace, with the image companions."""
    names = {value for key, value in vars(topics).items()
             if key.isupper() and isinstance(value, str) and key not in NOT_TOPICS}
    return ({absolute(name) for name in names}
            | {absolute(f"{base}/{suffix}") for base, suffix in COMPANIONS.items()})


def driver_frame_id() -> str:
    parameters = yaml.safe_load(DRIVER_CONFIG.read_text())["/fingerps/driver"]["ros__parameters"]
    return parameters["frame_id"]


@pytest.fixture(scope="module")
def layout() -> dict:
    return json.loads((CONFIG / "foxglove_layout.json").read_text())


@pytest.fixture(scope="module")
def rviz() -> dict:
    return yaml.safe_load((CONFIG / "fingerps.rviz").read_text())


def leaves(node: dict | str) -> Iterator[str]:
    """The panel ids of a Foxglove layout tree, checking each split on the way."""
    if isinstance(node, str):
        yield node
        return
    assert set(node) <= {"first", "second", "direction", "splitPercentage"}, node
    assert node["direction"] in ("row", "column")
    assert 0 < node.get("splitPercentage", 50) < 100
    yield from leaves(node["first"])
    yield from leaves(node["second"])


def foxglove_topics(layout: dict) -> set[str]:
    found = set()
    for config in layout["configById"].values():
        image_mode = config.get("imageMode", {})
        found |= {image_mode[k] for k in ("imageTopic", "calibrationTopic") if k in image_mode}
        found |= set(config.get("topics", {}))
        if "topicToRender" in config:
            found.add(config["topicToRender"])
    return found


def rviz_displays(rviz: dict) -> list[dict]:
    return rviz["Visualization Manager"]["Displays"]


def rviz_topics(rviz: dict) -> set[str]:
    found = set()

    def walk(node: object) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "Topic":
                    found.add(value["Value"] if isinstance(value, dict) else value)
                else:
                    walk(value)
        elif isinstance(node, list):
            for item in node:
                walk(item)

    walk(rviz)
    return found


def test_the_layout_has_the_structure_of_a_foxglove_export(layout: dict) -> None:
    assert set(layout) == {"configById", "globalVariables", "userNodes", "playbackConfig",
                           "layout"}
    ids = list(leaves(layout["layout"]))
    assert len(ids) == len(set(ids)), "a panel appears twice in the layout tree"
    assert set(ids) == set(layout["configById"])
    for panel_id in ids:
        kind, _, suffix = panel_id.partition("!")
        assert kind in FOXGLOVE_PANELS and suffix, panel_id
    assert layout["playbackConfig"]["speed"] > 0


def test_every_topic_the_configs_name_is_published(layout: dict, rviz: dict) -> None:
    published = published_topics()
    assert {"/fingerps/normal_map", "/fingerps/points", "/diagnostics",
            "/fingerps/normal_map/compressed", "/fingerps/depth/compressedDepth"} <= published
    assert "/fingerps/capture_burst" not in published
    for name, found in (("foxglove_layout.json", foxglove_topics(layout)),
                        ("fingerps.rviz", rviz_topics(rviz))):
        assert found, name
        assert found <= published, f"{name} names {sorted(found - published)}"


def test_the_foxglove_layout_shows_each_output(layout: dict) -> None:
    panels = layout["configById"]
    images = {c["imageMode"]["imageTopic"] for i, c in panels.items() if i.startswith("Image!")}
    assert {"/fingerps/normal_map/compressed", "/fingerps/fingerprint/compressed",
            "/fingerps/image_raw"} == images
    # Foxglove's Image panel decodes png/jpeg CompressedImage but not compressedDepth
    assert not any(topic.endswith("compressedDepth") for topic in images)
    diagnostics = [c for i, c in panels.items() if i.startswith("DiagnosticSummary!")]
    assert [c["topicToRender"] for c in diagnostics] == [topics.DIAGNOSTICS]


def test_the_3d_panels_colour_the_cloud_in_the_drivers_frame(layout: dict) -> None:
    frame = driver_frame_id()
    views = {i: c for i, c in layout["configById"].items() if i.startswith("3D!")}
    fields = set()
    for panel_id, config in views.items():
        assert config["followTf"] == frame, panel_id
        cloud = config["topics"][absolute(topics.POINTS)]
        assert cloud["visible"] is True
        assert cloud["colorMode"] == "colormap" and cloud["colorMap"] in ("turbo", "rainbow")
        fields.add(cloud["colorField"])
        camera = config["cameraState"]
        assert camera["near"] < 0.01 < camera["distance"] < camera["far"], (
            "the finger is ~9 cm from the camera: near must not clip it")
    # the albedo cloud, and the depth (32FC1 is grey in Foxglove's Image panel: by z here)
    assert fields == {"intensity", "z"}


def test_the_cloud_carries_the_field_the_configs_colour_by() -> None:
    header = Header(frame_id=driver_frame_id())
    cloud = points_to_cloud(np.zeros((2, 3), np.float32), np.ones(2, np.float32), header=header)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "intensity"]


def test_the_rviz_config_parses_with_its_displays_named(rviz: dict) -> None:
    assert {"Panels", "Visualization Manager", "Window Geometry"} <= set(rviz)
    manager = rviz["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == driver_frame_id()
    displays = rviz_displays(rviz)
    names = [d["Name"] for d in displays]
    assert len(names) == len(set(names))
    assert {"Point cloud (albedo)", "Normal map", "Fingerprint", "Depth"} <= set(names)
    for display in displays:
        assert display["Class"].startswith("rviz_default_plugins/"), display["Name"]
        assert display["Enabled"] == display["Value"], display["Name"]
    cloud = next(d for d in displays if d["Name"] == "Point cloud (albedo)")
    assert cloud["Class"] == "rviz_default_plugins/PointCloud2" and cloud["Enabled"]
    assert cloud["Topic"]["Value"] == absolute(topics.POINTS)
    assert (cloud["Color Transformer"], cloud["Channel Name"]) == ("Intensity", "intensity")
    assert manager["Views"]["Current"]["Near Clip Distance"] < 0.01


def test_the_rviz_displays_subscribe_with_the_publishers_qos(rviz: dict) -> None:
    by_name = {absolute(name): entry.qos for name, entry in TOPIC_TABLE.items()}
    for display in rviz_displays(rviz):
        topic = display["Topic"]
        profile = by_name[topic["Value"]]
        assert topic["Reliability Policy"] == RVIZ_RELIABILITY[profile.reliability], (
            display["Name"])
        assert topic["Durability Policy"] == RVIZ_DURABILITY[profile.durability], (
            display["Name"])
        assert topic["History Policy"] == RVIZ_HISTORY[profile.history], display["Name"]
        assert topic["Depth"] == profile.depth, display["Name"]


def test_make_build_installs_both_configs() -> None:
    for name in FILES:
        assert (CONFIG / name).is_file()
    if not INSTALL.is_dir():
        pytest.skip("install/ is absent: the workspace is not built (make build)")
    for name in FILES:
        installed = INSTALLED_CONFIG / name
        assert installed.is_file(), f"{installed} missing: run make build"
        assert filecmp.cmp(installed, CONFIG / name, shallow=False), f"{installed} is stale"
