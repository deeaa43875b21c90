"""fingerps_driver."""
