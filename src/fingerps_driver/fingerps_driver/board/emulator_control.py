"""The control channel of a ``BoardEmulator`` (``board_emulator --control PATH``): a small line
protocol on a UNIX socket by which another process (a test, a simulated camera) injects
faults, cuts the power and reads what the board has physically lit. The serial port stays
the only way to switch LEDs. Its client is ``emulator_control_client.BoardEmulatorControl``.
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import socket
import stat
import threading
from typing import Any

from fingerps_driver.board.board_emulator import BoardEmulator, Fault
from fingerps_driver.board.served import Served
from fingerps_driver.errors import BoardEmulatorError

CONTROL_COMMANDS = {
    "ping": "answer true",
    "lit": "mask of the LEDs lit now (int)",
    "state": "mask, lit LEDs, levels, trigger, connected, device, port, requests, "
             "pending faults",
    "history [N]": "the last N (default all) switches as [[time.monotonic(), mask], ...]",
    "inject FAULT [COUNT] [after N]": "FAULT: drop_reply, corrupt_byte, slow_reply, disconnect",
    "clear": "forget the faults not yet struck",
    "disconnect": "pull the cable now",
    "reconnect": "plug it back in (a new pty behind the link)",
    "help": "the commands",
}
"""Commands of the control channel (one a line) and what they answer."""

_MAX_CONTROL_LINE = 1024


class EmulatorControlServer(Served):
    """Serves the control channel of a ``BoardEmulator`` on a UNIX stream socket.

    Line protocol: the client sends one command a line (``CONTROL_COMMANDS``, words
    separated by blanks, case-insensitive); the server answers each with one JSON line,
    ``{"ok": true, "result": ...}`` or ``{"ok": false, "error": "..."}``. Several clients
    may stay connected; one thread serves them all, so the emulator's lifecycle methods
    are only ever called from that thread. Try it by hand with
    ``socat - UNIX-CONNECT:PATH``.

    Parameters
    ----------
    emulator : BoardEmulator
        The started emulator to control.
    path : str
        Socket path. A stale socket there is replaced; any other existing file is an error.
    """

    def __init__(self, emulator: BoardEmulator, path: str) -> None:
        self._emulator = emulator
        self._path = path
        self._listener: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._wake: tuple[int, int] | None = None

    @property
    def path(self) -> str:
        return self._path

    def start(self) -> None:
        """Bind the socket and start serving. Raises ``BoardEmulatorError`` if it cannot."""
        if self._thread is not None:
            raise BoardEmulatorError("control server already started")
        if os.path.lexists(self._path):
            if not stat.S_ISSOCK(os.lstat(self._path).st_mode):
                raise BoardEmulatorError(
                    f"{self._path} exists and is not a socket; remove it or choose another "
                    "control path")
            os.unlink(self._path)
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            listener.bind(self._path)
            listener.listen(8)
        except OSError as exc:
            listener.close()
            raise BoardEmulatorError(f"cannot serve the control socket {self._path}: {exc}") \
                from exc
        listener.setblocking(False)
        self._listener = listener
        self._wake = os.pipe()
        self._thread = threading.Thread(target=self._serve, name="board-emulator-control")
        self._thread.start()

    def stop(self) -> None:
        """Stop serving, close every connection and remove the socket. Safe to call twice."""
        if self._thread is not None:
            assert self._wake is not None
            os.write(self._wake[1], b"x")
            self._thread.join()
            self._thread = None
        if self._wake is not None:
            for fd in self._wake:
                os.close(fd)
            self._wake = None
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._path)

    def _serve(self) -> None:
        assert self._listener is not None and self._wake is not None
        buffers: dict[socket.socket, bytearray] = {}
        with selectors.DefaultSelector() as selector:
            selector.register(self._listener, selectors.EVENT_READ)
            selector.register(self._wake[0], selectors.EVENT_READ)
            try:
                while True:
                    for key, _ in selector.select():
                        if key.fileobj == self._wake[0]:
                            return
                        if key.fileobj is self._listener:
                            with contextlib.suppress(BlockingIOError):
                                conn, _ = self._listener.accept()
                                conn.setblocking(True)
                                conn.settimeout(1.0)  # a client that never reads is dropped
                                buffers[conn] = bytearray()
                                selector.register(conn, selectors.EVENT_READ)
                            continue
                        conn = key.fileobj
                        assert isinstance(conn, socket.socket)
                        if not self._serve_client(conn, buffers[conn]):
                            selector.unregister(conn)
                            del buffers[conn]
                            conn.close()
            finally:
                for conn in buffers:
                    conn.close()

    def _serve_client(self, conn: socket.socket, buffer: bytearray) -> bool:
        """Read what the client sent, answer complete lines; False when it is gone."""
        try:
            data = conn.recv(4096)
        except OSError:
            return False
        if not data:
            return False
        buffer.extend(data)
        while b"\n" in buffer:
            line, _, rest = bytes(buffer).partition(b"\n")
            buffer[:] = rest
            answer = self.execute(line.decode("utf-8", errors="replace"))
            try:
                conn.sendall(json.dumps(answer).encode("ascii") + b"\n")
            except OSError:
                return False
        return len(buffer) <= _MAX_CONTROL_LINE

    def execute(self, line: str) -> dict[str, Any]:
        """Run one command line; return the answer object (never raises)."""
        words = line.strip().lower().split()
        if not words:
            return {"ok": False, "error": "empty command; send 'help'"}
        try:
            return {"ok": True, "result": self._run(words[0], words[1:])}
        except (BoardEmulatorError, ValueError, OSError) as exc:
            return {"ok": False, "error": str(exc)}
        except Exception as exc:  # the control thread must survive any command
            return {"ok": False, "error": f"{' '.join(words)!r} failed: "
                                          f"{type(exc).__name__}: {exc}"}

    def _run(self, command: str, args: list[str]) -> object:
        emu = self._emulator
        if command == "ping" and not args:
            return True
        if command == "lit" and not args:
            return emu.lit_mask
        if command == "state" and not args:
            return {"mask": emu.lit_mask, "lit": list(emu.lit_leds()),
                    "levels": list(emu.levels), "trigger": list(emu.trigger),
                    "connected": emu.connected,
                    "device": emu.device, "port": emu.port, "requests": emu.request_count,
                    "pending_faults": emu.pending_faults}
        if command == "history" and len(args) <= 1:
            history = emu.history
            if args:
                history = history[-int(args[0]):] if int(args[0]) > 0 else []
            return [[t, mask] for t, mask in history]
        if command == "inject" and 1 <= len(args) <= 4:
            return self._inject(args)
        if command == "clear" and not args:
            emu.clear_faults()
            return True
        if command == "disconnect" and not args:
            emu.disconnect()
            return True
        if command == "reconnect" and not args:
            emu.reconnect()
            return True
        if command == "help" and not args:
            return CONTROL_COMMANDS
        raise ValueError(f"unknown command {' '.join([command, *args])!r}; send 'help'")

    def _inject(self, args: list[str]) -> list[str]:
        names = {f.value: f for f in Fault}
        if args[0] not in names:
            raise ValueError(f"unknown fault {args[0]!r}; one of {', '.join(names)}")
        rest = args[1:]
        after = 0
        if len(rest) >= 2 and rest[-2] == "after":
            after = int(rest[-1])
            rest = rest[:-2]
        if len(rest) > 1:
            raise ValueError("usage: inject FAULT [COUNT] [after N]")
        self._emulator.inject(names[args[0]], int(rest[0]) if rest else 1, after=after)
        return self._emulator.pending_faults


