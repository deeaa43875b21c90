"""recon_node's parameters: their table (names, defaults, descriptions, ranges, checks) and
the settings read from them (:class:`~fingerps_recon.reconstruction.worker.ReconSettings`)."""

from __future__ import annotations

from rclpy.node import Node
from rclpy.parameter import Parameter

from fingerps_recon.photometric.full_scale import MONO16_FULL_SCALE
from fingerps_recon.photometric.kernel_threads import set_thread_limit
from fingerps_recon.photometric.option_rows import (
    ENHANCE,
    HK_ITERATIONS,
    MASK_THRESHOLD,
    MODEL,
    PROJECTION,
    RIDGE_GAIN,
    RIDGE_PATCH,
    WORKING_DISTANCE,
)
from fingerps_recon.photometric.pipeline import Model, Projection, ReconstructionOptions
from fingerps_recon.reconstruction.burst_intake import BurstLimits
from fingerps_recon.reconstruction.worker import ReconSettings
from fingerps_ros.parameter_table import ParameterRow

PARAMETERS = (
    MODEL,
    PROJECTION,
    HK_ITERATIONS,
    ParameterRow(
        "threads", 0,
        "Threads of the per-pixel solvers; 0 = every core. On a machine whose other cores "
        "are busy (driver, recorder) fewer threads can finish a burst sooner",
        min_value=0, max_value=256, integer=True),
    ParameterRow(
        "queue_depth", 2,
        "Bursts waiting for reconstruction; the oldest is dropped beyond this",
        min_value=1, max_value=100, integer=True, read_only=True),
    MASK_THRESHOLD,
    ParameterRow(
        "fingerprint", False,
        "Also publish the rolled-equivalent 500 ppi print of every burst on 'fingerprint' "
        "(mono8, ridges dark; it costs time on top of the reconstruction (README, Real "
        "time), so off by default; the Scan action always makes one)"),
    ENHANCE,
    RIDGE_PATCH,
    RIDGE_GAIN,
    WORKING_DISTANCE,
    MONO16_FULL_SCALE,
    ParameterRow(
        "max_image_width", BurstLimits.max_width,
        "Widest image accepted (bursts, dark frames, flat-field maps, the camera_info "
        "the calibration is prepared for), pixels; wider ones are refused on arrival",
        min_value=1, max_value=65535, integer=True),
    ParameterRow(
        "max_image_height", BurstLimits.max_height,
        "Tallest image accepted, pixels (as max_image_width)", min_value=1,
        max_value=65535, integer=True),
    ParameterRow(
        "max_burst_frames", BurstLimits.max_frames,
        "Most frames a burst (or flat-field maps a flat field) may carry; more are "
        "refused on arrival", min_value=3, max_value=256, integer=True),
    ParameterRow(
        "health_window", 5,
        "Recent bursts /diagnostics judges: WARN while one of them failed, ERROR when "
        "all of them did", min_value=1, max_value=1000, integer=True, read_only=True),
)
"""recon_node's parameter table (``w`` odd, ``model`` and ``projection`` one of theirs), in
the order they are declared (``fingerps_ros.parameters.declare_parameters``)."""


def follow_threads(node: Node) -> None:
    """Apply ``threads`` now and every new value of it from the next burst on."""
    set_thread_limit(int(node.get_parameter("threads").value))

    def on_set(params: list[Parameter]) -> None:
        for param in params:
            if param.name == "threads":
                set_thread_limit(int(param.value))
    node.add_post_set_parameters_callback(on_set)


def read_settings(node: Node) -> ReconSettings:
    """The settings a burst is reconstructed with, from ``node``'s parameters now."""
    g = node.get_parameter
    options = ReconstructionOptions(
        model=Model(g("model").value), hk_iterations=int(g("hk_iterations").value),
        projection=Projection(g("projection").value),
        mask_threshold=float(g("mask_threshold").value), enhance=bool(g("enhance").value),
        w=int(g("w").value), k=float(g("k").value),
        working_distance_m=float(g("working_distance").value))
    limits = BurstLimits(max_width=int(g("max_image_width").value),
                         max_height=int(g("max_image_height").value),
                         max_frames=int(g("max_burst_frames").value))
    return ReconSettings(options, limits, float(g("mono16_full_scale").value),
                         fingerprint=bool(g("fingerprint").value))

