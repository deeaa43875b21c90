"""recon_node's parameter table (``reconstruction.parameters``) on a node of this process
(``ros_node``), without a graph: config/recon.yaml lists every one with its default, the
settings read from them, the checks that refuse a bad value, and ``threads`` followed at run
time."""

from __future__ import annotations

from pathlib import Path

import yaml
from rclpy.node import Node
from rclpy.parameter import Parameter

from fingerps_recon.photometric.kernel_threads import set_thread_limit, thread_limit
from fingerps_recon.photometric.pipeline import Model, ReconstructionOptions
from fingerps_recon.reconstruction.burst_intake import BurstLimits
from fingerps_recon.reconstruction.parameters import PARAMETERS, follow_threads, read_settings
from fingerps_ros.parameters import declare_parameters

CONFIG = Path(__file__).resolve().parents[2] / "src/fingerps_recon/config/recon.yaml"


def test_the_config_file_lists_every_parameter_with_its_default() -> None:
    listed = yaml.safe_load(CONFIG.read_text())["/fingerps/recon"]["ros__parameters"]
    ours = {name: value for name, value in listed.items() if "." not in name}  # not companions
    assert ours == {row.name: row.default for row in PARAMETERS}
    assert all(row.description for row in PARAMETERS)


def test_the_defaults_give_the_default_settings(ros_node: Node) -> None:
    declare_parameters(ros_node, PARAMETERS)
    settings = read_settings(ros_node)
    assert settings.options == ReconstructionOptions(model=Model.HK, enhance=True)
    assert settings.limits == BurstLimits() and settings.mono16_full_scale == 4095.0


def test_bad_values_are_refused_with_a_reason(ros_node: Node) -> None:
    declare_parameters(ros_node, PARAMETERS)
    for name, value, reason in (("w", 8, "must be odd"), ("model", "phong", "must be one of"),
                                ("projection", "fisheye", "must be one of")):
        result = ros_node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and reason in result.reason
    assert ros_node.set_parameters([Parameter("model", value="lambert")])[0].successful
    assert read_settings(ros_node).options.model is Model.LAMBERT


def test_threads_is_followed_from_the_next_burst_on(ros_node: Node) -> None:
    try:
        declare_parameters(ros_node, PARAMETERS)
        follow_threads(ros_node)
        ros_node.set_parameters([Parameter("threads", value=1)])
        assert thread_limit() == 1
    finally:
        set_thread_limit(0)  # the default: every core
