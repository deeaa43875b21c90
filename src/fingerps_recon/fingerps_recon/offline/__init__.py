"""Offline work without a graph: DiLiGenT folders, reconstruction and tuning sweeps."""
