"""The fingerps graph for a full ROS 2 Jazzy installation (launch and launch_ros):

    ros2 launch fingerps_driver fingerps.launch.py                      # simulated rig
    ros2 launch fingerps_driver fingerps.launch.py params_file:=/path/fingerps_hardware.yaml

The same nodes and parameter file as ``ros2 run fingerps_driver bringup``; Ctrl-C stops them
(the driver switches the LEDs off, the recorder finalises its bag). Launch sends each node
SIGINT and, run non-interactively, the process group gets one too: the nodes ignore every
signal after the first while they close their resources (``fingerps_ros.node_runner``),
and exit 0.

A node that exits on its own stops the whole graph, as bringup does: a non-zero exit (2 for
a refused parameter, with one line naming it) makes ``ros2 launch`` log the node and its
code, stop the others and exit 1 - launch (Jazzy) returns non-zero only when an action or
event handler raises, so the exit handler raises ``NodeExitedError``; a node exiting with 0
while the graph runs stops it too, with the reason logged. A node that does not exit 0 while
the graph is being stopped also makes the exit code 1. The recorder gets more time than
launch's default 5 s + 5 s before SIGTERM and SIGKILL, so that it can finish a large bag.
"""

import os
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, LogInfo, SetEnvironmentVariable
from launch.events import Shutdown
from launch.events.process import ProcessExited
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = (
    ("fingerps_driver", "driver_node", "driver"),
    ("fingerps_calib", "calib_node", "calib"),
    ("fingerps_recon", "recon_node", "recon"),
    ("fingerps_recon", "recorder_node", "recorder"),
    ("fingerps_recon", "scan_node", "scan"),
)
EXIT_BAD_INPUT = 2
# seconds after launch's SIGINT before SIGTERM, and after that before SIGKILL
STOP_TIMEOUTS_S = {"recorder": ("30", "10")}


class NodeExitedError(RuntimeError):
    """A node of the graph exited on its own, or did not stop cleanly; ros2 launch exits 1."""


def on_node_exit(event: ProcessExited, context: LaunchContext) -> list | None:
    """Exit handler of every node: stop the graph when a node exits while it runs; make
    ``ros2 launch`` fail (raise) when a node's exit code is not 0."""
    try:
        name = event.action.node_name  # /fingerps/<name> once the node has been started
    except Exception:  # launch_ros raises while the name is not expanded
        name = event.process_name
    code = event.returncode
    if code != 0:
        what = ("refused its start-up input (its error line above names the key)"
                if code == EXIT_BAD_INPUT else f"exited with code {code}")
        stopping = "; the graph was stopping" if context.is_shutdown else "; stopping the graph"
        raise NodeExitedError(f"{name} {what}{stopping}")
    if context.is_shutdown:
        return None
    reason = f"{name} exited; stopping the graph"
    return [LogInfo(msg=reason), EmitEvent(event=Shutdown(reason=reason))]


def generate_launch_description() -> LaunchDescription:
    share = Path(get_package_share_directory("fingerps_driver"))
    default = share / "config" / "fingerps_sim.yaml"
    params_file = LaunchConfiguration("params_file")
    nodes = []
    for package, executable, name in NODES:
        timeouts = {}
        if name in STOP_TIMEOUTS_S:
            sigterm_s, sigkill_s = STOP_TIMEOUTS_S[name]
            timeouts = {"sigterm_timeout": sigterm_s, "sigkill_timeout": sigkill_s}
        nodes.append(Node(package=package, executable=executable, name=name,
                          namespace="fingerps", parameters=[params_file], output="screen",
                          emulate_tty=True, on_exit=on_node_exit, **timeouts))
    # Private by default: discovery on this machine only, unless the user chose a range
    # (e.g. ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET to open the graph to the network).
    discovery = ([] if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
                 else [SetEnvironmentVariable("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")])
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=str(default),
                              description="ROS 2 parameter file of the whole graph"),
        *discovery,
        *nodes,
    ])
