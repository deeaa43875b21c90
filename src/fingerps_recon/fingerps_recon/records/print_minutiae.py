"""The minutiae and NFIQ 2 quality of a 500 ppi print, by NIST's NBIS (``nbis-py``).

NBIS's mindtct finds the minutiae: position, type, direction (in 11.25 degree steps,
counter-clockwise on the image from +x, pointing into the ridge for a ridge ending and
between the branches for a bifurcation: the ISO/IEC 19794-2 convention) and reliability;
NFIQ 2 scores the print. This module only puts them into arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from fingerps_recon.errors import RecordError

#: ISO/IEC 19794-2 minutia type codes.
RIDGE_ENDING, BIFURCATION = 1, 2
#: Smallest side of a print given to NBIS, pixels (3.3 mm at 500 ppi): NBIS's mindtct crashes
#: the process on a 10 x 10 image; 32 and more are handled.
MIN_SIDE_PX = 64
@dataclass(frozen=True)
class PrintMinutiae:
    """Minutiae of one print in its pixel frame (x right, y down, origin top-left).

    ``x_px``, ``y_px`` (N,) int; ``angle_deg`` (N,) float in [0, 360), ISO convention (module
    docstring); ``kind`` (N,) uint8 ISO type (1 ridge ending, 2 bifurcation); ``quality`` (N,)
    uint8 1-100 (mindtct's reliability); ``nfiq2`` 0-100, None when NFIQ 2 could not score
    the print (``nfiq2_problem`` says why); ``width``, ``height`` of the print.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    angle_deg: np.ndarray
    kind: np.ndarray
    quality: np.ndarray
    nfiq2: int | None
    width: int
    height: int
    nfiq2_problem: str = ""

    def __len__(self) -> int:
        return int(self.x_px.size)


@lru_cache(maxsize=2)
def _extractor(nfiq2: bool):
    """NBIS's extractor at 500 ppi, with or without NFIQ 2 (which fails on some prints)."""
    try:
        import nbis
    except ImportError as exc:
        raise RecordError(f"NIST NBIS is not installed ({exc}): pip install nbis-py") from exc
    settings = nbis.NbisExtractorSettings(min_quality=0.0, get_center=False,
                                          check_fingerprint=False, compute_nfiq2=nfiq2,
                                          ppi=500.0)
    return nbis.new_nbis_extractor(settings)


def find_minutiae(image: np.ndarray) -> PrintMinutiae:
    """NBIS's minutiae and NFIQ 2 of a 500 ppi print (H, W) uint8, ridges dark.

    Raises
    ------
    RecordError
        When the image is not 2-D uint8 or NBIS cannot read it (the reason says which).
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise RecordError(f"a print is one 8-bit grey channel: got {img.dtype} {img.shape}")
    if min(img.shape) < MIN_SIDE_PX:
        raise RecordError(f"a {img.shape[1]} x {img.shape[0]} px print is too small for NBIS "
                          f"(at least {MIN_SIDE_PX} px a side)")
    ok, png = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise RecordError("OpenCV could not encode the print for NBIS")
    nfiq2: int | None = None
    nfiq2_problem = ""
    with_nfiq2 = _extractor(True)
    import nbis  # importable: _extractor has imported it

    try:
        try:
            found = with_nfiq2.extract_minutiae(png.tobytes())
            nfiq2 = int(found.quality().score)
        except nbis.NbisError.Nfiq2ComputeFailed as exc:  # the minutiae without NFIQ 2
            nfiq2_problem = f"NFIQ 2 could not score the print ({type(exc).__name__} {exc})"
            found = _extractor(False).extract_minutiae(png.tobytes())
    except Exception as exc:  # nbis raises its own NbisError / InternalError
        raise RecordError(f"NBIS could not find a fingerprint's minutiae in the {img.shape[1]} "
                          f"x {img.shape[0]} print ({type(exc).__name__} {exc}): no minutiae "
                          "record") from exc
    rows = [(m.x(), m.y(), m.angle(), 1 if m.kind().name == "RIDGE_ENDING" else 2,
             m.reliability()) for m in found.get()]
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    return PrintMinutiae(
        x_px=table[:, 0].astype(np.int64), y_px=table[:, 1].astype(np.int64),
        angle_deg=table[:, 2] % 360.0, kind=table[:, 3].astype(np.uint8),
        quality=np.clip(np.rint(table[:, 4] * 100.0), 1, 100).astype(np.uint8),
        nfiq2=nfiq2, width=img.shape[1], height=img.shape[0], nfiq2_problem=nfiq2_problem)
