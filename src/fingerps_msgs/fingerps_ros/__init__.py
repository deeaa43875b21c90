"""fingerps_ros: the ROS plumbing every fingerps node shares.

QoS profiles and topic names, parameter declaration and checks, the one ``main`` of every
node (signals, clean shutdown, one-line errors), private file modes, conversions between
numpy arrays and sensor_msgs (Image, PointCloud2) and the image_transport-style compressed
companions. Installed by the interface package ``fingerps_msgs``, which every fingerps
package depends on for its messages already: so no package imports another only for its
plumbing (see ARCHITECTURE.md).
"""
