"""A PM QoS CPU latency request: idle CPUs stay in idle states they leave within a bound.

Why: a process woken on an idle CPU waits for that CPU to leave its idle state, and the
process that wakes it pays for the interrupt. On a machine whose idle CPUs sleep deeply, or
in a virtual machine whose idle vCPUs halt (a KVM guest's ``haltpoll`` driver), that costs
tens of microseconds on both sides of every wake-up, and a chain of worker hops pays two
per hop: on this project's 2-vCPU machine the new-frame pipe of 8 worker hops took 3.2 ms
end to end with the CPUs free to halt and 2.4 ms with the bound at 0 (benchmarks/RESULTS.md,
"Wake-ups"), dora-rs's the same way.

The kernel's PM QoS interface (Documentation/power/pm_qos_interface.rst): a process writes
its bound in microseconds, a 32-bit integer, to ``/dev/cpu_dma_latency``, and the request
holds while that file stays open; the cpuidle governor then chooses no state whose exit
latency is above the bound. The kernel drops the request when the file is closed, however
the process ends: nothing stays behind after a crash or a SIGKILL. ``cyclictest`` holds 0
this way for its whole run; tuned's ``latency-performance`` profile holds a bound too.

Cost: CPUs that may not sleep deeply draw more power, and at 0 an idle CPU polls (in a
virtual machine its vCPU keeps a host CPU busy). Machine-wide while held: every process of
the machine wakes faster, not only the runtime's.
"""

from __future__ import annotations

import os
import struct

DEVICE = "/dev/cpu_dma_latency"
MAX_US = 10_000  # above 10 ms every idle state of any machine is allowed: no request at all


class CpuLatencyRequest:
    """One request, held from :meth:`hold` to :meth:`release` (the file stays open)."""

    def __init__(self, seconds: float | None = None, device: str = DEVICE) -> None:
        """``seconds``: the bound asked for; None asks for none (``hold`` holds nothing)."""
        if seconds is not None and (
            isinstance(seconds, bool) or not isinstance(seconds, (int, float))
        ):
            raise TypeError(f"cpu_latency must be a number of seconds, got {seconds!r}")
        if seconds is not None and not 0 <= seconds <= MAX_US / 1e6:
            raise ValueError(f"cpu_latency must be between 0 and 0.01 s, got {seconds}")
        self.seconds = seconds
        self.device = device
        self._fd: int | None = None  # open while the request holds
        self.granted = ""  # what the table and the statistics say: held, or why not

    def hold(self) -> bool:
        """Ask that no CPU take longer than ``seconds`` to wake; False (and ``granted`` says
        why) when refused: never fatal, as ``--realtime`` is not. True when none is asked."""
        if self.seconds is None:
            return True
        us = round(self.seconds * 1e6)
        self.release()
        try:
            fd = os.open(self.device, os.O_WRONLY)
        except FileNotFoundError:
            self.granted = f"not held: {self.device} does not exist (no PM QoS here)"
            return False
        except PermissionError:
            self.granted = f"not held: {self.device} is not writable (needs root)"
            return False
        except OSError as e:
            self.granted = f"not held: {self.device}: {e.strerror}"
            return False
        try:
            os.write(fd, struct.pack("=i", us))
        except OSError as e:
            os.close(fd)
            self.granted = f"not held: {self.device} refused {us} us ({e.strerror})"
            return False
        self._fd = fd
        self.granted = f"held at {us} us"
        return True

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Close the file: the kernel drops the request."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def current_bound_us(device: str = DEVICE) -> int | None:
    """The bound in force now, every process's requests together (the file reads it), or
    None where it cannot be read."""
    try:
        with open(device, "rb") as f:
            data = f.read(4)
    except OSError:
        return None
    return struct.unpack("=i", data)[0] if len(data) == 4 else None
