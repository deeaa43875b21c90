"""Cameras: the base class and its checks, simulated, folder and OpenCV backends; calibration."""
