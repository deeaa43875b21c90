"""bringup as a real process: the whole graph from one parameter file, Ctrl-C stops it
cleanly (recorder's bag finalised, exit 0) however many signals follow; a bad parameter file
stops it naming the key, and a node refusing a parameter stops the others; each package's
config/<node>.yaml loads in its node and lists every parameter it has."""

from __future__ import annotations

import re
import signal
from pathlib import Path

import pytest
import yaml
from ament_index_python.packages import get_package_share_directory
from rcl_interfaces.msg import ParameterType
from rcl_interfaces.srv import GetParameters, ListParameters
from rclpy.node import Node

from fingerps_ros import topics

NS = "/" + topics.NAMESPACE
NODES = ("driver", "calib", "recon", "recorder", "scan")
CONFIGS = {"driver": ("fingerps_driver", "driver.yaml"),
           "calib": ("fingerps_calib", "calib.yaml"),
           "recon": ("fingerps_recon", "recon.yaml"),
           "recorder": ("fingerps_recon", "recorder.yaml"),
           "scan": ("fingerps_recon", "scan.yaml")}
ROS_DEFAULTS = {"use_sim_time", "start_type_description_service"}


def _config(package: str, name: str) -> Path:
    return Path(get_package_share_directory(package)) / "config" / name


def _write(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def _start_and_stop(bringup, ros_node: Node) -> str:
    for name in NODES:
        bringup.wait_in_graph(ros_node, name, NS, timeout=60.0)
    bringup.send_signal(signal.SIGINT)
    assert bringup.wait(timeout=40.0) == 0, bringup.output
    return bringup.output


def test_bringup_starts_the_graph_and_ctrl_c_stops_it_cleanly(
        ros_node: Node, start_node, tmp_path: Path) -> None:
    params = yaml.safe_load(_config("fingerps_driver", "fingerps_sim.yaml").read_text())
    params["/fingerps/recorder"]["ros__parameters"]["bags_dir"] = str(tmp_path / "bags")
    bringup = start_node("fingerps_driver", "bringup", "--params",
                         str(_write(tmp_path / "sim.yaml", params)))
    output = _start_and_stop(bringup, ros_node)
    assert re.search(r"stopped: driver_node 0, calib_node 0, recon_node 0, recorder_node 0, "
                     r"scan_node 0", output), output
    (session,) = list((tmp_path / "bags").iterdir())
    assert (session / "metadata.yaml").is_file()  # the recorder finalised its bag


def test_signals_repeated_while_bringup_stops_change_nothing(
        ros_node: Node, start_node, tmp_path: Path) -> None:
    """Ctrl-C, then SIGTERM and SIGINT in turn every 10 ms until bringup has exited (a second
    Ctrl-C, the process group's SIGINT, a supervisor's SIGTERM): still one clean stop."""
    params = yaml.safe_load(_config("fingerps_driver", "fingerps_sim.yaml").read_text())
    params["/fingerps/recorder"]["ros__parameters"]["bags_dir"] = str(tmp_path / "bags")
    bringup = start_node("fingerps_driver", "bringup", "--params",
                         str(_write(tmp_path / "sim.yaml", params)))
    for name in NODES:
        bringup.wait_in_graph(ros_node, name, NS, timeout=60.0)
    bringup.signal_until_exit(timeout=40.0)
    assert bringup.wait(timeout=10.0) == 0, bringup.output
    assert "Traceback" not in bringup.output, bringup.output
    assert re.search(r"stopped: driver_node 0, calib_node 0, recon_node 0, recorder_node 0, "
                     r"scan_node 0", bringup.output), bringup.output
    (session,) = list((tmp_path / "bags").iterdir())
    assert (session / "metadata.yaml").is_file()


def test_every_package_config_loads_and_lists_every_parameter(
        ros_node: Node, start_node, spin_until, tmp_path: Path) -> None:
    merged = {}
    for package, name in CONFIGS.values():
        merged.update(yaml.safe_load(_config(package, name).read_text()))
    documented = {node: _documented(node) for node in NODES}
    merged["/fingerps/recorder"]["ros__parameters"]["bags_dir"] = str(tmp_path / "bags")
    bringup = start_node("fingerps_driver", "bringup", "--params",
                         str(_write(tmp_path / "all.yaml", merged)))
    for name in NODES:
        bringup.wait_in_graph(ros_node, name, NS, timeout=60.0)
    for name in NODES:
        client = ros_node.create_client(ListParameters, f"{NS}/{name}/list_parameters")
        assert client.wait_for_service(timeout_sec=20.0)
        future = client.call_async(ListParameters.Request())
        spin_until(future.done, f"{name}'s parameters")
        names = list(future.result().result.names)
        declared = set(names) - ROS_DEFAULTS
        assert declared == documented[name], (
            f"{name}: undocumented {sorted(declared - documented[name])}, "
            f"documented but absent {sorted(documented[name] - declared)}")
        # What `ros2 param dump` asks: every value at once. rclpy answers nothing at all if
        # one of them is a typed parameter without a value (the dump then shows {}).
        getter = ros_node.create_client(GetParameters, f"{NS}/{name}/get_parameters")
        future = getter.call_async(GetParameters.Request(names=names))
        spin_until(future.done, f"{name}'s parameter values")
        values = future.result().values
        assert len(values) == len(names), f"{name}: get_parameters answered {len(values)} of " \
            f"{len(names)} values"
        unset = [n for n, v in zip(names, values, strict=True)
                 if v.type == ParameterType.PARAMETER_NOT_SET]
        assert not unset, f"{name}: parameters without a value: {unset}"
    bringup.send_signal(signal.SIGINT)
    assert bringup.wait(timeout=40.0) == 0, bringup.output


def _documented(node: str) -> set[str]:
    """Parameter names of a package's config/<node>.yaml, commented-out ones included."""
    text = _config(*CONFIGS[node]).read_text()
    keys = set(yaml.safe_load(text)[f"{NS}/{node}"]["ros__parameters"])
    return keys | set(re.findall(r"^ {4,}# ([a-z_.0-9]+): ", text, flags=re.MULTILINE))


@pytest.mark.parametrize("name", ["fingerps_sim.yaml", "fingerps_hardware.yaml"])
def test_the_graph_files_set_only_documented_parameters(name: str) -> None:
    data = yaml.safe_load(_config("fingerps_driver", name).read_text())
    assert set(data) == {f"{NS}/{node}" for node in NODES}
    for node in NODES:
        keys = set(data[f"{NS}/{node}"]["ros__parameters"])
        assert keys <= _documented(node), sorted(keys - _documented(node))


@pytest.mark.parametrize(("section", "params", "named"), [
    ("/fingerps/recon", {"modle": "hk"}, "'modle'"),
    ("/fingerps/driver", {"led_count": "seven"}, "led_count"),
    ("/fingerps/scann", {"model": "hk"}, "unknown node '/fingerps/scann'"),
])
def test_a_bad_parameter_file_stops_bringup_naming_the_key(
        start_node, tmp_path: Path, section: str, params: dict, named: str) -> None:
    data = yaml.safe_load(_config("fingerps_driver", "fingerps_sim.yaml").read_text())
    data["/fingerps/recorder"]["ros__parameters"]["bags_dir"] = str(tmp_path / "bags")
    data.setdefault(section, {"ros__parameters": {}})["ros__parameters"].update(params)
    bringup = start_node("fingerps_driver", "bringup", "--params",
                         str(_write(tmp_path / "bad.yaml", data)))
    assert bringup.wait(timeout=60.0) == 2, bringup.output
    assert named in bringup.output, bringup.output
    if not section.endswith("scann"):  # a node refused it: the others were stopped
        failed = section.rsplit("/", 1)[1]
        stopped = re.search(r"\[bringup\] stopped: (.*)", bringup.output)
        assert stopped, bringup.output
        codes = dict(item.rsplit(" ", 1) for item in stopped.group(1).split(", "))
        assert set(codes) == {f"{n}_node" for n in NODES}
        assert codes.pop(f"{failed}_node") == "2"
        # 0, or -15 for a node still importing its modules when it was stopped
        assert set(codes.values()) <= {"0", str(-signal.SIGTERM)}, bringup.output
        assert "Traceback" not in bringup.output, bringup.output


def test_the_graph_bringup_starts_discovers_on_this_machine_only(
        ros_node: Node, start_node, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Jazzy's default is the subnet: with the variable unset, bringup must start its nodes
    # with localhost discovery (fingerps_ros.privacy), and its files owner-only.
    params = yaml.safe_load(_config("fingerps_driver", "fingerps_sim.yaml").read_text())
    params["/fingerps/recorder"]["ros__parameters"]["bags_dir"] = str(tmp_path / "bags")
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE")
    bringup = start_node("fingerps_driver", "bringup", "--params",
                         str(_write(tmp_path / "sim.yaml", params)))
    for name in NODES:  # the test's own node discovers on localhost: it sees them
        bringup.wait_in_graph(ros_node, name, NS, timeout=60.0)
    pid = bringup.process.pid
    children = {int(c) for task in Path(f"/proc/{pid}/task").iterdir()
                for c in (task / "children").read_text().split()}
    assert len(children) == len(NODES), children
    for child in children:
        environ = dict(item.split("=", 1) for item in
                       Path(f"/proc/{child}/environ").read_bytes().decode().split("\0")
                       if "=" in item)
        assert environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST", child
    bringup.send_signal(signal.SIGINT)
    assert bringup.wait(timeout=40.0) == 0, bringup.output
    bag_files = list((tmp_path / "bags").rglob("*"))
    assert bag_files and all(p.stat().st_mode & 0o077 == 0 for p in bag_files), \
        [(p, oct(p.stat().st_mode)) for p in bag_files]
