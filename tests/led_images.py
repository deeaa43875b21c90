"""Which LED lit a frame, for the driver's graph tests.

A frame of the simulated rig is compared with the rig's noiseless finger under each LED
alone (centred, normalised): the LED of the highest correlation is the one that lit it, so
a frame tagged with one LED but taken under another is caught. A folder camera
(``led_folder``) shows LED i as a flat image of value ``led_value(i)``.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from fingerps_driver.simulation import RigConfig, Scene, SimulatedRig
from fingerps_ros.image_conversion import image_to_array


def led_references(config: RigConfig | None = None) -> np.ndarray:
    """(K, H*W) float64: the rig's finger under each of its K LEDs, centred, unit norm."""
    rig = SimulatedRig(RigConfig() if config is None else config)
    refs = np.stack([rig.noiseless(Scene.FINGER, [k]).ravel()
                     for k in range(rig.led_count)]).astype(np.float64)
    refs -= refs.mean(axis=1, keepdims=True)
    return refs / np.linalg.norm(refs, axis=1, keepdims=True)


def leds_seen(frames: Iterable[object], references: np.ndarray) -> list[int]:
    """The LED whose light each frame (a TaggedFrame) shows."""
    seen = []
    for frame in frames:
        image = image_to_array(frame.image).astype(np.float64).ravel()  # type: ignore[attr-defined]
        image -= image.mean()
        seen.append(int(np.argmax(references @ image)))
    return seen


def led_value(led: int) -> int:
    """The grey value of LED ``led``'s image in ``led_folder``: 10 (led + 1)."""
    return 10 * (led + 1)


def led_folder(path: Path, led_count: int = 7) -> Path:
    """A DiLiGenT-layout folder for ``camera:=folder``: LED i's image 6 x 8 mono8 of
    ``led_value(i)``."""
    path.mkdir(parents=True)
    names = [f"led_{i}.png" for i in range(led_count)]
    for i, name in enumerate(names):
        assert cv2.imwrite(str(path / name), np.full((6, 8), led_value(i), np.uint8))
    (path / "filenames.txt").write_text("\n".join(names) + "\n")
    return path
