"""Names of the fingerps topics and services, relative to the nodes' namespace.

Nodes start in the namespace ``/fingerps`` unless remapped (``--ros-args -r __ns:=/x``),
so the defaults resolve to ``/fingerps/<name>``.
"""

from __future__ import annotations

NAMESPACE = "fingerps"

# driver
FRAMES = "frames"                   # fingerps_msgs/TaggedFrame, one per LED image
IMAGE_RAW = "image_raw"             # sensor_msgs/Image, the same images for generic viewers
CAMERA_INFO = "camera_info"         # sensor_msgs/CameraInfo
BURST = "burst"                     # fingerps_msgs/Burst, complete bursts only
CAPTURE_BURST = "capture_burst"     # fingerps_msgs/srv/CaptureBurst

# calibration
LIGHT_CALIBRATION = "calibration/lights"          # fingerps_msgs/LightCalibration
FLAT_FIELD = "calibration/flat_field"             # fingerps_msgs/FlatField
CALIBRATE_LIGHTS = "calibrate_lights"             # fingerps_msgs/srv/CalibrateLights
CALIBRATE_FLAT_FIELD = "calibrate_flat_field"     # fingerps_msgs/srv/CalibrateFlatField

# reconstruction
NORMALS = "normals"                 # sensor_msgs/Image 32FC3, unit normals, optical frame
NORMAL_MAP = "normal_map"           # sensor_msgs/Image rgb8, normals as colours for viewing
DEPTH = "depth"                     # sensor_msgs/Image 32FC1, metres along the optical axis
ALBEDO = "albedo"                   # sensor_msgs/Image 32FC1, albedo rho per pixel
POINTS = "points"                   # sensor_msgs/PointCloud2, x y z intensity, optical frame
FINGERPRINT = "fingerprint"         # sensor_msgs/Image mono8, rolled-equivalent print, 500 ppi
FINGERPRINT_FRAME = "fingerps_rolled_print_500ppi"  # its frame_id: the rolled plane, 500 ppi

DIAGNOSTICS = "/diagnostics"        # diagnostic_msgs/DiagnosticArray (absolute, as usual)
