"""fingerps_calib."""
