"""A Burst message turned into the arrays the pipeline takes, without a graph
(``reconstruction.burst_intake.burst_inputs``): images in LED order whatever the frames'
order, the full scale of each encoding, the dark frame, the camera matrix. The refusals of
bad messages are tests/core/test_recon_bad_input.py's."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo

from fingerps_msgs.msg import Burst, TaggedFrame
from fingerps_recon.errors import IncompleteBurstError
from fingerps_recon.reconstruction.burst_intake import FULL_SCALE, BurstLimits, burst_inputs
from fingerps_ros.errors import FingerpsError
from fingerps_ros.image_conversion import array_to_image

K = np.array([[600.0, 0.0, 4.5], [0.0, 600.0, 3.5], [0.0, 0.0, 1.0]])


def stack(encoding: str) -> np.ndarray:
    """Four 8x10 images: a ramp with an offset of their own."""
    dtype = np.uint16 if encoding == "mono16" else np.uint8
    ramp = np.arange(80).reshape(8, 10)
    return np.stack([ramp + 100 * (k + 1) % 250 for k in range(4)]).astype(dtype)


def message(images: np.ndarray, encoding: str, *, order: list[int],
            dark: np.ndarray | None = None) -> Burst:
    frames = [TaggedFrame(led_index=k, image=array_to_image(images[k], encoding=encoding))
              for k in order]
    msg = Burst(burst_id=9, frames=frames, camera_info=CameraInfo(
        width=10, height=8, k=[float(x) for x in K.reshape(-1)]))
    if dark is not None:
        msg.has_dark_frame = True
        msg.dark_frame.image = array_to_image(dark, encoding=encoding)
    return msg


@pytest.mark.parametrize("encoding", ["mono8", "mono16"])
def test_the_arrays_of_a_burst_in_led_order(encoding: str) -> None:
    images = stack(encoding)
    dark = np.full((8, 10), 3, images.dtype)
    inputs = burst_inputs(message(images, encoding, order=[2, 0, 3, 1], dark=dark), 4,
                          mono16_full_scale=1023.0)
    np.testing.assert_array_equal(inputs.images, images)
    assert inputs.full_scale == (1023.0 if encoding == "mono16" else FULL_SCALE["mono8"])
    np.testing.assert_array_equal(inputs.dark, dark)
    np.testing.assert_array_equal(inputs.camera_matrix, K)


def test_no_dark_frame_is_none_and_the_limits_apply() -> None:
    msg = message(stack("mono8"), "mono8", order=[0, 1, 2, 3])
    assert burst_inputs(msg, 4).dark is None
    with pytest.raises(FingerpsError, match="beyond max_image_width"):
        burst_inputs(msg, 4, limits=BurstLimits(max_width=9))
    with pytest.raises(IncompleteBurstError, match=r"missing \[4\]"):
        burst_inputs(msg, 5)
