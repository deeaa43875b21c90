"""The ways a DiLiGenT-layout folder is broken for the tests of bad input.

Shared by the loader's tests (``core/test_diligent_folder.py``) and offline_recon's
(``graph/test_offline_recon.py``): :func:`spoil_folder` breaks a valid folder of four or
more 8-bit grey images in the one way its case names; each test keeps the message it
expects for each case it uses. The images spoiled are found in the folder's own
filenames.txt (the third one, or the second for the dark image), the sizes from its first
image, so the same case fits folders of any size and naming.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import scipy.io

LIGHT_ROWS = {"light rows != images": [], "malformed light row": ["0 x 1"],
              "light row of 2 numbers": ["0 1"], "zero light row": ["0 0 0"],
              "non-unit light row": ["0 0 0.5"]}
"""light_directions.txt cut to all its rows but the last, then these."""

CASES = (
    "filenames.txt missing", "listed image missing", "image unreadable",
    "image sizes differ", "bit depths differ", "grey and colour", "all-dark image",
    "too few images", "light_directions.txt missing", *LIGHT_ROWS,
    "intensity rows != images", "zero intensity", "mask size", "mask selects nothing",
    "Normal_gt.mat shape", "Normal_gt.mat variable",
)
"""Every case :func:`spoil_folder` knows."""


def spoil_folder(folder: Path, case: str) -> None:
    """Break the valid DiLiGenT-layout ``folder`` in the one way ``case`` (of `CASES`) names."""
    names = (folder / "filenames.txt").read_text().split()
    height, width = cv2.imread(str(folder / names[0]), cv2.IMREAD_UNCHANGED).shape[:2]
    third = str(folder / names[2])
    lights = folder / "light_directions.txt"
    if case in LIGHT_ROWS:
        lights.write_text("\n".join([*lights.read_text().splitlines()[:-1], *LIGHT_ROWS[case]]))
    elif case == "filenames.txt missing":
        (folder / "filenames.txt").unlink()
    elif case == "listed image missing":
        Path(third).unlink()
    elif case == "image unreadable":
        Path(third).write_bytes(b"not a png")
    elif case == "image sizes differ":
        cv2.imwrite(third, np.full((height, width + 1), 99, np.uint8))
    elif case == "bit depths differ":
        cv2.imwrite(third, np.full((height, width), 9999, np.uint16))
    elif case == "grey and colour":
        cv2.imwrite(third, np.full((height, width, 3), 99, np.uint8))
    elif case == "all-dark image":
        cv2.imwrite(str(folder / names[1]), np.full((height, width), 2, np.uint8))
    elif case == "too few images":
        (folder / "filenames.txt").write_text("\n".join(names[:2]) + "\n")
    elif case == "light_directions.txt missing":
        lights.unlink()
    elif case == "intensity rows != images":
        np.savetxt(folder / "light_intensities.txt", np.ones(len(names) + 1))
    elif case == "zero intensity":
        np.savetxt(folder / "light_intensities.txt", np.where(np.arange(len(names)) == 1, 0, 1.0))
    elif case == "mask size":
        cv2.imwrite(str(folder / "mask.png"), np.full((height + 1, width), 255, np.uint8))
    elif case == "mask selects nothing":
        cv2.imwrite(str(folder / "mask.png"), np.zeros((height, width), np.uint8))
    elif case == "Normal_gt.mat shape":
        scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": np.zeros((height, width))})
    elif case == "Normal_gt.mat variable":
        scipy.io.savemat(folder / "Normal_gt.mat", {"normals": np.zeros((height, width, 3))})
    else:
        raise AssertionError(f"unknown case {case!r}; known: {', '.join(CASES)}")
