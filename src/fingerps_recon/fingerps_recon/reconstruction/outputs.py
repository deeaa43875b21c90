"""recon_node's output messages, built from a reconstruction (no node): the normals, the
normal map, depth, albedo, the point cloud, and the fingerprint (:class:`Output` each, with
its topic; the node publishes them as they come).

:func:`output_messages` builds each message only when the caller asks for the next one, so
that the caller publishes each before the next is converted (the subscribers get the first
output sooner), and only those of the topics asked for (recon_node: the topics someone
subscribes to, as image_transport publishes nothing while nobody watches).
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from typing import Any, NamedTuple

import numpy as np
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image, PointCloud2
from std_msgs.msg import Header

from fingerps_recon.photometric.frames import ps_to_optical
from fingerps_recon.photometric.normal_map import normal_map_rgb
from fingerps_recon.photometric.pipeline import Reconstruction
from fingerps_recon.records.print_records import FILE_NAMES
from fingerps_recon.scan.scan_sequence import ScanOutcome
from fingerps_ros import topics
from fingerps_ros.image_conversion import array_to_image
from fingerps_ros.point_cloud_conversion import points_to_cloud

OUTPUT_TOPICS = (topics.POINTS, topics.NORMALS, topics.DEPTH, topics.ALBEDO,
                 topics.NORMAL_MAP)
"""The topics of :func:`output_messages`, in their order: the point cloud first (what robot
cells take), the picture for display last."""


class Output(NamedTuple):
    """One output: its topic, its message, and the image array and encoding it was built
    from (for a compressed companion; the points' array is None)."""

    topic: str
    message: Image | PointCloud2
    array: np.ndarray | None
    encoding: str


def output_messages(result: Reconstruction, header: Header,
                    wanted: Collection[str] = OUTPUT_TOPICS) -> Iterator[Output]:
    """The outputs of one burst with the burst's ``header``, in :data:`OUTPUT_TOPICS`'s
    order, of the topics in ``wanted`` (default all): the points (x y z intensity), the
    normals (32FC3, optical frame), depth and albedo (32FC1), the normal map (rgb8, of the
    enhanced normals if there are any)."""
    if topics.POINTS in wanted:
        yield Output(topics.POINTS, points_to_cloud(result.points_optical,
                                                    result.point_albedo, header=header),
                     None, "")
    if topics.NORMALS in wanted:
        normals_optical = normals_array(result)
        yield Output(topics.NORMALS, array_to_image(normals_optical, encoding="32FC3",
                                                    header=header), normals_optical, "32FC3")
    for topic, image in ((topics.DEPTH, result.depth_m), (topics.ALBEDO, result.albedo)):
        if topic in wanted:
            yield Output(topic, array_to_image(image, encoding="32FC1", header=header), image,
                         "32FC1")
    if topics.NORMAL_MAP in wanted:
        rgb = normal_map_array(result)
        yield Output(topics.NORMAL_MAP, array_to_image(rgb, encoding="rgb8", header=header),
                     rgb, "rgb8")


def normals_array(result: Reconstruction) -> np.ndarray:
    """The ``normals`` output: the unit normals in the optical frame, (H, W, 3) float32."""
    return ps_to_optical(result.normals_ps, dtype=np.float32)


def normal_map_array(result: Reconstruction) -> np.ndarray:
    """The ``normal_map`` output, (H, W, 3) uint8 RGB: of the enhanced normals if there are
    any (Eq. 12), else of the normals."""
    shown = result.enhanced_ps if result.enhanced_ps is not None else result.normals_ps
    return normal_map_rgb(shown, mask=result.mask)


def fingerprint_message(image: np.ndarray, stamp: Time) -> Image:
    """The rolled print (H, W) uint8 as a mono8 Image of the burst's ``stamp`` in the print's
    frame (``topics.FINGERPRINT_FRAME``)."""
    header = Header(stamp=stamp, frame_id=topics.FINGERPRINT_FRAME)
    return array_to_image(image, encoding="mono8", header=header)


def fingerprint_output(image: np.ndarray, stamp: Time) -> Output:
    """The ``fingerprint`` output of a rolled print (:func:`fingerprint_message`)."""
    return Output(topics.FINGERPRINT, fingerprint_message(image, stamp), image, "mono8")


def fill_scan_result(result: Any, outcome: ScanOutcome) -> None:
    """A Scan action's result (``fingerps_msgs/action/Scan``) of a scan that succeeded: the
    verdict, the best burst's normals (32FC3), normal map (rgb8) and points in its header,
    its print if made, the verdict's figures (NFIQ 2 among them) and the print's records
    when the goal asked for them."""
    rec, header, f = outcome.made.result, outcome.burst.source.header, outcome.verdict.figures
    result.success, result.accepted = True, outcome.accepted
    result.reasons, result.message = list(outcome.reasons), outcome.message
    result.normals = array_to_image(normals_array(rec), encoding="32FC3", header=header)
    result.normal_map = array_to_image(normal_map_array(rec), encoding="rgb8", header=header)
    result.points = points_to_cloud(rec.points_optical, rec.point_albedo, header=header)
    if outcome.fingerprint is not None:
        result.fingerprint = fingerprint_message(outcome.fingerprint, header.stamp)
    result.finger_coverage, result.saturated_fraction = f.coverage, f.saturated_fraction
    result.dark_fraction, result.ridge_visibility = f.dark_fraction, f.ridge_visibility
    result.motion_px, result.motion_correlation = f.motion_px, f.motion_correlation
    result.residual, result.nfiq2 = f.residual, f.nfiq2
    records = outcome.records
    if records is not None:
        result.wsq = records.wsq or b""
        result.iso_template = records.iso_template or b""
        result.ansi_nist_transaction = records.transaction or b""
        result.record_problems = [f"{FILE_NAMES[name]}: {why}"
                                  for name, why in records.reasons.items()]
