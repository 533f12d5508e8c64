"""Device benchmarks (``make bench``): what the rig's device handles cost, and how fast a stop
reaches a moving stage.

1. Call overhead: a no-op driver method called through a :class:`~dotshell.rig.handles.DeviceHandle`
   (lock, worker thread, timeout) against the same method called directly (the peer), in the
   same run.
2. Stop latency per serial stage/analyzer backend on its emulator (a real pty): from
   ``Rig.stop()`` — here the handle's ``stop_now()``, from another thread and from a SIGALRM
   handler while the main thread waits in ``move_to`` — to the emulator receiving the stop
   command, and to the moving call returning.
3. Stop latency of a signalled `dotshell scan` per case (tests/stop_cases.py: the Zaber stage
   homing at connect, a hung move, a refused move being retried; SIGINT and SIGTERM): from the
   signal to the emulator receiving ``stop``, and to the process's end; and SIGTERM to a scan
   whose stage driver hangs in ``move_to`` whatever it is told.

Prints the figures and writes them to ``bench-results/devices.json``. Nothing here asserts a
speed.
"""

from __future__ import annotations

import json
import signal
import statistics
import tempfile
import threading
import time
from pathlib import Path

from dotshell.backends import RigContext
from dotshell.errors import DeviceError
from dotshell.rig.handles import DeviceHandle, DevicePolicy
from dotshell.plugins import PluginManager

ROOT = Path(__file__).resolve().parents[1]
#: emulator, role, backend, the byte sequence of its stop command, the move method
BACKENDS = [("grbl", "stage", "grbl", b"!", "move_to"),
            ("zaber", "stage", "zaber", b"stop", "move_to"),
            ("apt", "stage", "thorlabs-apt", bytes.fromhex("6504"), "move_to"),
            ("elliptec", "analyzer", "elliptec", b"0st", "set_angle")]


class Noop:
    def connect(self) -> None: ...
    def close(self) -> None: ...
    def status(self) -> dict:
        return {}

    def ping(self) -> int:
        return 1


def call_overhead(n: int = 5000) -> dict[str, float]:
    dev = Noop()
    h = DeviceHandle("camera", "noop", "bench", "bench", dev, RigContext(), DevicePolicy())
    h.ping()  # start the worker
    t0 = time.perf_counter()
    for _ in range(n):
        dev.ping()
    direct = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    for _ in range(n):
        h.ping()
    handled = (time.perf_counter() - t0) / n
    h.shutdown()
    return {"direct_us": direct * 1e6, "handle_us": handled * 1e6,
            "ratio": handled / direct}


def stop_latency(pm: PluginManager, name: str, role: str, backend: str, marker: bytes,
                 method: str, repeats: int, via_signal: bool) -> dict[str, float]:
    from dotshell.plugins import emulator_class

    hold, back = [], []
    with tempfile.TemporaryDirectory() as tmp:
        emu = emulator_class(name)(link=Path(tmp) / "tty", speed_deg_s=60.0).start()
        ctx = RigContext().for_device(role, backend)
        dev = pm.create(role, backend, {"port": emu.port}, ctx)
        h = DeviceHandle(role, backend, "serial", "dotshell", dev, ctx, DevicePolicy())
        h.connect()
        for i in range(repeats):
            target = (float(h.position) + 100.0) % 300.0  # a 0.5..1.7 s move at 60°/s
            target = target if abs(target - float(h.position)) > 30.0 else target + 60.0
            t_stop: list[float] = []

            def fire(*_: object) -> None:
                t_stop.append(time.monotonic())
                h.stop_now()

            if via_signal:
                old = signal.signal(signal.SIGALRM, fire)
                signal.setitimer(signal.ITIMER_REAL, 0.3)
            else:
                threading.Timer(0.3, fire).start()
            try:
                getattr(h, method)(target)
            except DeviceError:
                pass
            ended = time.monotonic()
            if via_signal:
                signal.signal(signal.SIGALRM, old)
            got = next((t for t, chunk in emu.received if t >= t_stop[0] and marker in chunk),
                       None)
            if got is not None:
                hold.append(got - t_stop[0])
            back.append(ended - t_stop[0])
        h.shutdown()
        emu.close()
    return {"stop_command_ms_median": 1e3 * statistics.median(hold),
            "stop_command_ms_max": 1e3 * max(hold), "call_returned_ms_median":
            1e3 * statistics.median(back), "call_returned_ms_max": 1e3 * max(back),
            "received": len(hold), "repeats": repeats}


def signalled_scans() -> dict[str, dict[str, float | None]]:
    """Section 3: each case of tests/stop_cases.py under SIGINT and SIGTERM, printed."""
    import sys

    sys.path.insert(0, str(ROOT / "tests"))
    from stop_cases import CASES, SIGNALS, signal_scan

    from dotshell.plugins import emulator_class

    out: dict[str, dict[str, float | None]] = {}
    for case in CASES:
        for signame in ("SIGINT", "SIGTERM"):
            with tempfile.TemporaryDirectory() as tmp:
                emu = emulator_class("zaber")(link=Path(tmp) / "tty", speed_deg_s=10.0).start()
                try:
                    r = signal_scan(Path(tmp), emu, case, SIGNALS[signame])
                finally:
                    emu.close()
            out[f"{case} {signame}"] = {"stop_ms": None if r.stop_s is None else 1e3 * r.stop_s,
                                        "exit_s": r.exit_s, "exit_code": r.exit_code}
            stop = "never" if r.stop_s is None else f"{1e3 * r.stop_s:.1f} ms"
            ended = "not within the bound" if r.exit_s is None else f"{r.exit_s:.2f} s"
            print(f"scan signalled ({case:9s}, {signame:7s}): stop at the stage after {stop}, "
                  f"process ended after {ended} (exit {r.exit_code})")
    from stop_cases import hung_driver_scan

    with tempfile.TemporaryDirectory() as tmp:
        exit_s, code, _ = hung_driver_scan(Path(tmp), SIGNALS["SIGTERM"])
    out["hung driver SIGTERM"] = {"stop_ms": None, "exit_s": exit_s, "exit_code": code}
    ended = "not within the bound" if exit_s is None else f"{exit_s:.2f} s"
    print(f"scan signalled (driver hung in move_to, SIGTERM): process ended after {ended} "
          f"(exit {code}; the bound: STOP_WAIT_S = 2 s per hung device + saving frames)")
    return out


def main() -> None:
    pm = PluginManager()
    pm.load_entry_points()
    out: dict[str, object] = {"call_overhead": call_overhead()}
    c = out["call_overhead"]
    print(f"device call: direct {c['direct_us']:.2f} µs, through the rig's handle "
          f"{c['handle_us']:.1f} µs ({c['ratio']:.0f}x; a capture takes milliseconds)")
    for name, role, backend, marker, method in BACKENDS:
        for via in ("thread", "signal"):
            r = stop_latency(pm, name, role, backend, marker, method, 6, via == "signal")
            out[f"stop_{backend}_{via}"] = r
            print(f"stop {backend:13s} from a {via:6s}: command at the device after "
                  f"{r['stop_command_ms_median']:.1f} ms (max {r['stop_command_ms_max']:.1f}), "
                  f"move returned after {r['call_returned_ms_median']:.0f} ms (max "
                  f"{r['call_returned_ms_max']:.0f}), {r['received']}/{r['repeats']} seen")
    out["signalled_scans"] = signalled_scans()
    dest = ROOT / "bench-results" / "devices.json"
    dest.parent.mkdir(exist_ok=True)
    dest.write_text(json.dumps(out, indent=2))
    print(f"figures: {dest}")


if __name__ == "__main__":
    main()
