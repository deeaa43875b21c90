# Source this (bash) from the repository root: the project's venv, the ROS wheels as an
# underlay, and the colcon install/ overlay when it has been built.
# shellcheck shell=bash
_fingerps_root=$(pwd)
. "$_fingerps_root/.venv/bin/activate"
export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$VIRTUAL_ENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# Private by default: discovery on this machine only (fingerprints are biometric data); set
# ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET before sourcing to open the graph to the network.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
if [ -f "$_fingerps_root/install/setup.bash" ]; then
  # shellcheck disable=SC1091
  . "$_fingerps_root/install/setup.bash"
fi
unset _fingerps_root
