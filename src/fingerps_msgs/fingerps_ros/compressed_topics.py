"""The compressed companions of an image topic, as image_transport publishes them.

Beside a raw ``sensor_msgs/Image`` topic ``<base>``, image_transport's plugins publish
``<base>/compressed`` (compressed_image_transport: PNG or JPEG) and, for depth,
``<base>/compressedDepth`` (compressed_depth_image_transport), both
``sensor_msgs/CompressedImage``. :class:`CompressedTopics` does the same for one base topic
of a fingerps node, with image_transport's parameter names (``<base>`` with ``/`` as ``.``):

- ``<base>.enable_pub_plugins`` (string array, image_transport's own, read once at start):
  the transports published. ``image_transport/raw`` is always published (the other fingerps
  nodes read it); besides it ``image_transport/compressed`` for images,
  ``image_transport/compressedDepth`` for depth; any other value stops the node at start
  with one line naming the allowed ones.
- ``<base>.compressed.format`` (png, jpeg), ``.png_level`` (0-9), ``.jpeg_quality``
  (1-100); ``<base>.compressedDepth.format`` (png), ``.depth_max``, ``.depth_quantization``,
  ``.png_level``: read at every publish, so a change applies to the next image. fingerps's
  defaults: png (lossless) instead of upstream's jpeg; depth_max 0.2 m and
  depth_quantization 50 instead of 10 m and 100, which overflow 16 bits at the fingertip's
  distance (``image_compression.DepthQuantization``).

As image_transport, a companion is encoded only while it has a subscriber, so one that is on
costs nothing while nobody watches. Encoding happens in :meth:`CompressedTopics.publish`,
in the caller's thread, after the caller has published the raw image. A failure to encode or
publish is never raised into the node: each distinct problem is logged once through the
node's logger, and all are counted (:attr:`CompressedTopics.failures`). The companions use
the raw topic's QoS. The parameters of every transport are declared whether it is enabled
or not, so a parameter file may set them either way (upstream's deprecated unscoped names,
``<base>.format`` and the like, are not declared).

The encoding itself is ``fingerps_ros.image_compression`` (no rclpy).
"""

from __future__ import annotations

import array
from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from fingerps_ros.image_compression import (
    COMPRESSED_FORMATS,
    DEPTH_ENCODING,
    DEPTH_FORMATS,
    DepthQuantization,
    encode_compressed,
    encode_compressed_depth,
)
from fingerps_ros.node_runner import StartupError
from fingerps_ros.parameter_table import Check, ParameterRow
from fingerps_ros.parameters import ParameterChecks, declare_parameters

RAW = "image_transport/raw"
COMPRESSED = "image_transport/compressed"
COMPRESSED_DEPTH = "image_transport/compressedDepth"
_SUFFIX = {COMPRESSED: "compressed", COMPRESSED_DEPTH: "compressedDepth"}
_MAX_LOGGED = 32  # distinct problems logged per base topic; beyond, only counted


class CompressedTopics:
    """The ``compressed`` (or, with ``depth``, ``compressedDepth``) companion of one image
    topic of ``node``: declares its parameters, advertises it if enabled, publishes it.

    Parameters
    ----------
    node : Node
        The node that publishes the raw topic. Create this before the node calls
        ``ParameterChecks.refuse_unknown_overrides`` (it declares parameters).
    base_topic : str
        The raw topic's name as the node publishes it (``"normal_map"``); the companions are
        ``<base_topic>/compressed`` or ``<base_topic>/compressedDepth``.
    qos_profile : QoSProfile
        The raw topic's QoS, used for the companion too.
    checks : ParameterChecks
        The node's checks; the ``format`` parameters' values are checked there.
    depth : bool
        The raw topic carries 32FC1 depth in metres: compressedDepth instead of compressed.
    enabled_by_default : bool
        Whether ``<base>.enable_pub_plugins`` lists the companion by default.

    Raises
    ------
    StartupError
        ``<base>.enable_pub_plugins`` is not a list of the allowed transports.
    """

    def __init__(self, node: Node, base_topic: str, qos_profile: QoSProfile,
                 checks: ParameterChecks, *, depth: bool = False,
                 enabled_by_default: bool = True) -> None:
        self._node = node
        self.base_topic = base_topic
        self._depth = depth
        self._transport = COMPRESSED_DEPTH if depth else COMPRESSED
        self._base = base_topic.strip("/").replace("/", ".")
        self.failures = 0
        """Images whose companion could not be encoded or published."""
        self.published = 0
        """Companion messages published."""
        self.last_problem = ""
        self._logged: set[str] = set()
        self._declare(checks, enabled_by_default)
        self.transports = self._enabled_transports()
        """The transports enabled at start (``<base>.enable_pub_plugins``)."""
        self._publisher: Publisher | None = None
        if self._transport in self.transports:
            self._publisher = node.create_publisher(
                CompressedImage, self.topic, qos_profile)

    @property
    def topic(self) -> str:
        """The companion's topic name, relative as ``base_topic`` is."""
        return f"{self.base_topic}/{_SUFFIX[self._transport]}"

    @property
    def enabled(self) -> bool:
        """Whether the companion is advertised (``enable_pub_plugins`` lists it)."""
        return self._publisher is not None

    @property
    def watched(self) -> bool:
        """Whether the companion is advertised and someone subscribes to it."""
        return self._publisher is not None and self._publisher.get_subscription_count() > 0

    def publish(self, image: np.ndarray, encoding: str, header: Header) -> None:
        """Encode ``image`` (the raw message's pixels, of ``encoding``) and publish it with
        ``header`` on the companion, if it is enabled and has a subscriber. Never raises:
        a problem is logged (once per distinct problem) and counted in :attr:`failures`."""
        publisher = self._publisher
        if publisher is None:
            return
        try:
            if publisher.get_subscription_count() == 0:
                return  # as image_transport: no work while nobody watches
            fmt, data = self._encode(image, encoding)
            msg = CompressedImage(check_fields=True)  # takes the array.array as it is
            msg.header = header
            msg.format = fmt
            buffer = array.array("B")
            buffer.frombytes(data)
            msg.data = buffer
            publisher.publish(msg)
            self.published += 1
        except Exception as exc:  # a companion must never disturb the node
            self._failed(exc)

    # ------------------------------------------------------------------ internals
    def _name(self, key: str) -> str:
        return f"{self._base}.{_SUFFIX[self._transport]}.{key}"

    def _value(self, key: str) -> Any:
        return self._node.get_parameter(self._name(key)).value

    def _encode(self, image: np.ndarray, encoding: str) -> tuple[str, bytes]:
        if self._depth:
            if encoding != DEPTH_ENCODING:
                raise ValueError(
                    f"compressedDepth needs {DEPTH_ENCODING} depth, got {encoding}")
            quantization = DepthQuantization(
                depth_max_m=float(self._value("depth_max")),
                depth_quantization=float(self._value("depth_quantization")))
            return encode_compressed_depth(
                image, quantization=quantization, codec=str(self._value("format")),
                png_level=int(self._value("png_level")))
        return encode_compressed(
            image, encoding, codec=str(self._value("format")),
            png_level=int(self._value("png_level")),
            jpeg_quality=int(self._value("jpeg_quality")))

    def _failed(self, exc: Exception) -> None:
        self.failures += 1
        problem = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
        self.last_problem = f"{self.topic} not published: {problem}"
        if problem not in self._logged and len(self._logged) < _MAX_LOGGED:
            self._logged.add(problem)
            self._node.get_logger().error(
                f"{self.last_problem} (logged once; further failures are only counted)")

    def _declare(self, checks: ParameterChecks, enabled_by_default: bool) -> None:
        allowed = self._allowed()
        rows = [ParameterRow(
            self._base + ".enable_pub_plugins",
            [RAW, self._transport] if enabled_by_default else [RAW],
            f"image_transport transports published for '{self.base_topic}', read at start. "
            f"{RAW} is always published (the other fingerps nodes read it); "
            f"{self._transport} adds '{self.topic}' (encoded only while subscribed)",
            read_only=True, constraints=f"Supported values: [{', '.join(allowed)}]",
            dynamic_typing=True)]  # [] (no companion) is typed as bytes by rclpy
        if self._depth:
            rows += [
                ParameterRow(self._name("format"), DEPTH_FORMATS[0],
                             "compressedDepth compression method",
                             constraints="Supported values: [png]",
                             check=_format_check(DEPTH_FORMATS, "rvl")),
                ParameterRow(self._name("depth_max"), DepthQuantization.depth_max_m,
                             "Maximum depth value, metres: depths at or beyond it are sent as "
                             "no depth (NaN)", min_value=0.01, max_value=100.0),
                ParameterRow(self._name("depth_quantization"),
                             DepthQuantization.depth_quantization,
                             "z0 of the inverse-depth quantization A = z0 (z0 + 1): larger, "
                             "finer steps (z^2 / A metres at depth z) and a nearer limit "
                             "A / (65536 - B) moving out; the defaults keep 32.6-200 mm in "
                             "steps of 3.2 um at 90 mm", min_value=1.0, max_value=150.0)]
        else:
            rows += [
                ParameterRow(self._name("format"), COMPRESSED_FORMATS[0],
                             "Compression method: png (lossless, keeps 16 bits) or jpeg "
                             "(lossy, 8 bits)", constraints="Supported values: [png, jpeg]",
                             check=_format_check(COMPRESSED_FORMATS, "tiff")),
                ParameterRow(self._name("jpeg_quality"), 95, "Image quality for JPEG format",
                             min_value=1, max_value=100, integer=True)]
        rows.append(ParameterRow(
            self._name("png_level"), 3,
            "Compression level for PNG format (zlib): higher, smaller and slower",
            min_value=0, max_value=9, integer=True))
        declare_parameters(self._node, rows, checks=checks)

    def _allowed(self) -> tuple[str, ...]:
        return (RAW, self._transport)

    def _enabled_transports(self) -> tuple[str, ...]:
        name = self._base + ".enable_pub_plugins"
        value = self._node.get_parameter(name).value
        if value is None:  # [] on the command line: rclpy leaves it unset
            value = []
        allowed = self._allowed()
        values = list(value) if isinstance(value, Sequence) and not isinstance(
            value, (str, bytes)) else None
        if values is None or not all(isinstance(v, str) for v in values):
            raise StartupError(
                f"{name} {value!r}: must be a list of transports, e.g. "
                f"\"['{RAW}', '{self._transport}']\"; allowed values: {', '.join(allowed)}")
        unknown = [v for v in values if v not in allowed]
        if unknown:
            hint = ""
            if self._depth and COMPRESSED in unknown:
                hint = (f" ({self.base_topic} is 32FC1 depth, which PNG/JPEG cannot carry: "
                        f"use {COMPRESSED_DEPTH})")
            elif not self._depth and COMPRESSED_DEPTH in unknown:
                hint = f" ({COMPRESSED_DEPTH} is for 32FC1 depth only)"
            raise StartupError(
                f"{name}: unknown or unsupported transport(s) "
                f"{', '.join(repr(u) for u in unknown)}{hint}; allowed values: "
                f"{', '.join(allowed)}")
        return tuple(dict.fromkeys([RAW, *values]))


def _format_check(supported: tuple[str, ...], upstream_only: str) -> Check:
    """A check of a ``format`` parameter: one of ``supported``; ``upstream_only`` (an
    image_transport format fingerps does not implement) is refused with that reason."""
    def check(value: Any) -> str | None:
        if value in supported:
            return None
        extra = f" ({upstream_only} is not implemented in fingerps)" if value == upstream_only \
            else ""
        return f"must be one of {', '.join(supported)}{extra}"
    return check
