"""Camera intrinsics: checkerboard calibration, camera_info YAML files, URLs, messages."""
