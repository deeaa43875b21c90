"""Capturing a burst: the plan (order, exposures, levels), the sequencing, the rate."""
