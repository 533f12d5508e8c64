"""The far end of a serial device on a real pseudo-terminal (``os.openpty``): the driver under
test opens the pty's path exactly as it would open ``/dev/ttyUSB0``.

A :class:`PtyEmulator` runs a thread that reads what the driver writes, feeds it to the device
model (a subclass) and writes the replies back. :class:`Faults` are switches a test (or
``dotshell emulate --fault``) flips at any time: error replies, silence, garbage bytes, a move
that never finishes, a limit/alarm during the next move, and the port vanishing mid-move (and
coming back, like a re-plugged USB cable, under the same stable path).
"""

from __future__ import annotations

import os
import random
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable


#: Bytes the garbage fault never sends: line breaks (they would add reply lines) and XON/XOFF
#: (0x11/0x13), which freeze a driver that uses software flow control (pyserial's ``xonxoff``).
NOT_NOISE = (10, 13, 0x11, 0x13)


@dataclass
class Faults:
    """Fault switches (all off by default).

    Attributes:
        error: answer motion commands (and homing) with the device's error reply: True for
            every one, a number N for the next N only.
        silence: answer nothing at all (the driver's reply timeout fires).
        garbage: put noise bytes before every reply.
        stuck: moves start but never finish.
        alarm: a limit switch trips during the next move (the device's alarm/limit state).
        vanish_after_s: the port disappears this long after the next move starts.
        vanish_after_connect_s: the port disappears this long after the driver first writes to
            it (``dotshell emulate --vanish-after``: counted from connect, whatever moves).
        return_after_s: ...and comes back this long after vanishing (None = stays gone).
        extra: the emulator's own faults that are on (names its class lists in
            ``extra_faults``; its model checks ``"name" in self.faults.extra``).
    """

    error: bool | int = False
    silence: bool = False
    garbage: bool = False
    stuck: bool = False
    alarm: bool = False
    vanish_after_s: float | None = None
    vanish_after_connect_s: float | None = None
    return_after_s: float | None = None
    extra: set[str] = field(default_factory=set)

    NAMES = ("error", "silence", "garbage", "stuck", "alarm", "vanish")


class PtyEmulator:
    """Base of the device emulators.

    Args:
        link: a path to keep pointing at the current pty (a symlink, like
            ``/dev/serial/by-id/...``); profiles name it so a re-plugged device is found again.
        speed_deg_s: how fast simulated motion runs (degrees per second).
        seed: seed of the garbage bytes.

    Attributes:
        faults: the :class:`Faults` switches.
        received: ``(monotonic time, bytes)`` chunks as the driver wrote them.
        commands: ``(monotonic time, command)`` as the model parsed them.
        plugs: how many times the port appeared (1 after start, 2 after one re-plug).
    """

    name = "device"
    newline = b"\n"
    #: Faults this emulator defines beyond :attr:`Faults.NAMES` (``dotshell emulate --fault``).
    extra_faults: tuple[str, ...] = ()

    def __init__(self, link: str | os.PathLike | None = None, speed_deg_s: float = 360.0,
                 seed: int = 0) -> None:
        self.link = Path(link) if link else None
        self.speed_deg_s = float(speed_deg_s)
        self.faults = Faults()
        self.received: list[tuple[float, bytes]] = []
        self.commands: list[tuple[float, str]] = []
        self.plugs = 0
        self.errors: list[str] = []
        self.pty_path = ""
        self._rng = random.Random(seed)
        self._master = self._slave = -1
        self._thread: threading.Thread | None = None
        self._running = False
        self._lock = threading.RLock()
        self._vanish_at: float | None = None
        self._return_at: float | None = None
        # motion, in degrees
        self.angle = 0.0
        self._move: tuple[float, float, float] | None = None  # (start angle, target, t0)

    # ---- lifecycle ------------------------------------------------------------------------------

    @property
    def port(self) -> str:
        """What a profile names: the stable link if there is one, else the pty path."""
        return str(self.link) if self.link else self.pty_path

    def start(self) -> PtyEmulator:
        self._plug()
        self._running = True
        self._thread = threading.Thread(target=self._serve, name=f"emulator-{self.name}",
                                        daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(2.0)
        self._unplug()

    @classmethod
    def fault_names(cls) -> tuple[str, ...]:
        """Every fault ``set_fault`` takes: the switches of :class:`Faults` and the
        emulator's own ``extra_faults``."""
        return tuple(n for n in Faults.NAMES if n != "vanish") + tuple(cls.extra_faults)

    def set_fault(self, name: str) -> None:
        """Switch fault ``name`` on (a :class:`Faults` switch or one of ``extra_faults``);
        ValueError naming the choices otherwise."""
        if name in self.extra_faults:
            self.faults.extra.add(name)
        elif name in self.fault_names():
            setattr(self.faults, name, True)
        else:
            raise ValueError(f"the {self.name} emulator has no fault {name!r}; its faults: "
                             f"{', '.join(self.fault_names())}")

    def __enter__(self) -> PtyEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes pass as they are
        self._master, self._slave = master, slave
        self.pty_path = os.ttyname(slave)
        if self.link is not None:
            tmp = self.link.with_name(f".{self.link.name}.tmp")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(self.pty_path, tmp)
            os.replace(tmp, self.link)
        self.plugs += 1
        self.on_plug()

    def _unplug(self) -> None:
        with self._lock:
            for fd in (self._master, self._slave):
                if fd >= 0:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
            self._master = self._slave = -1
            if self.link is not None and self.link.is_symlink():
                self.link.unlink()

    def unplug(self, back_after_s: float | None = None) -> None:
        """Make the port vanish now (the driver's next read or write fails); with
        ``back_after_s`` it comes back (a new pty behind the same link) after that long."""
        self._unplug()
        self._return_at = None if back_after_s is None else time.monotonic() + back_after_s

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    # ---- serving --------------------------------------------------------------------------------

    def _serve(self) -> None:
        while self._running:
            now = time.monotonic()
            if self._master < 0:
                if self._return_at is not None and now >= self._return_at:
                    self._return_at = None
                    self._plug()
                time.sleep(0.01)
                continue
            try:
                ready, _, _ = select.select([self._master], [], [], 0.005)
                data = os.read(self._master, 4096) if ready else b""
            except OSError:
                data = b""
            try:
                if data:
                    if not self.received and self.faults.vanish_after_connect_s is not None:
                        self._vanish_at = time.monotonic() + self.faults.vanish_after_connect_s
                        self.faults.vanish_after_connect_s = None
                    self.received.append((time.monotonic(), data))
                    with self._lock:
                        self.feed(data)
                with self._lock:
                    self._advance(time.monotonic())
            except Exception as exc:  # a model bug must not kill the port; tests read errors
                self.errors.append(f"{type(exc).__name__}: {exc}")
            if self._vanish_at is not None and time.monotonic() >= self._vanish_at:
                self._vanish_at = None
                self.unplug(self.faults.return_after_s)

    def send(self, data: bytes) -> None:
        """Write a reply to the driver, through the fault switches."""
        if self.faults.silence or self._master < 0:
            return
        if self.faults.garbage:
            noise = [b for b in range(1, 255) if b not in NOT_NOISE]
            data = bytes(self._rng.choice(noise) for _ in range(7)) + data
        try:
            os.write(self._master, data)
        except OSError:
            pass

    def log_command(self, text: str) -> None:
        self.commands.append((time.monotonic(), text))

    def first_time(self, predicate: Callable[[str], bool]) -> float | None:
        """Monotonic time of the first parsed command matching ``predicate``."""
        return next((t for t, c in self.commands if predicate(c)), None)

    def first_byte_time(self, byte: bytes, after: float = 0.0) -> float | None:
        """Monotonic time the driver first wrote ``byte`` after ``after``."""
        return next((t for t, chunk in self.received if t >= after and byte in chunk), None)

    def refuse(self) -> bool:
        """True if this motion command gets the error reply (``faults.error``)."""
        e = self.faults.error
        if e is True:
            return True
        if isinstance(e, int) and e > 0:
            self.faults.error = e - 1
            return True
        return False

    # ---- motion ---------------------------------------------------------------------------------

    def begin_move(self, target_deg: float) -> None:
        """Start moving to ``target_deg`` (faults: stuck, alarm, vanish apply)."""
        self._move = (self.angle, float(target_deg), time.monotonic())
        if self.faults.vanish_after_s is not None:
            self._vanish_at = time.monotonic() + self.faults.vanish_after_s
            self.faults.vanish_after_s = None

    @property
    def moving(self) -> bool:
        return self._move is not None

    def halt(self) -> None:
        """Stop where the motion is now."""
        if self._move is not None:
            self._advance(time.monotonic())
            self._move = None

    def _advance(self, now: float) -> None:
        if self._move is None:
            return
        start, target, t0 = self._move
        if self.faults.stuck:
            self.angle = start + (0.001 if target >= start else -0.001)
            return
        span = target - start
        travelled = self.speed_deg_s * (now - t0)
        if self.faults.alarm and travelled >= abs(span) / 2:
            self.faults.alarm = False
            self.angle = start + span / 2
            self._move = None
            self.on_limit()
            return
        if travelled >= abs(span):
            self.angle = target
            self._move = None
            self.on_move_done()
        else:
            self.angle = start + travelled * (1 if span >= 0 else -1)

    # ---- the model (subclasses) ------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        """Bytes the driver wrote."""
        raise NotImplementedError

    def on_plug(self) -> None:
        """The port (re)appeared: reset the protocol state, keep the position."""

    def on_move_done(self) -> None:
        """A move reached its target."""

    def on_limit(self) -> None:
        """A limit switch tripped mid-move (``faults.alarm``)."""


class LineEmulator(PtyEmulator):
    """A device with a line protocol: :meth:`line` gets each command line."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._buf = b""

    def on_plug(self) -> None:
        self._buf = b""

    def feed(self, data: bytes) -> None:
        self._buf += data
        while True:
            cut = [i for i in (self._buf.find(b"\n"), self._buf.find(b"\r")) if i >= 0]
            if not cut:
                return
            i = min(cut)
            raw, self._buf = self._buf[:i], self._buf[i + 1:]
            text = raw.decode("ascii", errors="replace").strip()
            if text:
                self.log_command(text)
                self.line(text)

    def line(self, text: str) -> None:
        raise NotImplementedError

    def reply(self, text: str) -> None:
        self.send(text.encode("ascii") + b"\r\n")
