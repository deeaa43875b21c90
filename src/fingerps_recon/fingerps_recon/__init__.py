"""fingerps_recon."""
