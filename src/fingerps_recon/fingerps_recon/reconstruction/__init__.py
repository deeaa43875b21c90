"""recon_node's core without a node: burst intake, the burst reconstructed with the prepared
calibration, the worker's bookkeeping, the outputs' messages, parameters and diagnostics."""
