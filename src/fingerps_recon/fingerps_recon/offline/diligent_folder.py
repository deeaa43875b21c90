"""Reading a photometric-stereo folder in the DiLiGenT layout into arrays.

Layout (DiLiGenT, Shi et al. 2016)::

    filenames.txt          one image path a line, relative to the folder (blank lines skipped)
    light_directions.txt   one row "x y z" per image: unit vector towards the light, PS frame
                           (x right, y up, z towards the camera)
    light_intensities.txt  optional; one row per image, three numbers (R G B) or one
    mask.png               optional; non-zero pixels are the object
    Normal_gt.mat          optional; MATLAB v5 file with ``Normal_gt`` (H, W, 3), PS frame
    normal_gt.npy          optional alternative to Normal_gt.mat (used if the .mat is absent)

Images are 8- or 16-bit PNG, grey or colour, all of one size and bit depth.

Colour to grey (:class:`ColourConversion`), one rule a folder:

- grey images are used as they are;
- colour images with three-channel intensities (DiLiGenT): each channel is divided by its
  intensity and the channels are averaged, ``mean_c(I_c / e_c)``, which is what DiLiGenT's
  own code does. So that the grey values stay in the PNG's units (for the shadow and
  saturation levels), the result is multiplied by the image's harmonic-mean intensity
  ``e = 3 / sum_c(1 / e_c)`` and ``e`` becomes that image's intensity: the grey value is the
  mean of the channels weighted by ``1 / e_c`` (weights summing to one);
- colour images otherwise (no intensities, or one channel): Rec. 601 luma
  ``0.299 R + 0.587 G + 0.114 B``; one-channel intensities are used as they are;
- grey images with three-channel intensities use the Rec. 601 luma of the intensities.

A pixel any of whose channels is at or above the saturation level is set to the full-scale
value in the grey image, so that the reconstruction leaves it out however the channels mix.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

import cv2
import numpy as np
import scipy.io

from fingerps_recon.errors import FingerpsReconError

#: Rec. 601 luma weights of (R, G, B).
LUMA_601 = np.array([0.299, 0.587, 0.114])
#: Light rows whose length is within this of 1 are normalised; the others are refused.
UNIT_TOLERANCE = 0.02
#: Default shadow level as a fraction of full scale, by bit depth: 8-bit data carry
#: quantisation and sensor noise of a few levels (2 % = 5 of 255); 16-bit data are finer.
DEFAULT_SHADOW_FRACTION = {8: 0.02, 16: 0.002}


class ColourConversion(Enum):
    """How the images of a folder were turned into grey (see the module docstring)."""

    GREY = "grey images used as they are"
    INVERSE_INTENSITY = (
        "colour: each channel divided by its light intensity, then averaged (scaled by the "
        "harmonic-mean intensity, which is passed on as the image's intensity)")
    LUMA = "colour: Rec. 601 luma 0.299 R + 0.587 G + 0.114 B"


@dataclass(frozen=True)
class PhotometricDataset:
    """A DiLiGenT-layout folder read into arrays.

    Attributes
    ----------
    images : (K, H, W) float32
        Grey images in the PNG's units (0..255 or 0..65535); saturated pixels hold the
        full-scale value.
    lights_ps : (K, 3) float64
        Unit light directions, PS frame.
    intensities : (K,) float64 or None
        Relative light intensity of each grey image; None when the folder has none.
    mask : (H, W) bool or None
        ``mask.png`` (non-zero pixels); None when the folder has no mask.
    names : tuple of str
        The image paths as listed in ``filenames.txt``.
    bit_depth : int
        8 or 16.
    normal_gt : (H, W, 3) float64 or None
        Ground-truth normals (``Normal_gt.mat`` or ``normal_gt.npy``), PS frame.
    normal_gt_file : str or None
        The file they came from.
    conversion : ColourConversion
    shadow_level, saturation_level : float
        The levels used, in the PNG's units.
    """

    images: np.ndarray
    lights_ps: np.ndarray
    intensities: np.ndarray | None
    mask: np.ndarray | None
    names: tuple[str, ...]
    bit_depth: int
    normal_gt: np.ndarray | None
    normal_gt_file: str | None
    conversion: ColourConversion
    shadow_level: float
    saturation_level: float

    @property
    def full_scale(self) -> float:
        """The largest value of the bit depth: 255 or 65535."""
        return float(2**self.bit_depth - 1)


def default_shadow_level(bit_depth: int) -> float:
    """Shadow level used when none is given: 5.1 (8 bit) or 131.07 (16 bit)."""
    return DEFAULT_SHADOW_FRACTION[bit_depth] * (2**bit_depth - 1)


def load_diligent_folder(
    path: str | os.PathLike,
    *,
    shadow_level: float | None = None,
    saturation_level: float | None = None,
) -> PhotometricDataset:
    """Read a DiLiGenT-layout folder (see the module docstring).

    Parameters
    ----------
    path : str or path-like
        The folder.
    shadow_level : float, optional
        PNG values at or below this are shadow. An image with nothing above it (inside the
        mask, when there is one) is refused as dark. Default :func:`default_shadow_level`.
    saturation_level : float, optional
        PNG values at or above this (in any channel) are saturated. Default: the full-scale
        value (255 or 65535). Must lie above ``shadow_level`` and at most at full scale.

    Returns
    -------
    PhotometricDataset

    Raises
    ------
    FingerpsReconError
        With a one-line message naming the file and the problem, for a missing folder or
        file, an unreadable or odd image, images of different sizes or bit depths, a light
        or intensity row count that differs from the image count, malformed, zero or
        non-unit light rows, non-positive intensities, a mask of another size or selecting
        nothing, dark images, or a malformed ground truth.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise FingerpsReconError(f"{folder}: no such folder")
    names = _read_filenames(folder / "filenames.txt")
    count = len(names)
    lights = _read_lights(folder / "light_directions.txt", count)
    channel_intensities = _read_intensities(folder / "light_intensities.txt", count)
    first = _read_png(folder / names[0], names[0])
    bit_depth = _bits(first)
    full_scale = float(2**bit_depth - 1)
    shadow = default_shadow_level(bit_depth) if shadow_level is None else float(shadow_level)
    saturation = full_scale if saturation_level is None else float(saturation_level)
    if not (np.isfinite(shadow) and shadow >= 0):
        raise FingerpsReconError(f"the shadow level must be >= 0, got {shadow:g}")
    if not (np.isfinite(saturation) and shadow < saturation <= full_scale):
        raise FingerpsReconError(
            f"the saturation level must lie above the shadow level {shadow:g} and at most at "
            f"the {bit_depth}-bit full scale {full_scale:g}, got {saturation:g}")
    conversion, weights, intensities = _conversion(first.ndim == 3, channel_intensities,
                                                   count=count)

    # One image at a time, so that only the grey stack is ever held (DiLiGenT: 96 colour
    # 16-bit images would take 0.7 GB as one float64 array).
    height, width = first.shape[:2]
    images = np.empty((count, height, width), dtype=np.float32)
    for i, name in enumerate(names):
        img = first if i == 0 else _read_png(folder / name, name)
        if img.shape[:2] != first.shape[:2]:
            raise FingerpsReconError(
                f"{name} is {_size(img)} but {names[0]} is {_size(first)}: all images must "
                "have one size")
        if img.dtype != first.dtype:
            raise FingerpsReconError(
                f"{name} is {_bits(img)}-bit but {names[0]} is {_bits(first)}-bit: all images "
                "must have one bit depth")
        if img.ndim != first.ndim:
            raise FingerpsReconError(
                f"{name} and {names[0]} mix grey and colour: all images must be one kind")
        images[i] = _grey(img, None if weights is None else weights[i],
                          saturation_level=saturation, full_scale=full_scale)
    mask = _read_mask(folder / "mask.png", (height, width))

    region = images[:, mask] if mask is not None else images.reshape(count, -1)
    brightest = region.max(axis=1)
    for name, value in zip(names, brightest, strict=True):
        if value <= shadow:
            where = "inside mask.png" if mask is not None else "anywhere"
            raise FingerpsReconError(
                f"{name} is dark: nothing {where} is above the shadow level {shadow:g} (its "
                f"largest value is {value:g}); check the image or lower the shadow threshold")

    normal_gt, gt_file = _read_normal_gt(folder, (height, width))
    return PhotometricDataset(
        images=images, lights_ps=lights, intensities=intensities, mask=mask, names=names,
        bit_depth=bit_depth, normal_gt=normal_gt, normal_gt_file=gt_file,
        conversion=conversion, shadow_level=shadow, saturation_level=saturation)


def _size(img: np.ndarray) -> str:
    return f"{img.shape[1]}x{img.shape[0]}"


def _bits(img: np.ndarray) -> int:
    return 8 * img.dtype.itemsize


def _read_filenames(path: Path) -> tuple[str, ...]:
    if not path.is_file():
        raise FingerpsReconError(f"{path}: missing; list one image file a line in it")
    names = tuple(line.strip() for line in _read_text(path).splitlines() if line.strip())
    if len(names) < 3:
        raise FingerpsReconError(
            f"{path} lists {len(names)} image(s): photometric stereo needs at least 3")
    return names


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FingerpsReconError(f"{path}: cannot read it ({exc})") from None


def _read_png(path: Path, name: str) -> np.ndarray:
    """One image as (H, W) or (H, W, 3) BGR (OpenCV's order), uint8 or uint16."""
    if not path.is_file():
        raise FingerpsReconError(f"{name} is listed in filenames.txt but {path} does not exist")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FingerpsReconError(f"{path}: not a readable image")
    if img.dtype not in (np.uint8, np.uint16):
        raise FingerpsReconError(f"{path}: {img.dtype} pixels; use 8- or 16-bit PNG")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, :3]  # alpha dropped
    elif img.ndim != 2:
        raise FingerpsReconError(f"{path}: {img.shape} pixels; use grey or RGB images")
    return img


def _read_rows(path: Path, widths: tuple[int, ...]) -> np.ndarray:
    """Rows of numbers (whitespace or comma separated), all of one of ``widths``."""
    rows = []
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = [float(x) for x in line.replace(",", " ").split()]
        except ValueError:
            raise FingerpsReconError(
                f"{path.name} line {number}: {line.strip()!r} is not a row of numbers") from None
        if len(row) not in widths or (rows and len(row) != len(rows[0])):
            expected = " or ".join(str(w) for w in widths)
            raise FingerpsReconError(
                f"{path.name} line {number}: {len(row)} numbers, expected {expected} "
                "(the same on every line)")
        if not np.all(np.isfinite(row)):
            raise FingerpsReconError(f"{path.name} line {number}: not finite: {line.strip()!r}")
        rows.append(row)
    return np.array(rows, dtype=np.float64).reshape(len(rows), -1)


def _read_lights(path: Path, count: int) -> np.ndarray:
    if not path.is_file():
        raise FingerpsReconError(f"{path}: missing; give one light direction 'x y z' a line")
    rows = _read_rows(path, (3,))
    if len(rows) != count:
        raise FingerpsReconError(
            f"{path.name} has {len(rows)} rows but filenames.txt lists {count} images: give "
            "one light direction per image")
    norms = np.linalg.norm(rows, axis=1)
    for i, norm in enumerate(norms):
        if norm < 1e-9:
            raise FingerpsReconError(f"{path.name} row {i + 1} is a zero vector: no direction")
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            raise FingerpsReconError(
                f"{path.name} row {i + 1} has length {norm:.4g}, not a unit vector: give unit "
                "directions (put light strengths in light_intensities.txt)")
    return rows / norms[:, None]


def _read_intensities(path: Path, count: int) -> np.ndarray | None:
    """(K, 1) or (K, 3) intensities, or None when the file is absent."""
    if not path.exists():
        return None
    rows = _read_rows(path, (1, 3))
    if len(rows) != count:
        raise FingerpsReconError(
            f"{path.name} has {len(rows)} rows but filenames.txt lists {count} images: give "
            "one intensity row per image")
    bad = np.flatnonzero(~np.all(rows > 0, axis=1))
    if bad.size:
        raise FingerpsReconError(
            f"{path.name} row {bad[0] + 1} is {rows[bad[0]].tolist()}: intensities must be > 0")
    return rows


def _read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
    if not path.exists():
        return None
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FingerpsReconError(f"{path}: not a readable image")
    if img.ndim == 3:
        img = img[:, :, :3].max(axis=2)  # any colour channel; alpha ignored
    if img.shape != shape:
        raise FingerpsReconError(
            f"mask.png is {img.shape[1]}x{img.shape[0]} but the images are "
            f"{shape[1]}x{shape[0]}: give a mask of the images' size")
    mask = img > 0
    if not mask.any():
        raise FingerpsReconError("mask.png selects nothing (all pixels are zero)")
    return mask


def _conversion(
    colour: bool, channel_intensities: np.ndarray | None, *, count: int
) -> tuple[ColourConversion, np.ndarray | None, np.ndarray | None]:
    """The folder's rule, its (K, 3) channel weights (None for grey) and (K,) intensities."""
    three = channel_intensities is not None and channel_intensities.shape[1] == 3
    one = None if channel_intensities is None or three else channel_intensities[:, 0]
    if not colour:
        return ColourConversion.GREY, None, channel_intensities @ LUMA_601 if three else one
    if three:
        inverse = 1.0 / channel_intensities
        weights = inverse / inverse.sum(axis=1, keepdims=True)
        harmonic = 3.0 / inverse.sum(axis=1)
        return ColourConversion.INVERSE_INTENSITY, weights, harmonic
    return ColourConversion.LUMA, np.tile(LUMA_601, (count, 1)), one


def _grey(
    img: np.ndarray, weights: np.ndarray | None, *, saturation_level: float, full_scale: float
) -> np.ndarray:
    """(H, W) float32 grey image; pixels with a channel >= the saturation level at full scale.

    ``img`` is grey or BGR as OpenCV reads it; ``weights`` (3,) are in RGB order.
    """
    if weights is None:
        grey = img.astype(np.float32)
        saturated = img >= saturation_level
    else:
        grey = (img.astype(np.float64) @ weights[::-1]).astype(np.float32)
        brightest = np.maximum(np.maximum(img[:, :, 0], img[:, :, 1]), img[:, :, 2])
        saturated = brightest >= saturation_level
    grey[saturated] = full_scale
    return grey


def _read_normal_gt(
    folder: Path, shape: tuple[int, int]
) -> tuple[np.ndarray | None, str | None]:
    mat, npy = folder / "Normal_gt.mat", folder / "normal_gt.npy"
    if mat.exists():
        try:
            content = scipy.io.loadmat(str(mat))
        except NotImplementedError:
            raise FingerpsReconError(
                f"{mat}: a MATLAB v7.3 file; save it as v5 (-v7 or older)") from None
        except (OSError, ValueError, TypeError) as exc:
            raise FingerpsReconError(f"{mat}: cannot read it ({exc})") from None
        if "Normal_gt" not in content:
            raise FingerpsReconError(f"{mat}: has no variable 'Normal_gt'")
        gt, source = content["Normal_gt"], mat.name
    elif npy.exists():
        try:
            gt = np.load(npy, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise FingerpsReconError(f"{npy}: cannot read it ({exc})") from None
        source = npy.name
    else:
        return None, None
    gt = np.asarray(gt)
    if gt.shape != (*shape, 3) or not np.issubdtype(gt.dtype, np.number):
        raise FingerpsReconError(
            f"{source}: normals of shape {gt.shape} {gt.dtype}, expected numbers of shape "
            f"{(*shape, 3)} (the images' H x W x 3)")
    gt = gt.astype(np.float64)
    if not np.all(np.isfinite(gt)):
        raise FingerpsReconError(f"{source}: contains NaN or infinite values")
    return gt, source
