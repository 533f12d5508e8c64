"""An idle TUI attached to a rig server after a full-resolution scan: its resident memory and CPU,
next to a bare Textual app (the peer) measured the same way in the same run.

``dotshell tui`` runs on a pseudo-terminal (120×40) with private runtime/state directories; it
starts its server, the scan is started from the TUI's keys (2, s) on the reference bench
(``--quick``: scaled down), and once the run has completed and the TUI has drawn it, the TUI is
left idle: its RSS (``VmRSS``) and peak RSS (``VmHWM``) are read from /proc, and its CPU time
over an idle window. Usage: ``python benchmarks/bench_tui.py [--quick]`` (also run by
``run.py``).
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import pty
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import termios
import threading
import time
from pathlib import Path
from typing import Any

import tomli_w

from bench_profile import ROOT, load_bench_profile
from dotshell.plugins import get_plugin_manager

#: Views of the benchmark scan (the issue's case: a 4-view full-resolution scan).
VIEWS = 4
IDLE_S = 10.0
COLS, ROWS = 120, 40
PEER = """
from textual.app import App
from textual.widgets import Footer, Header, Static
class Peer(App):
    def compose(self):
        yield Header()
        yield Static("a bare Textual app: header, text, footer")
        yield Footer()
Peer().run()
"""


class PtyProcess:
    """A process on a pseudo-terminal whose output is read (and dropped) as it comes."""

    def __init__(self, argv: list[str], env: dict[str, str], cwd: Path) -> None:
        master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", ROWS, COLS, 0, 0))
        self.proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, env=env,
                                     cwd=cwd, start_new_session=True)
        os.close(slave)
        self.master = master
        self.output = bytearray()
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        while True:
            try:
                data = os.read(self.master, 65536)
            except OSError:
                return
            if not data:
                return
            self.output += data
            del self.output[:-200000]

    def send(self, keys: str) -> None:
        os.write(self.master, keys.encode())

    def wait_for(self, needle: bytes, timeout_s: float = 120.0) -> None:
        t0 = time.monotonic()
        while needle not in self.output:
            if self.proc.poll() is not None or time.monotonic() - t0 > timeout_s:
                raise RuntimeError(f"{needle!r} never shown; output ends with "
                                   f"{bytes(self.output[-500:])!r}")
            time.sleep(0.1)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGHUP)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        os.close(self.master)


def proc_status(pid: int) -> dict[str, float]:
    """VmRSS and VmHWM (MiB) and CPU seconds (user + system) of a process, from /proc."""
    out: dict[str, float] = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024.0
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    out["cpu_s"] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def idle_figures(pid: int, idle_s: float) -> dict[str, float]:
    """Memory now and the CPU share over ``idle_s`` seconds of doing nothing."""
    before, t0 = proc_status(pid), time.monotonic()
    time.sleep(idle_s)
    after, wall = proc_status(pid), time.monotonic() - t0
    return {"rss_mib": after["VmRSS"], "peak_rss_mib": after["VmHWM"],
            "idle_cpu_pct": 100.0 * (after["cpu_s"] - before["cpu_s"]) / wall}


def write_profile(quick: bool, path: Path) -> Path:
    profile = load_bench_profile(get_plugin_manager(), quick)
    raw = profile.raw()
    raw["scan"]["views"] = 2 if quick else VIEWS
    path.write_text(tomli_w.dumps(raw))
    return path


def run_tui_bench(quick: bool) -> dict[str, Any]:
    """The figures: the TUI's and the peer's memory and idle CPU, the server's memory, the scan."""
    from dotshell.server.client import RemoteSession
    from dotshell.runtime.paths import server_name, socket_path

    work = Path(tempfile.mkdtemp(prefix="ds-bench-", dir="/tmp"))
    env = {**os.environ, "TERM": "xterm-256color", "COLORTERM": "truecolor"}
    for var, sub in (("XDG_RUNTIME_DIR", "run"), ("XDG_STATE_HOME", "state"),
                     ("XDG_CONFIG_HOME", "config")):
        (work / sub).mkdir(mode=0o700)
        env[var] = os.environ[var] = str(work / sub)
    profile = write_profile(quick, work / "bench.toml")
    tui = PtyProcess([sys.executable, "-m", "dotshell.cli.app", "tui", str(profile), "--out",
                      str(work / "runs")], env, work)
    try:
        tui.wait_for(b"sim-turntable")
        sock = socket_path(server_name(profile))
        watcher = RemoteSession(sock, "bench")
        t0 = time.monotonic()
        tui.send("2")
        time.sleep(1.0)
        tui.send("s")
        while watcher.refresh()["tracker"]["status"] in ("idle", "running", "paused"):
            if time.monotonic() - t0 > 3600:
                raise RuntimeError("the benchmark scan did not end within an hour")
            time.sleep(0.5)
        scan_s = time.monotonic() - t0
        tracker = watcher.refresh()["tracker"]
        server_pid = watcher.state["server"]["pid"]
        tui.wait_for(b"completed")
        time.sleep(3.0)  # the last previews drawn
        figures = idle_figures(tui.proc.pid, IDLE_S)
        server = proc_status(server_pid)
        watcher.close()
    finally:
        tui.close()
        subprocess.run([sys.executable, "-m", "dotshell.cli.app", "stop", str(profile), "--abort"],
                       env=env, capture_output=True, timeout=600)
    peer = PtyProcess([sys.executable, "-c", PEER], env, work)
    try:
        peer.wait_for(b"a bare Textual app")
        time.sleep(2.0)
        peer_figures = idle_figures(peer.proc.pid, IDLE_S)
    finally:
        peer.close()
        shutil.rmtree(work, ignore_errors=True)
    return {"quick": quick, "views": tracker["n_views"], "frames": tracker["frames_done"],
            "status": tracker["status"], "points": tracker["points"], "scan_s": scan_s,
            "tui": figures, "peer": peer_figures,
            "server_rss_mib": server["VmRSS"], "server_peak_rss_mib": server["VmHWM"]}


def print_tui(d: dict[str, Any]) -> None:
    t, p = d["tui"], d["peer"]
    print(f"\n== idle TUI attached to a rig server after a {d['views']}-view "
          f"{'quick' if d['quick'] else 'full-resolution'} scan ({d['frames']} frames, "
          f"{d['points']} points, {d['status']}, {d['scan_s']:.0f} s) ==")
    print(f"  dotshell tui        RSS {t['rss_mib']:6.1f} MiB  peak {t['peak_rss_mib']:6.1f} MiB  "
          f"idle CPU {t['idle_cpu_pct']:5.2f} %  (limit: 300 MiB)")
    print(f"  peer: bare Textual  RSS {p['rss_mib']:6.1f} MiB  peak {p['peak_rss_mib']:6.1f} MiB  "
          f"idle CPU {p['idle_cpu_pct']:5.2f} %")
    print(f"  ratio tui/peer      RSS {t['rss_mib'] / p['rss_mib']:.2f}×")
    print(f"  the server (holds the rig and the scan): RSS {d['server_rss_mib']:.0f} MiB, "
          f"peak {d['server_peak_rss_mib']:.0f} MiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a scaled-down scan (harness test)")
    args = ap.parse_args()
    d = run_tui_bench(args.quick)
    print_tui(d)
    out = ROOT / "bench-results" / ("tui-quick.json" if args.quick else "tui.json")
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(d, indent=2))


if __name__ == "__main__":
    main()
