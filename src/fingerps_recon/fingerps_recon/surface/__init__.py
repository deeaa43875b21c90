"""The surface from the normals: depth integration, 3D points, PLY, the rolled print (no ROS)."""
