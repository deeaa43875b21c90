"""Photometric stereo: the paper's reflectance models, solvers, lights and normals (no ROS)."""
