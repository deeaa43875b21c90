"""A camera that replays a folder of images captured elsewhere (DiLiGenT layout).

The folder holds ``filenames.txt`` (one image path a line, relative to the folder; blank
lines skipped) and the images: the i-th listed image is what the camera sees when LED i is
lit. Bursts still go through the board: the camera asks ``lit_leds`` which LEDs are lit
when it grabs (the board's acknowledged mask, or the emulator's physical state) and
returns that LED's image; with several LEDs lit, the sum of their images (light adds up,
clipped at full scale); with none, a black frame (the folder holds no dark frame).

Images are 8- or 16-bit PNG/TIFF/..., grey or colour (colour becomes Rec. 601 luma, as in
``fingerps_recon.offline.diligent_folder``), all of one size and bit depth; 8-bit images give mono8
frames, 16-bit images mono16. The images the LEDs need are read and checked once at
``open``, so a bad folder stops the driver at start with the file named.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from fingerps_driver.cameras.camera import (
    ENCODING_DTYPES,
    Camera,
    check_encoding,
    check_requested_size,
    to_mono,
)
from fingerps_driver.errors import CameraError, FingerpsDriverError

LIST_FILE = "filenames.txt"


class FolderCamera(Camera):
    """Replays the images of a DiLiGenT-layout folder, one per LED.

    Parameters
    ----------
    folder : str or Path
        The folder holding ``filenames.txt``.
    lit_leds : callable
        Returns the indices of the LEDs lit now.
    led_count : int
        LEDs that can be lit: the first ``led_count`` listed images are used (the folder
        may list more).
    width, height : int
        Size every image must have; 0 takes the first image's.
    encoding : str
        ``"mono8"`` or ``"mono16"`` that the images must give; empty: whatever they give.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        lit_leds: Callable[[], Sequence[int]],
        led_count: int,
        width: int = 0,
        height: int = 0,
        encoding: str = "",
    ) -> None:
        if led_count < 1:
            raise ValueError(f"led_count {led_count} must be >= 1")
        if encoding:
            check_encoding(encoding)
        check_requested_size(width, height, name="size")
        super().__init__(f"image folder {Path(folder)}", width=width, height=height,
                         encoding=encoding or "mono8")
        self._folder = Path(folder)
        self._lit_leds = lit_leds
        self._led_count = led_count
        self._size = (width, height)
        self._wanted_encoding = encoding
        self._images: tuple[np.ndarray, ...] = ()
        self._names: tuple[str, ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        """The image of each LED, as listed in filenames.txt (after ``open``)."""
        return self._names

    @property
    def is_open(self) -> bool:
        return bool(self._images)

    def _acquire(self) -> None:
        """Read and check the images of the LEDs; ``encoding`` and the size are known then.

        Raises
        ------
        CameraError
            No ``filenames.txt``, fewer images than LEDs, an image missing or unreadable, or
            images of different sizes or bit depths; the message names the file.
        """
        listing = self._folder / LIST_FILE
        try:
            lines = listing.read_text(encoding="utf-8").splitlines()
        except OSError as exc:
            raise CameraError(
                f"cannot read {listing} ({exc.strerror or exc}): camera_folder must be a "
                f"folder in the DiLiGenT layout, with {LIST_FILE} listing one image a line"
            ) from None
        names = tuple(line.strip() for line in lines if line.strip())
        if len(names) < self._led_count:
            raise CameraError(
                f"{listing} lists {len(names)} images for {self._led_count} LEDs; the i-th "
                "listed image is what LED i lights, so list one per LED")
        images = []
        for index, name in enumerate(names[: self._led_count]):
            images.append(self._read(index, name, images[0] if images else None))
        self._names = names[: self._led_count]
        self._height, self._width = images[0].shape
        self._encoding = "mono8" if images[0].dtype == np.uint8 else "mono16"
        for image in images:
            image.setflags(write=False)
        self._images = tuple(images)

    def _read(self, index: int, name: str, first: np.ndarray | None) -> np.ndarray:
        path = self._folder / name
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise CameraError(
                f"{self.source}: cannot read {path} (image of LED {index}); check that it "
                "exists and is an image file")
        if raw.dtype not in (np.uint8, np.uint16):
            raise CameraError(f"{self.source}: {path} holds {raw.dtype} pixels; images must be "
                              "8- or 16-bit")
        encoding = "mono8" if raw.dtype == np.uint8 else "mono16"
        if self._wanted_encoding and encoding != self._wanted_encoding:
            raise CameraError(
                f"{self.source}: {path} is {raw.dtype.itemsize * 8}-bit, not "
                f"{self._wanted_encoding}; set the pixel format to {encoding} (or leave it "
                "empty)")
        image = to_mono(raw, encoding=encoding, source=f"{self.source} ({path.name})")
        height, width = image.shape
        if first is not None and (image.shape != first.shape or image.dtype != first.dtype):
            raise CameraError(
                f"{self.source}: {path} (LED {index}) is {width}x{height} {image.dtype}, but "
                f"the first image is {first.shape[1]}x{first.shape[0]} {first.dtype}; all "
                "images must have one size and bit depth")
        if self._size != (0, 0) and (width, height) != self._size:
            raise CameraError(
                f"{self.source}: {path} (LED {index}) is {width}x{height}, not the "
                f"{self._size[0]}x{self._size[1]} asked for (camera_width/camera_height; 0 "
                "takes the images' size)")
        return image

    def _release(self) -> None:
        """Forget the images."""
        self._images = ()

    def _frame(self, timeout_s: float) -> np.ndarray:
        """The image of the LED lit now (sum if several, black if none)."""
        try:
            lit = sorted(set(self._lit_leds()))
        except FingerpsDriverError as exc:
            raise CameraError(f"no frame from {self.source}: cannot tell which LEDs are lit "
                              f"({exc})") from exc
        beyond = [led for led in lit if not 0 <= led < len(self._images)]
        if beyond:
            raise CameraError(f"{self.source} has no image for LED(s) {beyond} "
                              f"(it holds LEDs 0..{len(self._images) - 1})")
        dtype = ENCODING_DTYPES[self._encoding]
        if not lit:
            image = np.zeros((self._height, self._width), dtype)
        elif len(lit) == 1:
            image = self._images[lit[0]].copy()
        else:
            total = np.sum([self._images[led] for led in lit], axis=0, dtype=np.uint32)
            image = np.minimum(total, np.iinfo(dtype).max).astype(dtype)
        return image
