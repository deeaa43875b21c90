"""The Scan action's judgement: finger presence, motion within a burst, quality (no ROS)."""
