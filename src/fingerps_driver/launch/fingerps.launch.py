"""The fingerps graph for a full ROS 2 Jazzy installation (launch and launch_ros):

    ros2 launch fingerps_driver fingerps.launch.py                      # simulated rig
    ros2 launch fingerps_driver fingerps.launch.py params_file:=/path/fingerps_hardware.yaml

The same nodes and parameter file as ``ros2 run fingerps_driver bringup``; Ctrl-C stops them
(the driver switches the LEDs off, the recorder finalises its bag).
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = (
    ("fingerps_driver", "driver_node", "driver"),
    ("fingerps_calib", "calib_node", "calib"),
    ("fingerps_recon", "recon_node", "recon"),
    ("fingerps_recon", "recorder_node", "recorder"),
    ("fingerps_recon", "scan_node", "scan"),
)


def generate_launch_description() -> LaunchDescription:
    share = Path(get_package_share_directory("fingerps_driver"))
    default = share / "config" / "fingerps_sim.yaml"
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=str(default),
                              description="ROS 2 parameter file of the whole graph"),
        *(Node(package=package, executable=executable, name=name, namespace="fingerps",
               parameters=[params_file], output="screen", emulate_tty=True)
          for package, executable, name in NODES),
    ])
