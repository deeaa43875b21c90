"""The camera's calibration as camera_info_manager keeps it: loaded from a URL, replaced by
``set_camera_info``, stored back to the URL's file.

A plain class (no ROS graph): driver_node converts CameraInfo messages and calls it. The
rules follow ``camera_info_manager`` (see `fingerps_calib.intrinsics.camera_info_url`), with three
differences a user sees:

- a calibration is validated before it is taken (the camera's image size, a finite K with
  fx, fy > 0, a distortion model fingerps knows with its number of coefficients), and a
  refused one changes nothing;
- it is taken only once it is stored (camera_info_manager takes it even when storing
  fails, so the next start silently loses it);
- a missing, unreadable or wrong-size file is one line saying what was looked for; the
  camera then publishes its fallback (the simulated rig's true intrinsics, else none:
  K = 0), so that ``set_camera_info`` can still put a calibration in place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from fingerps_calib.errors import FingerpsCalibError
from fingerps_calib.intrinsics.camera_info_url import (
    check_camera_name,
    resolve_camera_info_url,
    store_camera_info,
)
from fingerps_calib.intrinsics.camera_info_yaml import (
    DISTORTION_LENGTHS,
    CameraIntrinsics,
    load_camera_info,
)


@dataclass(frozen=True)
class CameraCalibration:
    """What the camera publishes as CameraInfo and where it came from.

    Attributes
    ----------
    intrinsics : CameraIntrinsics or None
        None: uncalibrated (CameraInfo with K = 0).
    source : str
        For logs and diagnostics: the file, "the simulated rig's true intrinsics" or "none".
    problem : str or None
        Why the calibration file was not used (missing, unreadable, wrong size), one line.
    """

    intrinsics: CameraIntrinsics | None
    source: str
    problem: str | None = None


class CameraInfoManager:
    """Load, validate and store one camera's calibration.

    Parameters
    ----------
    camera_name : str
        ``${NAME}`` of the URL and the name written into the file.
    url : str
        camera_info_manager URL; empty = ``file://${ROS_HOME}/camera_info/${NAME}.yaml``.
    width, height : int
        The size of the camera's images.
    fallback : CameraIntrinsics or None
        Published when no calibration file is usable (the simulated rig's truth).
    fallback_source : str
        How `CameraCalibration.source` names the fallback.
    strict : bool
        A missing, unreadable or wrong-size file raises instead of falling back (the legacy
        ``camera_info_file`` parameter, which always did).

    Raises
    ------
    FingerpsCalibError
        An invalid camera name or URL (at construction).
    """

    def __init__(self, *, camera_name: str, url: str, width: int, height: int,
                 fallback: CameraIntrinsics | None = None,
                 fallback_source: str = "none (K = 0)", strict: bool = False) -> None:
        self.camera_name = check_camera_name(camera_name)
        self.url = url
        self.path: Path = resolve_camera_info_url(url, camera_name)
        self.width, self.height = int(width), int(height)
        self._fallback = fallback
        self._fallback_source = fallback_source if fallback is not None else "none (K = 0)"
        self._strict = strict
        self._current = CameraCalibration(fallback, self._fallback_source)

    @property
    def current(self) -> CameraCalibration:
        """The calibration in force."""
        return self._current

    def load(self) -> CameraCalibration:
        """Read the URL's file; on a problem (not strict) fall back and say why."""
        try:
            if not self.path.exists():
                raise FingerpsCalibError(f"no camera calibration at {self.path}")
            intrinsics = load_camera_info(self.path)
            self._check_size(intrinsics, f"the camera calibration {self.path}")
        except FingerpsCalibError as exc:
            if self._strict:
                raise
            self._current = CameraCalibration(self._fallback, self._fallback_source, str(exc))
            return self._current
        problem = None
        if intrinsics.camera_name != self.camera_name:
            problem = (f"the camera calibration {self.path} names camera "
                       f"{intrinsics.camera_name!r}, not {self.camera_name!r}; it is used")
        self._current = CameraCalibration(intrinsics, str(self.path), problem)
        return self._current

    def store(self, intrinsics: CameraIntrinsics) -> CameraCalibration:
        """Validate ``intrinsics``, write them to the URL's file, then put them in force.

        Raises
        ------
        FingerpsCalibError
            A calibration of another size or an unknown distortion model, or the file
            cannot be written; nothing changes then.
        """
        self._check_size(intrinsics, "the calibration sent")
        wanted = DISTORTION_LENGTHS.get(intrinsics.distortion_model)
        if wanted is None:
            raise FingerpsCalibError(
                f"distortion model {intrinsics.distortion_model!r} is not one of "
                f"{sorted(DISTORTION_LENGTHS)}")
        named = dataclasses.replace(intrinsics, camera_name=self.camera_name)
        store_camera_info(self.path, named)
        self._current = CameraCalibration(named, str(self.path))
        return self._current

    def _check_size(self, intrinsics: CameraIntrinsics, what: str) -> None:
        if (intrinsics.width, intrinsics.height) != (self.width, self.height):
            raise FingerpsCalibError(
                f"{what} is for {intrinsics.width}x{intrinsics.height} images but the camera "
                f"delivers {self.width}x{self.height}")
