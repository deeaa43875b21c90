"""QoS profiles as rosbag2 records them: the publishers' offered profiles as plain fields
(`QosProfileFields`, no rclpy) and the ``offered_qos_profiles`` YAML of an MCAP channel
and of metadata.yaml (`qos_profiles_yaml`, rosbag2_storage's version-9 form: policies by
name, durations as ``{sec, nsec}``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fingerps_recon.errors import SessionBagError
from fingerps_recon.sessions.rosbag2_yaml import yaml_lines
from fingerps_ros.time_conversion import NS_PER_S

# rmw enum values -> rmw_qos_*_policy_to_str() names (rmw/qos_string_conversions.h).
_HISTORY = {0: "system_default", 1: "keep_last", 2: "keep_all", 3: "unknown"}
_RELIABILITY = {0: "system_default", 1: "reliable", 2: "best_effort", 3: "unknown",
                4: "best_available"}
_DURABILITY = {0: "system_default", 1: "transient_local", 2: "volatile", 3: "unknown",
               4: "best_available"}
_LIVELINESS = {0: "system_default", 1: "automatic", 3: "manual_by_topic", 4: "unknown",
               5: "best_available"}


def _policy_name(value: Any, names: dict[int, str], policy: str) -> str:
    if isinstance(value, str):
        if value not in names.values():
            raise SessionBagError(
                f"QoS {policy} {value!r} unknown; use one of {sorted(set(names.values()))}")
        return value
    try:
        return names[int(value)]
    except (KeyError, TypeError, ValueError):
        raise SessionBagError(
            f"QoS {policy} value {value!r} unknown; use one of {sorted(names)} "
            f"({', '.join(names.values())})") from None


def _nanoseconds(value: Any) -> int:
    """Nanoseconds of an int or of an rclpy Duration-like object (``.nanoseconds``)."""
    return int(getattr(value, "nanoseconds", value))


@dataclass(frozen=True)
class QosProfileFields:
    """One QoS profile as plain fields (no rclpy), for the rosbag2 YAML.

    Policies are rmw's lower-case names (``"keep_last"``, ``"reliable"``,
    ``"transient_local"``, ``"automatic"``, ...); durations are integer nanoseconds
    (0: the rmw default; `INT64_MAX`: infinite).
    """

    history: str = "keep_last"
    depth: int = 10
    reliability: str = "reliable"
    durability: str = "volatile"
    deadline_ns: int = 0
    lifespan_ns: int = 0
    liveliness: str = "system_default"
    liveliness_lease_duration_ns: int = 0
    avoid_ros_namespace_conventions: bool = False

    def __post_init__(self) -> None:
        _policy_name(self.history, _HISTORY, "history")
        _policy_name(self.reliability, _RELIABILITY, "reliability")
        _policy_name(self.durability, _DURABILITY, "durability")
        _policy_name(self.liveliness, _LIVELINESS, "liveliness")
        if self.depth < 0 or min(self.deadline_ns, self.lifespan_ns,
                                 self.liveliness_lease_duration_ns) < 0:
            raise SessionBagError("QoS depth and durations must not be negative")

    @classmethod
    def from_profile(cls, profile: Any) -> QosProfileFields:
        """Copy an rclpy ``QoSProfile`` (or anything with its attribute names) into fields.

        Policies may be the rclpy enums (their integer values are rmw's), ints or names;
        durations ``rclpy.duration.Duration`` (``.nanoseconds``) or int nanoseconds.
        """
        if isinstance(profile, QosProfileFields):
            return profile
        return cls(
            history=_policy_name(profile.history, _HISTORY, "history"),
            depth=int(profile.depth),
            reliability=_policy_name(profile.reliability, _RELIABILITY, "reliability"),
            durability=_policy_name(profile.durability, _DURABILITY, "durability"),
            deadline_ns=_nanoseconds(profile.deadline),
            lifespan_ns=_nanoseconds(profile.lifespan),
            liveliness=_policy_name(profile.liveliness, _LIVELINESS, "liveliness"),
            liveliness_lease_duration_ns=_nanoseconds(profile.liveliness_lease_duration),
            avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
        )

    def to_yaml_node(self) -> dict[str, Any]:
        """The mapping rosbag2 (metadata version 9) writes for one profile, in its key order."""
        return {
            "history": self.history,
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": _rmw_time(self.deadline_ns),
            "lifespan": _rmw_time(self.lifespan_ns),
            "liveliness": self.liveliness,
            "liveliness_lease_duration": _rmw_time(self.liveliness_lease_duration_ns),
            "avoid_ros_namespace_conventions": self.avoid_ros_namespace_conventions,
        }


def _rmw_time(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), NS_PER_S)
    return {"sec": sec, "nsec": nsec}


def qos_profiles_yaml(profiles: Any) -> str:
    """The ``offered_qos_profiles`` string rosbag2 Jazzy writes into an MCAP channel.

    It is ``YAML::Dump`` of the list of profiles (rosbag2_storage
    ``serialize_rclcpp_qos_vector``, version 9: policies as names, durations as
    ``{sec, nsec}``), without a final newline; ``"[]"`` for no profile.

    Parameters
    ----------
    profiles : QosProfileFields or QoSProfile-like, or an iterable of them
        The offered profiles (an rclpy ``QoSProfile`` is accepted as is, through
        `QosProfileFields.from_profile`).

    Returns
    -------
    str
        For example ``"- history: keep_last\\n  depth: 1\\n  reliability: reliable\\n..."``.
    """
    if isinstance(profiles, QosProfileFields) or hasattr(profiles, "reliability"):
        profiles = [profiles]
    nodes = [QosProfileFields.from_profile(p).to_yaml_node() for p in profiles]
    return "\n".join(yaml_lines(nodes))
