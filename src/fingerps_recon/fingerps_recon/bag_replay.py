"""bag_replay: plays a session bag's topics back into the graph.

    ros2 run fingerps_recon bag_replay --ros-args -p bag:=bags/fingerps_20250131T120000Z \\
        -p rate:=2.0 -p start:=5.0 -p stop:=20.0 -p "topics:=[/fingerps/burst]"

Messages are published on their recorded (absolute) topic names, as serialized bytes (no
decoding), with the recorded spacing of their log times divided by ``rate``; ``rate`` 0
publishes them back to back. ``start``/``stop`` are seconds after the bag's first message.
Calibration topics (offered transient-local when recorded) are published with
`fingerps_ros.qos.CALIBRATION_QOS`, and the last calibration message before ``start`` is
published when playback begins, so a consumer gets the calibration in force; other known
topics get the recorder's QoS (`sessions.session_topics.TOPIC_TABLE`), unknown ones reliable
depth 10.
``wait_for_subscribers`` holds each topic's first message until that many subscribers have
matched (a volatile topic's messages published before would be lost), and holds playback
after a calibration message until they acknowledged it: a consumer then has the calibration
in force before the bursts that follow it (discovery matches the topics in no set order, so
a transient-local calibration alone could reach it after the first burst). The recorded
spacing is kept from after these waits.

The bag is read with `fingerps_recon.sessions.bag_reader.SessionBagReader`: a bag recorded with
another version of our messages is refused (exit code 1 and one line), a damaged bag is
played whole but for its damaged chunks (then an error naming the damaged byte ranges,
exit code 1).

Threads: the executor spins the node; one worker thread reads and publishes. With
``exit_when_done`` the node shuts down once the last message is out.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import rclpy
import yaml
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile

from fingerps_recon.errors import FingerpsReconError
from fingerps_recon.sessions.bag_reader import BagMessage, SessionBagReader, message_class
from fingerps_recon.sessions.session_topics import TOPIC_TABLE
from fingerps_ros import qos
from fingerps_ros.node_runner import StartupError, run_node
from fingerps_ros.parameter_table import ParameterRow
from fingerps_ros.parameters import declare_parameters

SUBSCRIBER_WAIT_S = 10.0
LINGER_S = 0.5
"""Seconds the node stays up after the last message, so reliable deliveries complete."""


BAG_REPLAY_PARAMETERS = (
    ParameterRow("bag", "", "Bag directory (or .mcap file) to play", read_only=True,
                 check=lambda v: None if str(v) else "must name a bag directory or .mcap"),
    ParameterRow("rate", 1.0, "Speed factor of the recorded timing; 0 = back to back",
                 min_value=0.0, max_value=1000.0, read_only=True),
    ParameterRow("start", 0.0, "Seconds after the bag's first message to start at",
                 min_value=0.0, max_value=1e9, read_only=True),
    ParameterRow("stop", 0.0, "Seconds after the bag's first message to stop at; 0 = the end",
                 min_value=0.0, max_value=1e9, read_only=True),
    ParameterRow("topics", [""], "Topics to play (absolute, as recorded); empty = all",
                 read_only=True),
    ParameterRow("wait_for_subscribers", 0,
                 "Hold each topic's first message until this many subscribers matched, and "
                 "playback after a calibration message until they acknowledged it (at most "
                 f"{SUBSCRIBER_WAIT_S:.0f} s each)", min_value=0, max_value=100,
                 integer=True, read_only=True),
    ParameterRow("exit_when_done", True, "Shut the node down after the last message",
                 read_only=True),
)
"""bag_replay's parameters, in declaration order (all read-only: set at start)."""


def _is_transient_local(offered_qos_yaml: str) -> bool:
    try:
        profiles = yaml.safe_load(offered_qos_yaml) or []
    except yaml.YAMLError:
        return False
    return any(isinstance(p, dict) and p.get("durability") in ("transient_local", 1)
               for p in profiles)


class BagReplayNode(Node):
    """Publishes a bag's messages with their recorded timing (scaled by ``rate``)."""

    def __init__(self) -> None:
        super().__init__("bag_replay", namespace="/fingerps")
        checks = declare_parameters(self, BAG_REPLAY_PARAMETERS)
        checks.refuse_unknown_overrides(self)
        g = self.get_parameter
        bag = str(g("bag").value)
        if not bag:
            raise StartupError("no bag given: set -p bag:=<bag directory or .mcap file>")
        try:
            self._reader = SessionBagReader(bag)
        except FingerpsReconError as err:
            raise StartupError(str(err)) from None
        self._rate = float(g("rate").value)
        self._start_ns = int(float(g("start").value) * 1e9)
        stop = float(g("stop").value)
        self._stop_ns = int(stop * 1e9) if stop > 0 else None
        self._topics = [t for t in (g("topics").value or []) if t] or None
        self._subscribers = int(g("wait_for_subscribers").value)
        self._exit_when_done = bool(g("exit_when_done").value)
        self._topic_publishers: dict[str, Any] = {}
        self._stop = threading.Event()
        self.failed = False
        self.published = 0
        self._held_s = 0.0  # seconds held by wait_for_subscribers so far
        self._worker = threading.Thread(target=self._play, name="bag_replay")
        self._worker.start()
        self.get_logger().info(
            f"playing {self._reader.mcap_path} at rate {self._rate:g}"
            f"{' (back to back)' if self._rate == 0 else ''}")

    # ------------------------------------------------------------------ publishing
    def _publisher(self, message: BagMessage) -> Any:
        """The topic's publisher; the first time, it waits for ``wait_for_subscribers``."""
        publisher = self._topic_publishers.get(message.topic)
        if publisher is not None:
            return publisher
        profile = (qos.CALIBRATION_QOS if _is_transient_local(message.offered_qos_yaml)
                   else self._profile(message.topic))
        publisher = self.create_publisher(message_class(message.type_name), message.topic,
                                          profile)
        self._topic_publishers[message.topic] = publisher
        if self._subscribers:
            start = time.monotonic()
            while (publisher.get_subscription_count() < self._subscribers
                   and time.monotonic() < start + SUBSCRIBER_WAIT_S
                   and not self._stop.is_set()):
                time.sleep(0.02)
            self._held_s += time.monotonic() - start
        return publisher

    def _publish(self, message: BagMessage) -> None:
        """Publish one message; a calibration is then waited for until its subscribers
        acknowledged it (with ``wait_for_subscribers``), so it arrives before what follows."""
        publisher = self._publisher(message)
        publisher.publish(message.data)
        self.published += 1
        if self._subscribers and _is_transient_local(message.offered_qos_yaml):
            start = time.monotonic()
            if not publisher.wait_for_all_acked(Duration(seconds=SUBSCRIBER_WAIT_S)):
                self.get_logger().warning(
                    f"{message.topic}: not acknowledged by every subscriber within "
                    f"{SUBSCRIBER_WAIT_S:.0f} s; playing on")
            self._held_s += time.monotonic() - start

    def _profile(self, topic: str) -> QoSProfile:
        for key, spec in TOPIC_TABLE.items():
            if self.resolve_topic_name(key) == topic:
                return spec.qos
        return QoSProfile(depth=10)

    def _play(self) -> None:
        try:
            self._play_messages()
        except FingerpsReconError as err:
            self.failed = True
            self.get_logger().error(str(err))
        except Exception as err:  # the worker must end the node, not hang it
            self.failed = True
            self.get_logger().error(f"replay failed: {type(err).__name__}: {err}")
        finally:
            self.get_logger().info(f"replay done: {self.published} messages published")
            if self._exit_when_done and not self._stop.wait(LINGER_S):
                rclpy.try_shutdown(context=self.context)

    def _play_messages(self) -> None:
        first_ns: int | None = None
        clock: tuple[float, int] | None = None  # (wall time, bag offset) of the first played
        held_s = 0.0  # self._held_s when the clock was last set
        held: dict[str, BagMessage] = {}  # calibration before start: the latest of each
        for message in self._reader.messages(self._topics):
            if self._stop.is_set():
                return
            if first_ns is None:
                first_ns = message.log_time_ns
            offset = message.log_time_ns - first_ns
            if self._stop_ns is not None and offset > self._stop_ns:
                return
            if offset < self._start_ns:
                if _is_transient_local(message.offered_qos_yaml):
                    held[message.topic] = message
                continue
            for early in held.values():
                self._publish(early)
            held.clear()
            self._publisher(message)  # the first time, it may wait for subscribers
            if self._rate > 0:
                if clock is None:
                    clock = (time.monotonic(), offset)
                else:  # the recorded spacing holds from after the waits
                    clock = (clock[0] + self._held_s - held_s, clock[1])
                held_s = self._held_s
                due = clock[0] + (offset - clock[1]) / 1e9 / self._rate
                if self._stop.wait(max(due - time.monotonic(), 0.0)):
                    return
            self._publish(message)
        for early in held.values():  # start beyond the last message: still the calibration
            self._publish(early)

    def destroy_node(self) -> None:
        """Stop the worker and destroy the node."""
        self._stop.set()
        if self._worker.is_alive() and self._worker is not threading.current_thread():
            self._worker.join(timeout=5.0)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run fingerps_recon bag_replay``; 1 when the bag could not be
    played to its end (damage, another message version), 2 on bad input."""
    made: list[BagReplayNode] = []

    def make() -> BagReplayNode:
        made.append(BagReplayNode())
        return made[-1]

    code = run_node(make, args=args, name="bag_replay",
                    expected_errors=(FingerpsReconError,))
    return 1 if code == 0 and made and made[0].failed else code


if __name__ == "__main__":
    raise SystemExit(main())
