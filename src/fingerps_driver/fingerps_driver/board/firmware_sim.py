"""The LED board's real firmware, run by simavr on a pseudo-terminal.

``make firmware`` builds the firmware (``fingerps_board.elf``, ATmega328P) and its simavr
harness (``board_sim``, from ``firmware/sim/board_sim.c``) into ``build/firmware``. The
harness runs the firmware on a simulated chip at 16 MHz, its simulated time locked to the
wall clock, with the UART on a pty: the board emulator's interface (``--link PATH``, the
pty path printed), the firmware behind it. SIGINT/SIGTERM stop it (the link is removed),
SIGUSR1 resets the chip; ``--vcd FILE`` traces the LED, trigger and status pins and the
UART bytes (written when it stops).

``FirmwareSim`` runs it from Python (the tests); ``main`` is the console script
``board_firmware_sim``. The files are found in ``$FINGERPS_FIRMWARE_DIR`` or else in the
repository's ``build/firmware``.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Self

from fingerps_driver.board.board_emulator import DEFAULT_LINK_PATH
from fingerps_driver.errors import BoardEmulatorError, FirmwareNotBuiltError

FIRMWARE_DIR_ENV = "FINGERPS_FIRMWARE_DIR"
HARNESS = "board_sim"
FIRMWARE_ELF = "fingerps_board.elf"
FIRMWARE_NAME = "fingerps-avr-0.1"
"""What the firmware answers ``INFO`` (with its LED count, 7)."""

_REPOSITORY = Path(__file__).resolve().parents[4]  # src/fingerps_driver/fingerps_driver/board
_READY = "Ctrl-C to stop"  # the end of the harness's line with the pty path


@dataclass(frozen=True)
class FirmwareFiles:
    """The harness and the firmware it runs."""

    harness: Path
    firmware: Path


def firmware_dir() -> Path:
    """``$FINGERPS_FIRMWARE_DIR`` if set, else the repository's ``build/firmware``."""
    configured = os.environ.get(FIRMWARE_DIR_ENV)
    return Path(configured) if configured else _REPOSITORY / "build" / "firmware"


def find_firmware(directory: Path | None = None) -> FirmwareFiles:
    """The built harness and firmware in ``directory`` (default ``firmware_dir()``).

    Raises ``FirmwareNotBuiltError`` (saying to run ``make firmware``) if one is missing.
    """
    directory = firmware_dir() if directory is None else directory
    files = FirmwareFiles(directory / HARNESS, directory / FIRMWARE_ELF)
    for path in (files.harness, files.firmware):
        if not (path.is_file() and os.access(path, os.X_OK if path is files.harness
                                              else os.R_OK)):
            raise FirmwareNotBuiltError(
                f"{path} is not built: run 'make firmware' in the repository (or set "
                f"{FIRMWARE_DIR_ENV} to the directory holding {HARNESS} and {FIRMWARE_ELF})")
    return files


def harness_command(files: FirmwareFiles, *, link: str, vcd: str | None = None) -> list[str]:
    """The harness's command line: the firmware on a pty linked at ``link``."""
    return [str(files.harness), "--link", link, *(("--vcd", vcd) if vcd else ()),
            str(files.firmware)]


class FirmwareSim:
    """The firmware under simavr in a child process, its pty linked at ``link``.

    ``start`` returns once the link is there; ``stop`` (idempotent) stops the harness with
    SIGTERM, which removes the link and writes the ``vcd`` trace. A context manager.

    Parameters
    ----------
    link : str
        Symlink to the pty; ``port`` is this path.
    vcd : str or None
        Trace file of the pins and UART bytes (complete once stopped).
    files : FirmwareFiles or None
        Default: ``find_firmware()``.
    """

    def __init__(self, link: str, *, vcd: str | None = None,
                 files: FirmwareFiles | None = None) -> None:
        self._link = link
        self._vcd = vcd
        self._files = files
        self._process: subprocess.Popen[str] | None = None
        self.returncode: int | None = None
        """The harness's exit status once stopped (0: a clean stop)."""
        self.banner = ""
        """The harness's line naming the pty."""

    @property
    def port(self) -> str:
        return self._link

    @property
    def vcd(self) -> str | None:
        return self._vcd

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def start(self) -> None:
        """Start the harness; return when the pty is linked. Raises ``BoardEmulatorError``
        if it exits instead (its error output in the message)."""
        if self._process is not None:
            raise BoardEmulatorError("FirmwareSim already started; call stop() first")
        files = self._files if self._files is not None else find_firmware()
        process = subprocess.Popen(
            harness_command(files, link=self._link, vcd=self._vcd),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self._process = process
        assert process.stdout is not None
        for line in process.stdout:  # simavr's loader lines, then the harness's
            if line.rstrip().endswith(_READY):
                self.banner = line.strip()
                break
        else:
            process.wait()
            assert process.stderr is not None
            error = process.stderr.read().strip()
            self.stop()
            raise BoardEmulatorError(
                f"the firmware simulator exited ({self.returncode}) before serving: {error}")

    def reset(self) -> None:
        """Press the reset button (SIGUSR1): the chip restarts, LEDs off, settings lost.

        Returns once the harness has reset the chip (it says so on its error output), so
        every byte written to the port from then on reaches the restarted firmware (which
        takes some 0.1 ms to set its UART up: a client's resend covers that).
        """
        process = self._process
        if process is None or process.poll() is not None:
            raise BoardEmulatorError("FirmwareSim not running; call start() first")
        assert process.stderr is not None
        process.send_signal(signal.SIGUSR1)
        for line in process.stderr:
            if line.strip() == f"{HARNESS}: reset":
                return
        raise BoardEmulatorError(f"the firmware simulator exited ({process.wait()}) "
                                 "instead of resetting the chip")

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """SIGTERM and wait; return the exit status. Safe to call twice."""
        process, self._process = self._process, None
        if process is None:
            return self.returncode
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        for stream in (process.stdout, process.stderr):
            if stream is not None:
                stream.close()
        self.returncode = process.returncode
        return self.returncode

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    """Console script ``board_firmware_sim``: the firmware under simavr until SIGINT/SIGTERM.

    The harness replaces this process (exec), so the signals reach it directly.
    """
    parser = argparse.ArgumentParser(
        prog="board_firmware_sim",
        description="Run the fingerps LED board's firmware in simavr, its serial port on a "
                    "pseudo-terminal (SIGUSR1 resets the chip).")
    parser.add_argument("--link", default=DEFAULT_LINK_PATH,
                        help=f"symlink to the pty a client opens (default {DEFAULT_LINK_PATH})")
    parser.add_argument("--vcd", default=None, metavar="FILE",
                        help="trace the LED, trigger and status pins and the UART bytes")
    options = parser.parse_args(argv)
    try:
        files = find_firmware()
    except FirmwareNotBuiltError as exc:
        print(f"board_firmware_sim: {exc}", file=sys.stderr)
        return 1
    command = harness_command(files, link=options.link, vcd=options.vcd)
    sys.stdout.flush()
    os.execv(command[0], command)
    return 1  # not reached


if __name__ == "__main__":
    sys.exit(main())
