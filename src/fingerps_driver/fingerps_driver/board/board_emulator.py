"""Emulator of the LED board on a real pseudo-terminal.

The emulator opens a pty pair (``os.openpty``), sets it raw and serves the protocol of
``fingerps_driver.board.board_protocol`` on the master side from one background thread; a
client opens the slave device (``port``) with pyserial exactly as it would open the real
board. Faults can be injected to test the client's recovery.

Remote control: ``board_emulator --control PATH`` also serves the emulator's control
channel (``emulator_control.EmulatorControlServer``; its client is
``emulator_control_client.BoardEmulatorControl``).

Port paths: every pty (at ``start()`` and at each ``reconnect()``) gets a new kernel
device ``/dev/pts/<n>``, usually with a different number. Give ``link_path=`` to have a
stable path: the emulator keeps a symlink there pointing at the current pty, removes it
on ``disconnect()``/``stop()`` (so the port vanishes for clients) and recreates it on
``reconnect()``. ``port`` is ``link_path`` if given, else the current device.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import os
import select
import signal
import sys
import threading
import time
import tty
from enum import Enum
from functools import partial

from fingerps_driver.board.board_protocol import (
    LED_COUNT,
    MAX_LEDS,
    MAX_LEVEL,
    REQUEST_SIGIL,
    Command,
    ErrorCode,
    Reply,
    Request,
    decode_request,
    encode_reply,
    format_mask,
    mask_to_indices,
)
from fingerps_driver.board.frame_reader import POLL_S, FrameReader
from fingerps_driver.board.served import Served
from fingerps_driver.errors import BoardEmulatorError, FingerpsDriverError, ProtocolError

DEFAULT_LINK_PATH = "/tmp/fingerps_board"
FIRMWARE = "fingerps-emu-1.0"


# Replies a fault queue may cover (faults plus the replies let through before them).
MAX_PENDING_FAULTS = 10_000


class Fault(Enum):
    """Faults ``BoardEmulator.inject`` can cause.

    DROP_REPLY, CORRUPT_BYTE and SLOW_REPLY each affect the next reply the board sends
    (the request itself is executed normally). DISCONNECT acts at once, or, injected with
    ``after=n``, when the board is about to send its (n+1)-th reply from now: the request
    has been executed, the reply is never sent and the board loses power then (a cable
    pulled in the middle of a burst, at an exactly known step).
    """

    DROP_REPLY = "drop_reply"  # the reply is lost
    CORRUPT_BYTE = "corrupt_byte"  # one bit of one payload byte of the reply flips
    DISCONNECT = "disconnect"  # the pty closes, like pulling the USB cable
    SLOW_REPLY = "slow_reply"  # the reply leaves ``slow_reply_s`` late


class BoardEmulator(Served):
    """The LED board, emulated on a pseudo-terminal served by a background thread.

    The lifecycle methods (start, stop, disconnect, reconnect, inject) are serialised by a
    lock (a deferred power cut runs one from a helper thread); the state properties
    (lit_mask, levels, history, pending_faults) are safe from any thread.

    Parameters
    ----------
    led_count : int
        Number of LEDs, 1..32.
    reply_delay_s : float
        Delay before every reply (a real board's processing time).
    slow_reply_s : float
        Extra delay of a reply hit by ``Fault.SLOW_REPLY``; the default lies between one
        and two default client timeouts, so one retry recovers.
    link_path : str or None
        Stable symlink to the current pty (see the module docstring). An existing
        symlink there is replaced; any other existing file is an error.
    firmware : str
        Firmware token reported by ``INFO``.
    history_limit : int
        Switches kept in ``history`` (the oldest are forgotten), so a long run stays bounded.
    with_trigger : bool
        False: an older board without the camera trigger, which answers ``TRIG`` with
        ``ERR,CMD``.
    """

    def __init__(
        self,
        led_count: int = LED_COUNT,
        *,
        reply_delay_s: float = 0.0,
        slow_reply_s: float = 0.075,
        link_path: str | None = None,
        firmware: str = FIRMWARE,
        history_limit: int = 10_000,
        with_trigger: bool = True,
    ) -> None:
        if not 1 <= led_count <= MAX_LEDS:
            raise ValueError(f"led_count {led_count} outside 1..{MAX_LEDS}")
        if reply_delay_s < 0 or slow_reply_s < 0:
            raise ValueError("reply_delay_s and slow_reply_s must be >= 0")
        if history_limit < 1:
            raise ValueError(f"history_limit must be >= 1, got {history_limit}")
        Reply(0, (firmware,))  # raises ValueError if the token is not valid on the wire
        self._led_count = led_count
        self._reply_delay_s = reply_delay_s
        self._slow_reply_s = slow_reply_s
        self._link_path = link_path
        self._firmware = firmware
        self._lock = threading.Lock()
        self._mask = 0
        self._levels = [MAX_LEVEL] * led_count
        self._trigger = (0, 0)
        self._commands = tuple(c for c in Command if with_trigger or c is not Command.TRIG)
        self._history: collections.deque[tuple[float, int]] = collections.deque(
            maxlen=history_limit
        )
        self._faults: collections.deque[Fault | None] = collections.deque()
        self._lifecycle = threading.Lock()
        self._power_cut: threading.Thread | None = None
        self._requests = 0
        self._started = False
        self._device: str | None = None
        self._fds: tuple[int, int, int, int] | None = None  # master, slave, wake_r, wake_w
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> None:
        """Create the pty and start serving. Raises if already started."""
        with self._lifecycle:
            if self._started:
                raise BoardEmulatorError("BoardEmulator already started; call stop() first")
            self._check_link_free()
            self._started = True
            self._connect()

    def stop(self) -> None:
        """Stop serving, close the pty and remove the symlink. Safe to call twice."""
        with self._lifecycle:
            self._disconnect()
            self._started = False
            cutter, self._power_cut = self._power_cut, None
        if cutter is not None and cutter is not threading.current_thread():
            cutter.join()

    def disconnect(self) -> None:
        """Close the pty now, as if the USB cable were pulled.

        The board loses power: all LEDs go off (recorded in ``history``), levels return
        to 255 and pending faults are forgotten. The symlink, if any, is removed.
        """
        with self._lifecycle:
            if not self._started:
                raise BoardEmulatorError("BoardEmulator not started; call start() first")
            self._lose_power()

    def reconnect(self) -> None:
        """Serve on a new pty (a new ``/dev/pts/<n>``; the symlink follows it)."""
        with self._lifecycle:
            if not self._started:
                raise BoardEmulatorError("BoardEmulator not started; call start() first")
            self._disconnect()
            self._connect()

    def _lose_power(self) -> None:
        """Disconnect and reset the board's state; the caller holds ``_lifecycle``."""
        self._disconnect()
        with self._lock:
            if self._mask:
                self._history.append((time.monotonic(), 0))
            self._mask = 0
            self._levels = [MAX_LEVEL] * self._led_count
            self._trigger = (0, 0)
            self._faults.clear()

    def _cut_power_later(self, served: threading.Event) -> None:
        """From the serving thread: disconnect from a helper thread (it cannot join itself).

        ``served`` is the stop event of the connection to cut; if that connection is gone
        by the time the helper runs (stopped or reconnected meanwhile), nothing happens.
        """
        def cut() -> None:
            with self._lifecycle:
                if self._started and self._fds is not None and self._stop is served:
                    self._lose_power()

        thread = threading.Thread(target=cut, name="board-emulator-power-cut")
        self._power_cut = thread
        thread.start()

    # -- state -----------------------------------------------------------------------

    @property
    def port(self) -> str:
        """Path a client opens: ``link_path`` if given, else the current pty device."""
        if self._link_path is not None:
            return self._link_path
        if self._device is None:
            raise BoardEmulatorError("BoardEmulator not started; call start() first")
        return self._device

    @property
    def device(self) -> str | None:
        """Current (or last) pty slave device, ``/dev/pts/<n>``; None before start."""
        return self._device

    @property
    def connected(self) -> bool:
        """True while a pty is being served."""
        return self._fds is not None

    @property
    def led_count(self) -> int:
        return self._led_count

    @property
    def lit_mask(self) -> int:
        """Mask of the LEDs physically lit right now."""
        with self._lock:
            return self._mask

    def lit_leds(self) -> tuple[int, ...]:
        """Indices of the LEDs physically lit right now, ascending."""
        return mask_to_indices(self.lit_mask)

    @property
    def levels(self) -> tuple[int, ...]:
        """Drive level 0..255 of every LED."""
        with self._lock:
            return tuple(self._levels)

    @property
    def trigger(self) -> tuple[int, int]:
        """(delay_us, width_us) of the camera trigger as the last ``TRIG`` set it; width 0:
        off (the power-up state). The emulator has no trigger output: this is the setting
        only."""
        with self._lock:
            return self._trigger

    @property
    def history(self) -> list[tuple[float, int]]:
        """(time.monotonic(), mask) of the last switches (each LEDS/OFF applied, power loss)."""
        with self._lock:
            return list(self._history)

    @property
    def request_count(self) -> int:
        """Number of request lines received (valid or not)."""
        with self._lock:
            return self._requests

    @property
    def pending_faults(self) -> list[str]:
        """Faults still to strike, in order (``"none"`` for a reply left alone)."""
        with self._lock:
            return [f.name if f is not None else "none" for f in self._faults]

    def inject(self, fault: Fault, count: int = 1, *, after: int = 0) -> None:
        """Make ``count`` replies suffer ``fault``, once ``after`` more replies have gone.

        Faults queue up behind those injected before. DISCONNECT with ``after=0``
        disconnects now (``count`` is then ignored); with ``after=n`` the board loses
        power instead of sending its (n+1)-th reply from now.
        """
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        if after < 0:
            raise ValueError(f"after must be >= 0, got {after}")
        if count + after > MAX_PENDING_FAULTS:
            raise ValueError(
                f"count + after must be <= {MAX_PENDING_FAULTS} (replies a test can wait "
                f"for), got {count} + {after}")
        if fault is Fault.DISCONNECT and after == 0:
            self.disconnect()
            return
        if fault is Fault.DISCONNECT:
            count = 1
        with self._lock:
            if len(self._faults) + count + after > MAX_PENDING_FAULTS:
                raise ValueError(
                    f"at most {MAX_PENDING_FAULTS} faults may be pending, "
                    f"{len(self._faults)} are; 'clear' them first")
            self._faults.extend([None] * after + [fault] * count)

    def clear_faults(self) -> None:
        """Forget every fault not yet struck."""
        with self._lock:
            self._faults.clear()

    # -- pty and thread ----------------------------------------------------------------

    def _check_link_free(self) -> None:
        path = self._link_path
        if path is not None and os.path.lexists(path) and not os.path.islink(path):
            raise BoardEmulatorError(
                f"{path} exists and is not a symlink; remove it or choose another link_path"
            )

    def _connect(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # the line discipline lives on the slave side
        os.set_blocking(master, False)  # a client that never reads must not block us
        wake_r, wake_w = os.pipe()
        self._device = os.ttyname(slave)
        self._fds = (master, slave, wake_r, wake_w)
        if self._link_path is not None:
            tmp = f"{self._link_path}.{os.getpid()}.tmp"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self._device, tmp)
            os.replace(tmp, self._link_path)
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._serve, args=(master, wake_r, self._stop), name="board-emulator"
        )
        self._thread.start()

    def _disconnect(self) -> None:
        if self._thread is not None:
            if self._thread is threading.current_thread():
                raise BoardEmulatorError("cannot disconnect from the emulator's own thread")
            self._stop.set()
            assert self._fds is not None
            with contextlib.suppress(OSError):
                os.write(self._fds[3], b"x")
            self._thread.join()
            self._thread = None
        if self._link_path is not None and os.path.islink(self._link_path):
            if os.readlink(self._link_path) == self._device:
                os.unlink(self._link_path)
        if self._fds is not None:
            for fd in self._fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._fds = None

    def _serve(self, master: int, wake_r: int, stop: threading.Event) -> None:
        reader = FrameReader(master, partial(os.read, master), REQUEST_SIGIL, wake_fd=wake_r)
        while not stop.is_set():
            try:
                for line in reader.lines(stop=stop):
                    if stop.is_set():
                        break  # power is being cut: nothing more is executed
                    reply = self._handle(line)
                    if reply is not None and not stop.is_set():
                        self._send(master, reply, stop)
            except OSError:  # EIO: no slave open; cannot happen while we hold one
                stop.wait(POLL_S)

    def _send(self, master: int, reply: bytes, stop: threading.Event) -> None:
        with self._lock:
            fault = self._faults.popleft() if self._faults else None
        if fault is Fault.DISCONNECT:
            stop.set()  # serve no more; the helper thread closes the pty
            self._cut_power_later(stop)
            return
        delay = self._reply_delay_s + (self._slow_reply_s if fault is Fault.SLOW_REPLY else 0)
        if delay and stop.wait(delay):
            return
        if fault is Fault.DROP_REPLY:
            return
        if fault is Fault.CORRUPT_BYTE:
            corrupt = bytearray(reply)
            corrupt[1 + (len(reply) - 5) // 2] ^= 0x01  # a payload byte, never sigil/newline
            reply = bytes(corrupt)
        view = memoryview(reply)
        while view and not stop.is_set():
            try:
                view = view[os.write(master, view) :]
            except BlockingIOError:
                select.select([], [master], [], POLL_S)
            except OSError:
                return

    def _handle(self, line: bytes) -> bytes | None:
        """Execute one request line; return the encoded reply, or None if unaddressable."""
        with self._lock:
            self._requests += 1
        try:
            request = decode_request(line, commands=self._commands)
        except ProtocolError as exc:
            if exc.seq is None:
                return None
            return encode_reply(Reply.failure(exc.seq, exc.code, str(exc)))
        return encode_reply(self._execute(request))

    def _execute(self, request: Request) -> Reply:
        seq, command, args = request.seq, request.command, request.args
        with self._lock:
            if command is Command.PING:
                return Reply(seq)
            if command is Command.INFO:
                return Reply(seq, (self._firmware, str(self._led_count)))
            if command is Command.STATE:
                levels = (str(level) for level in self._levels)
                return Reply(seq, (format_mask(self._mask), *levels))
            if command is Command.LEVEL:
                index, level = args
                if index >= self._led_count:
                    return Reply.failure(
                        seq, ErrorCode.OUT_OF_RANGE,
                        f"LED {index} does not exist (0..{self._led_count - 1})",
                    )
                self._levels[index] = level
                return Reply(seq)
            if command is Command.TRIG:
                self._trigger = (args[0], args[1])
                return Reply(seq)
            mask = args[0] if command is Command.LEDS else 0
            if mask >> self._led_count:
                return Reply.failure(
                    seq, ErrorCode.OUT_OF_RANGE,
                    f"mask {format_mask(mask)} names LEDs beyond {self._led_count - 1}",
                )
            self._mask = mask
            self._history.append((time.monotonic(), mask))
            return Reply(seq, (format_mask(mask),))


def main(argv: list[str] | None = None) -> int:
    """Console script ``board_emulator``: serve a board on a pty until SIGINT/SIGTERM."""
    parser = argparse.ArgumentParser(
        prog="board_emulator",
        description="Emulate the fingerps LED board on a pseudo-terminal.",
    )
    parser.add_argument("--link", default=DEFAULT_LINK_PATH,
                        help=f"symlink to the pty a client opens (default {DEFAULT_LINK_PATH})")
    parser.add_argument("--leds", type=int, default=7, help="number of LEDs (default 7)")
    parser.add_argument("--reply-delay", type=float, default=0.0, metavar="S",
                        help="delay before every reply in seconds (default 0)")
    parser.add_argument("--slow-reply", type=float, default=0.075, metavar="S",
                        help="extra delay of a reply hit by slow_reply (default 0.075)")
    parser.add_argument("--control", default=None, metavar="PATH",
                        help="serve the control channel on this UNIX socket: inject faults, "
                             "disconnect, read the lit LEDs (send 'help')")
    options = parser.parse_args(argv)
    from fingerps_driver.board.emulator_control import EmulatorControlServer  # needs this module


    stop = threading.Event()

    def _on_signal(signum: int, frame: object) -> None:
        stop.set()

    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        emulator = BoardEmulator(options.leds, reply_delay_s=options.reply_delay,
                                 slow_reply_s=options.slow_reply, link_path=options.link)
        with contextlib.ExitStack() as stack:
            stack.enter_context(emulator)
            control = ""
            if options.control:
                stack.enter_context(EmulatorControlServer(emulator, options.control))
                control = f", control {options.control}"
            print(f"board_emulator: {options.leds} LEDs on {emulator.device}, "
                  f"link {emulator.port}{control}; Ctrl-C to stop", flush=True)
            while not stop.wait(0.5):
                pass
    except (FingerpsDriverError, ValueError, OSError) as exc:
        print(f"board_emulator: {exc}", file=sys.stderr)
        return 1
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0


if __name__ == "__main__":
    # The module itself, not this __main__ copy: the control channel (emulator_control)
    # imports it, and its Fault and BoardEmulator must be the ones the command serves.
    from fingerps_driver.board import board_emulator

    sys.exit(board_emulator.main())
