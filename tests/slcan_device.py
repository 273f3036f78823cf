"""A CAN-to-serial gateway that speaks the slcan (Lawicel) ASCII protocol, on a pseudo-terminal.

It plays the soccer robot's CAN-PC gateway for tests and benchmarks, with no hardware: the
host opens the pty's slave end as a serial port (``interface: slcan``), the device answers on
the master end, and its CAN side is a python-can ``virtual`` bus that test peers join.
Bytes are paced at the configured baud rate (10 bits per byte: start, 8 data, stop) in both
directions, so throughput and latency are those of a real 115200-baud link, not of a pipe.

``unplug()`` closes the device end (the host's reads fail, as when a USB adapter is pulled)
and removes the port's path; ``replug()`` opens a new pty behind the same path. The path is
a symlink, as udev gives a real adapter (``/dev/serial/by-id/...``).

Protocol subset: ``O``/``L``/``C`` open/listen/close, ``Sn`` bitrate, ``V``/``N`` version and
serial, ``F`` status flags, ``Z`` timestamps; ``tiiildd..``/``Tiiiiiiiildd..`` transmit,
answered ``z``/``Z``; received CAN frames sent to the host as ``t``/``T`` lines. Unknown
commands get the error bell (0x07).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from pathlib import Path

import can

_BITRATES = {
    0: 10_000,
    1: 20_000,
    2: 50_000,
    3: 100_000,
    4: 125_000,
    5: 250_000,
    6: 500_000,
    7: 800_000,
    8: 1_000_000,
}


class _Pacer:
    """Releases bytes no faster than the serial line carries them."""

    def __init__(self, baud: int) -> None:
        self.byte_s = 10.0 / baud
        self.free_at = 0.0

    def wait(self, nbytes: int) -> None:
        """Return when ``nbytes`` more have left the line. A UART's FIFO sends back to back,
        so a thread that woke a little late catches up; after an idle gap (> 5 ms) the line
        starts afresh."""
        now = time.perf_counter()
        if now - self.free_at > 0.005:
            self.free_at = now
        self.free_at += nbytes * self.byte_s
        delay = self.free_at - now
        if delay > 0:
            time.sleep(delay)


class SlcanDevice:
    """A slcan gateway on a pty; ``path`` is the serial port the host opens."""

    def __init__(self, path: str | Path, can_channel: str, baud: int = 115200) -> None:
        self.path = Path(path)
        self.can_channel = can_channel
        self.baud = baud
        self.is_open = False  # the host sent O (bus on)
        self.bitrate: int | None = None
        self.from_host: list[tuple[float, can.Message]] = []  # frames the host transmitted
        self.to_host = 0  # frames written to the host
        self.commands: list[str] = []
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._master = self._slave = -1
        self._bus: can.BusABC | None = None
        self._wlock = threading.Lock()
        self.replug()

    # --- plugging ----------------------------------------------------------------------------

    def replug(self) -> None:
        """Plug the adapter (back) in: a fresh pty behind ``path``."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tmp = self.path.with_suffix(".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(os.ttyname(self._slave))
        tmp.replace(self.path)
        self._bus = can.Bus(interface="virtual", channel=self.can_channel)
        self._stop = threading.Event()
        self._out_pacer = _Pacer(self.baud)
        self._threads = [
            threading.Thread(
                target=self._serve_host,
                args=(self._master, self._stop),
                name="slcan-device-rx",
                daemon=True,
            ),
            threading.Thread(
                target=self._serve_can,
                args=(self._master, self._bus, self._stop),
                name="slcan-device-tx",
                daemon=True,
            ),
        ]
        for t in self._threads:
            t.start()

    def unplug(self) -> None:
        """Pull the adapter: the device end closes and the port's path disappears."""
        self._stop.set()
        for t in self._threads:
            t.join(2.0)
        self._threads = []
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None
        self.is_open = False

    close = unplug

    # --- host -> device ----------------------------------------------------------------------

    def _serve_host(self, fd: int, stop: threading.Event) -> None:
        pacer = _Pacer(self.baud)
        line = bytearray()
        while not stop.is_set():
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
                if not ready:
                    continue
                chunk = os.read(fd, 64)
            except OSError:
                return
            for b in chunk:
                pacer.wait(1)  # the UART takes the bytes one by one at the baud rate
                if b == 0x0D:
                    self._command(line.decode(errors="replace"))
                    line.clear()
                else:
                    line.append(b)

    def _command(self, cmd: str) -> None:
        self.commands.append(cmd)
        if not cmd:
            self._reply("\r")
            return
        op = cmd[0]
        if op in "tT" and self.is_open:
            try:
                ext = op == "T"
                n = 8 if ext else 3
                ident = int(cmd[1 : 1 + n], 16)
                dlc = int(cmd[1 + n])
                data = bytes.fromhex(cmd[2 + n : 2 + n + 2 * dlc])
            except (ValueError, IndexError):
                self._reply("\a")
                return
            msg = can.Message(arbitration_id=ident, data=data, is_extended_id=ext)
            self.from_host.append((time.perf_counter(), msg))
            if self._bus is not None:
                self._bus.send(msg)
            self._reply("Z\r" if ext else "z\r")
        elif op in "OL":
            self.is_open = True
            self._reply("\r")
        elif op == "C":
            self.is_open = False
            self._reply("\r")
        elif op == "S" and cmd[1:].isdigit() and int(cmd[1:]) in _BITRATES:
            self.bitrate = _BITRATES[int(cmd[1:])]
            self._reply("\r")
        elif op == "V":
            self._reply("V1013\r")
        elif op == "N":
            self._reply("NFLRT\r")
        elif op == "F":
            self._reply("F00\r")
        elif op in "Zsm":
            self._reply("\r")
        else:
            self._reply("\a")

    # --- device -> host ----------------------------------------------------------------------

    def _reply(self, text: str) -> None:
        self._write(text.encode())

    def _write(self, data: bytes) -> None:
        with self._wlock:
            self._out_pacer.wait(len(data))
            fd = self._master
            if fd < 0:
                return
            with contextlib.suppress(OSError):
                os.write(fd, data)

    def _serve_can(self, fd: int, bus: can.BusABC, stop: threading.Event) -> None:
        while not stop.is_set():
            msg = bus.recv(0.05)
            if msg is None or not self.is_open or msg.is_error_frame:
                continue
            if msg.is_extended_id:
                line = f"T{msg.arbitration_id:08X}{msg.dlc}{bytes(msg.data).hex().upper()}\r"
            else:
                line = f"t{msg.arbitration_id:03X}{msg.dlc}{bytes(msg.data).hex().upper()}\r"
            self._write(line.encode())
            self.to_host += 1


def line_bytes(dlc: int, extended: bool = False) -> int:
    """Bytes of one slcan frame line: type, id, dlc, 2 hex digits per byte, CR."""
    return 1 + (8 if extended else 3) + 1 + 2 * dlc + 1


def max_frames_per_s(baud: int, dlc: int, extended: bool = False) -> float:
    """The serial line's ceiling for frames of this size (10 bits per byte)."""
    return baud / 10.0 / line_bytes(dlc, extended)
