"""Recorded sessions: MCAP/rosbag2 bags written, read, recovered and replayed."""
