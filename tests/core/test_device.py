"""Device: the open/close/with lifecycle the cameras and the LED board share."""

from __future__ import annotations

import pytest

from fingerps_driver.board.led_board import LedBoard
from fingerps_driver.cameras.camera import Camera, SimulatedCamera
from fingerps_driver.device import Device


class _Counted(Device):
    def __init__(self) -> None:
        self.acquired = self.released = 0
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def _acquire(self) -> None:
        self.acquired += 1
        self._open = True

    def _release(self) -> None:
        self.released += 1
        self._open = False


def test_open_twice_acquires_once_and_close_is_safe_twice():
    device = _Counted()
    device.open()
    device.open()
    assert device.is_open and device.acquired == 1
    device.close()
    device.close()
    assert not device.is_open


def test_with_opens_and_closes_also_after_an_error():
    device = _Counted()
    with pytest.raises(RuntimeError), device as entered:
        assert entered is device and device.is_open
        raise RuntimeError("mid-burst")
    assert not device.is_open and device.released == 1


def test_cameras_and_the_board_are_devices():
    assert issubclass(Camera, Device) and issubclass(LedBoard, Device)
    assert isinstance(SimulatedCamera(lambda lit: None, list, width=2, height=2), Device)
