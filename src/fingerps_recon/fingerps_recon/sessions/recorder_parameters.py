"""recorder_node's parameter table (``fingerps_ros.parameter_table``: names, defaults,
descriptions, ranges, checks; no ROS), in declaration order."""

from __future__ import annotations

from collections.abc import Callable

from fingerps_recon.sessions.session_bag import DEFAULT_CHUNK_SIZE
from fingerps_recon.sessions.session_metadata import default_session_name, session_name_problem
from fingerps_recon.sessions.session_topics import SESSION_TOPICS, TOPIC_TABLE, topics_problem
from fingerps_ros.parameter_table import ParameterRow


def recorder_parameters(resolve: Callable[[str], str]) -> tuple[ParameterRow, ...]:
    """The recorder's parameters in declaration order; ``resolve`` gives a topic's full name."""
    return (
        ParameterRow(
            "topics", list(SESSION_TOPICS),
            "Topics to record, relative to the namespace or absolute; each must be one of "
            f"the known session topics ({', '.join(TOPIC_TABLE)})", read_only=True,
            check=lambda v: topics_problem(v, resolve)),
        ParameterRow(
            "record_outputs", True,
            "Also record the reconstruction outputs (normals, depth, points, normal_map); "
            "false leaves these heavy topics out", read_only=True),
        ParameterRow(
            "bags_dir", "bags",
            "Directory the session bag directory is created in (created if missing)",
            read_only=True, check=lambda v: None if str(v) else "must not be empty"),
        ParameterRow(
            "session_name", default_session_name,
            "Name of the bag directory (and of its MCAP file, <name>_0.mcap); must not "
            "exist yet", read_only=True, check=session_name_problem),
        ParameterRow(
            "chunk_size", DEFAULT_CHUNK_SIZE,
            "Uncompressed bytes per MCAP chunk: the compression unit and the most a killed "
            "recorder loses", min_value=64 * 1024, max_value=512 * 1024 * 1024, integer=True,
            read_only=True),
        ParameterRow(
            "flush_period", 2.0,
            "Seconds after which an open MCAP chunk is written even if not full (bounds the "
            "loss on a crash in time); 0 writes chunks only when full",
            min_value=0.0, max_value=3600.0),
        ParameterRow(
            "queue_limit_mb", 512,
            "Megabytes of messages waiting for the writer; beyond this the oldest are "
            "dropped (and counted)", min_value=1, max_value=65536, integer=True,
            read_only=True),
        ParameterRow(
            "history_depth", 50,
            "Keep-last depth of the recorder's subscriptions: messages per topic DDS holds "
            "for the recorder while its executor is busy (a deeper reader history is "
            "compatible with every publisher; the publishers' own depth is kept in the bag's "
            "QoS metadata)", min_value=1, max_value=10000, integer=True, read_only=True),
        ParameterRow(
            "max_bagfile_size", 0,
            "Bytes after which the bag goes on in a new MCAP file <session_name>_<n>.mcap "
            "(rosbag2's max_bagfile_size); 0 = one file", min_value=0,
            max_value=2**50, integer=True, read_only=True),
        ParameterRow(
            "max_bagfile_duration", 0,
            "Seconds of messages after which the bag goes on in a new MCAP file (rosbag2's "
            "max_bagfile_duration); 0 = no limit", min_value=0, max_value=10**7,
            integer=True, read_only=True),
        ParameterRow(
            "bags_dir_limit_mb", 0,
            "Megabytes the sessions in bags_dir may add up to; beyond it the oldest whole "
            "sessions are removed, never the one being recorded; 0 = no limit",
            min_value=0, max_value=2**30, integer=True, read_only=True),
    )
