"""Stops that must reach a moving stage, on the shipped Zaber emulator (a real pty): a `dotshell
scan` process is signalled while the stage homes at connect, while a move hangs, and while a
refused move is retried. Used by tests/test_stop_unconditional.py (which asserts) and
benchmarks/devices.py (which prints the latencies)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
#: How long a signalled scan may take to end (seconds): the handles' STOP_WAIT_S per device
#: still inside a call, saving the frames, and a loaded 2-core host's slack. Without the
#: unconditional stop a homing or hung move runs to its limit (home 300 s, move_to 120 s).
EXIT_BOUND_S = 30.0


@dataclass
class StopCase:
    """What one signalled scan did.

    Attributes:
        stop_s: from the signal to the emulator receiving ``stop`` (seconds), None if never.
        exit_s: from the signal to the process's end (seconds), None if it outlived the bound.
        exit_code: the process's exit code (None if it was killed at the bound).
        stderr: what it printed on stderr.
        commands: the emulator's parsed commands (monotonic time, text), relative to the signal.
    """

    stop_s: float | None
    exit_s: float | None
    exit_code: int | None
    stderr: str
    commands: list[tuple[float, str]]


def zaber_profile(tmp: Path, port: str, home: str, views: int = 2) -> Path:
    """profiles/emu-zaber-metal-cylinder.toml at 1/8 scale on ``port``."""
    import tomli_w
    from dotshell_sim.bench import scale_profile

    raw = tomllib.loads((ROOT / "profiles" / "emu-zaber-metal-cylinder.toml").read_text())
    raw = scale_profile(raw, 0.125)
    raw["camera"]["settings"]["supersample"] = 1
    raw["stage"]["settings"]["port"] = port
    raw["stage"]["home"] = home
    raw["scan"]["views"] = views
    raw["outputs"] = {"previews": False}
    path = tmp / "emu-zaber.toml"
    path.write_text(tomli_w.dumps(raw))
    return path


def wait_for(predicate: Callable[[], bool], timeout: float) -> bool:
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout:
            return False
        time.sleep(0.005)
    return True


def moves(emu: Any) -> int:
    return sum(" move abs " in c for _, c in emu.commands)


#: case → (home policy, how the emulator is set up, when the stage is ready for the signal)
CASES: dict[str, tuple[str, Callable[[Any], None], Callable[[Any], bool]]] = {
    "homing": ("on_connect", lambda e: setattr(e, "angle", 90.0),
               lambda e: e.moving and e.angle < 89.0),
    "hung move": ("never", lambda e: setattr(e.faults, "stuck", True),
                  lambda e: e.moving and moves(e) >= 1),
    "retry": ("never", lambda e: (setattr(e, "angle", 90.0), setattr(e.faults, "error", 1)),
              lambda e: e.moving and moves(e) >= 2 and e.angle < 89.0),
}


def signal_scan(tmp: Path, emu: Any, case: str, signum: int, command: str = "scan"
                ) -> StopCase:
    """Start `dotshell scan` (or `dotshell check --connect`) on ``emu`` (a started Zaber
    emulator, 10°/s), send ``signum`` once ``case`` is under way, and measure the stop and the
    exit."""
    home, setup, ready = CASES[case]
    setup(emu)
    prof = zaber_profile(tmp, emu.port, home)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    args = (["scan", str(prof), "--out", str(tmp / "runs")] if command == "scan" else
            ["check", str(prof), "--connect"])
    proc = subprocess.Popen([sys.executable, "-m", "dotshell.cli.app", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    t_sig, exit_s, err = signal_when(proc, lambda: ready(emu), signum, case)
    stop = next((t for t, c in emu.commands if t >= t_sig and c.split()[-1] == "stop"), None)
    return StopCase(None if stop is None else stop - t_sig, exit_s,
                    proc.returncode if exit_s is not None else None, err,
                    [(t - t_sig, c) for t, c in emu.commands])


def signal_when(proc: subprocess.Popen, ready: Callable[[], bool], signum: int, what: str
                ) -> tuple[float, float | None, str]:
    """Send ``signum`` to ``proc`` once ``ready()``; (signal time, seconds until the process
    ended or None if it outlived EXIT_BOUND_S (it is then killed), its stderr)."""
    try:
        if not wait_for(lambda: ready() or proc.poll() is not None, 120.0):
            raise AssertionError(f"{what}: never under way")
        if proc.poll() is not None:
            raise AssertionError(f"{what}: the process ended early: {proc.communicate()[1]}")
        t_sig = time.monotonic()
        proc.send_signal(signum)
        try:
            _, err = proc.communicate(timeout=EXIT_BOUND_S)
            return t_sig, time.monotonic() - t_sig, err
        except subprocess.TimeoutExpired:
            proc.kill()
            return t_sig, None, proc.communicate()[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


SIGNALS = {"SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM, "SIGHUP": signal.SIGHUP}


HUNG_PLUGIN = '''
import threading
from pathlib import Path

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.settings import Setting


class HungStage:
    """A stage whose move_to never returns, whatever it is told (a driver hung in C)."""

    position = 0.0

    def __init__(self, settings, context=None):
        self.marker = Path(settings["marker"])

    connect = close = stop = lambda self: None
    status = lambda self: {}  # noqa: E731

    def move_to(self, degrees):
        self.marker.write_text("inside move_to")
        threading.Event().wait()


@hookimpl
def dotshell_stages():
    return [Backend("hung-stage", HungStage, {"marker": Setting("str", "", "marker file")})]
'''


def hung_driver_scan(tmp: Path, signum: int) -> tuple[float | None, int | None, str]:
    """`dotshell scan` whose stage driver hangs in move_to (a plugin installed for the child
    only), signalled once it is inside: (seconds until the process ended or None past
    EXIT_BOUND_S, exit code, stderr)."""
    import tomli_w

    site = tmp / "site"
    info = site / "dotshell_hung-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: dotshell-hung\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[dotshell]\nhung = dotshell_hung\n")
    (site / "dotshell_hung.py").write_text(HUNG_PLUGIN)
    marker = tmp / "inside"
    prof = zaber_profile(tmp, "unused", "never")
    raw = tomllib.loads(prof.read_text())
    raw["stage"] = {"backend": "hung-stage", "settings": {"marker": str(marker)}}
    prof.write_text(tomli_w.dumps(raw))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(site), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.Popen([sys.executable, "-m", "dotshell.cli.app", "scan", str(prof), "--out",
                             str(tmp / "runs")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=env)
    _, exit_s, err = signal_when(proc, marker.exists, signum, "the hung driver")
    return exit_s, proc.returncode if exit_s is not None else None, err
