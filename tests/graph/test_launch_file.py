"""launch/fingerps.launch.py stops the whole graph when a node exits, and ros2 launch fails.

launch and launch_ros have no wheel here: the first tests load the launch file against a
minimal stand-in of the launch API they use (the names and signatures of Jazzy's launch
0.26 / launch_ros 0.26) and check its exit handler; the last one runs the real
``LaunchService`` (what ``ros2 launch`` runs) where launch_ros is installed and is skipped
otherwise. Checked by hand against the Jazzy sources: a refused parameter (exit 2) stops the
other four nodes (each "finished cleanly") and the run returns 1.
"""

from __future__ import annotations

import importlib.util
import signal
import sys
import threading
import types
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]
LAUNCH_FILE = REPO / "src" / "fingerps_driver" / "launch" / "fingerps.launch.py"
GRAPH = {"driver", "calib", "recon", "recorder", "scan"}


class _Entity:
    def __init__(self, *args, **kwargs) -> None:
        self.args = args
        self.kwargs = kwargs


class _Shutdown(_Entity):
    @property
    def reason(self) -> str:
        return self.kwargs["reason"]


def _stand_in_modules() -> dict[str, types.ModuleType]:
    modules = {name: types.ModuleType(name) for name in (
        "launch", "launch.actions", "launch.events", "launch.events.process",
        "launch.substitutions", "launch_ros", "launch_ros.actions")}
    modules["launch"].LaunchContext = object
    modules["launch"].LaunchDescription = _Entity
    for name in ("DeclareLaunchArgument", "EmitEvent", "LogInfo", "SetEnvironmentVariable"):
        setattr(modules["launch.actions"], name, type(name, (_Entity,), {}))
    modules["launch.events"].Shutdown = _Shutdown
    modules["launch.events.process"].ProcessExited = object
    modules["launch.substitutions"].LaunchConfiguration = type("LaunchConfiguration",
                                                               (_Entity,), {})
    modules["launch_ros.actions"].Node = type("Node", (_Entity,), {})
    return modules


@pytest.fixture
def launch_file(monkeypatch: pytest.MonkeyPatch) -> types.ModuleType:
    for name, module in _stand_in_modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("fingerps_launch_file", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _exit(name: str, code: int) -> types.SimpleNamespace:
    return types.SimpleNamespace(action=types.SimpleNamespace(node_name=f"/fingerps/{name}"),
                                 process_name=f"{name}_node-1", returncode=code)


def _context(shutting_down: bool) -> types.SimpleNamespace:
    return types.SimpleNamespace(is_shutdown=shutting_down)


def test_every_node_of_the_graph_has_the_exit_handler(launch_file) -> None:
    description = launch_file.generate_launch_description()
    nodes = [e for e in description.args[0] if type(e).__name__ == "Node"]
    assert {n.kwargs["name"] for n in nodes} == GRAPH
    for node in nodes:
        assert node.kwargs["on_exit"] is launch_file.on_node_exit
    recorder = next(n for n in nodes if n.kwargs["name"] == "recorder")
    # more than launch's 5 s + 5 s to finish a large bag before SIGKILL
    assert float(recorder.kwargs["sigterm_timeout"]) + float(recorder.kwargs["sigkill_timeout"]) \
        > 10.0


@pytest.mark.parametrize(("code", "named"), [
    (2, "/fingerps/recon refused its start-up input"),
    (1, "/fingerps/recon exited with code 1"),
    (-signal.SIGSEGV, f"/fingerps/recon exited with code {-signal.SIGSEGV}"),
])
def test_a_node_exiting_non_zero_stops_the_graph_and_fails_the_launch(
        launch_file, code: int, named: str) -> None:
    # launch (Jazzy) answers an exception in an event handler with a Shutdown of every
    # process and a return code of 1: ros2 launch exits 1
    with pytest.raises(launch_file.NodeExitedError, match=named + ".*stopping the graph"):
        launch_file.on_node_exit(_exit("recon", code), _context(shutting_down=False))


def test_a_node_exiting_0_while_the_graph_runs_stops_the_graph(launch_file) -> None:
    entities = launch_file.on_node_exit(_exit("scan", 0), _context(shutting_down=False))
    (shutdown,) = [e.kwargs["event"] for e in entities if type(e).__name__ == "EmitEvent"]
    assert isinstance(shutdown, _Shutdown)
    assert "/fingerps/scan exited" in shutdown.reason


def test_nodes_stopping_cleanly_with_the_graph_change_nothing(launch_file) -> None:
    assert launch_file.on_node_exit(_exit("driver", 0), _context(shutting_down=True)) is None
    with pytest.raises(launch_file.NodeExitedError, match="the graph was stopping"):
        launch_file.on_node_exit(_exit("recorder", -signal.SIGKILL), _context(True))


def test_ros2_launch_stops_the_graph_and_fails_when_a_node_refuses_a_parameter(
        ros_domain: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("launch_ros", reason="launch_ros is not installed (no wheel here)")
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription, LaunchService
    from launch.actions import IncludeLaunchDescription
    from launch.launch_description_sources import PythonLaunchDescriptionSource

    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))
    share = Path(get_package_share_directory("fingerps_driver"))
    data = yaml.safe_load((share / "config" / "fingerps_sim.yaml").read_text())
    data["/fingerps/recorder"]["ros__parameters"]["bags_dir"] = str(tmp_path / "bags")
    data["/fingerps/recon"]["ros__parameters"]["modle"] = "hk"
    params = tmp_path / "bad.yaml"
    params.write_text(yaml.safe_dump(data))
    service = LaunchService(noninteractive=True)
    service.include_launch_description(LaunchDescription([IncludeLaunchDescription(
        PythonLaunchDescriptionSource(str(share / "launch" / "fingerps.launch.py")),
        launch_arguments=[("params_file", str(params))])]))
    watchdog = threading.Timer(60.0, service.shutdown)  # the graph running on: fail, not hang
    watchdog.start()
    try:
        assert service.run() == 1
    finally:
        watchdog.cancel()
    (session,) = list((tmp_path / "bags").iterdir())
    assert (session / "metadata.yaml").is_file()  # the recorder was stopped cleanly
