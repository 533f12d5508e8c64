"""Regenerate the TUI screenshots of docs/tui.md and docs/server.md (SVG, exported by Textual).

    .venv/bin/python docs/img/make_tui_screenshots.py

Serves a reduced simulated bench (in a temporary directory, with private runtime and state
directories) with a real rig server, drives `dotshell tui` attached to it with Textual's Pilot,
and writes docs/img/tui-*.svg at 120×40 (the rig also at 80×24 and 60×20) and
docs/img/server-watcher.svg (a second TUI watching the scan).
"""

from __future__ import annotations

import asyncio
import os
import shutil
import sys
import tempfile
import threading
import tomllib
from pathlib import Path

import tomli_w

ROOT = Path(__file__).resolve().parents[2]
OUT = Path(__file__).resolve().parent


def bench_profile(path: Path) -> Path:
    from dotshell_sim.bench import scale_profile

    raw = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text())
    raw = scale_profile(raw, 0.25)
    raw["scan"]["views"] = 4
    path.write_text(tomli_w.dumps(raw))
    return path


async def settle(pilot, seconds: float = 60.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while loop.time() < end and not all(w.is_finished for w in pilot.app.workers):
        await pilot.pause(0.05)
    await pilot.pause(0.3)


async def until(pilot, condition, seconds: float = 300.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while not condition():
        if loop.time() > end:
            raise RuntimeError("the screen never got there")
        await pilot.pause(0.05)


async def shoot(pilot, name: str, size=(120, 40), suffix: str | None = None) -> None:
    await pilot.resize_terminal(*size)
    await settle(pilot)
    if suffix is None:
        suffix = "" if size == (120, 40) else f"-{size[0]}x{size[1]}"
    pilot.app.save_screenshot(f"{name}{suffix}.svg", str(OUT))
    print("wrote", OUT / f"{name}{suffix}.svg")


async def console_inputs(pilot, sources) -> None:
    from dotshell.tui.widgets.console_input import ConsoleInput
    from dotshell.tui.widgets.console_panel import ConsolePanel

    box = pilot.app.panel(ConsoleInput)
    box.cursor_blink = False
    for source in sources:
        box.text = source
        box.move_cursor(box.document.end)
        await pilot.press("enter")
        await settle(pilot)
        await until(pilot, lambda: not pilot.app.panel(ConsolePanel).busy
                    or box.waiting_prompt is not None)


async def main() -> None:
    import textual.constants

    textual.constants.COLOR_SYSTEM = "truecolor"
    from dotshell.session.console import Session
    from dotshell.events import FrameCaptured
    from dotshell.server.client import RemoteSession
    from dotshell.runtime.paths import history_path, server_log_dir, socket_path
    from dotshell.server.server import RigServer
    from dotshell.tui.app import DotshellApp
    from dotshell.tui.widgets.console_input import ConsoleInput

    work = Path(tempfile.mkdtemp(prefix="ds-shots-", dir="/tmp"))
    for var, sub in (("XDG_RUNTIME_DIR", "run"), ("XDG_STATE_HOME", "state"),
                     ("XDG_CONFIG_HOME", "config")):
        (work / sub).mkdir(mode=0o700)
        os.environ[var] = str(work / sub)
    os.chdir(work)
    (work / "profiles").mkdir()
    session = Session(bench_profile(work / "profiles" / "sim-metal-cylinder-small.toml"),
                      out_dir="runs")
    name = "sim-metal-cylinder-small"
    server = RigServer(session, socket_path(name), name=name, log_dir=server_log_dir(name),
                       history_file=history_path())
    server.start()
    threading.Thread(target=server.serve_forever, daemon=True).start()
    hold = threading.Event()
    held = threading.Event()

    def pause_at(ev):  # the "running" shots are taken with the scan held at a known frame
        if isinstance(ev, FrameCaptured) and (ev.view, ev.index) == (1, 20) and not hold.is_set():
            held.set()
            hold.wait(120)

    session.bus.subscribe(pause_at)
    app = DotshellApp(RemoteSession(server.socket_path, "tui", control=True),
                      notice=f"started the rig server {name} (pid {os.getpid()})")
    async with app.run_test(size=(120, 40)) as pilot:
        await until(pilot, lambda: app.focused is not None)
        await pilot.press("c")
        await settle(pilot)
        await pilot.press("right_square_bracket", "right_square_bracket")
        await settle(pilot)
        await pilot.press("space")
        await settle(pilot)
        await until(pilot, lambda: any(r["status"].get("angle_deg") == 10.0
                                       for r in app.session.rows))
        await shoot(pilot, "tui-rig")
        await shoot(pilot, "tui-rig", (80, 24))
        await shoot(pilot, "tui-rig", (60, 20))
        await pilot.resize_terminal(120, 40)
        app.action_show_tab("preview")
        await shoot(pilot, "tui-preview")
        app.action_show_tab("scan")
        await pilot.pause()
        await pilot.press("s")
        await until(pilot, held.is_set)
        await until(pilot, lambda: app.tracker.frames_done >= 50)
        await shoot(pilot, "tui-scan-running")
        watcher = DotshellApp(RemoteSession(server.socket_path, "tui", control=False))
        async with watcher.run_test(size=(100, 30)) as wpilot:
            await until(wpilot, lambda: watcher.focused is not None)
            watcher.action_show_tab("scan")
            await until(wpilot, lambda: watcher.tracker.frames_done >= 50)
            await shoot(wpilot, "server-watcher", (100, 30), suffix="")
        hold.set()
        await until(pilot, lambda: app.tracker.status == "completed"
                    and not app.session.scanning)
        await shoot(pilot, "tui-scan")
        app.action_show_tab("log")
        await shoot(pilot, "tui-log")
        app.action_show_tab("console")
        await pilot.pause()
        await console_inputs(pilot, (
            "run", "run.report['validation']['mean_rel_error_pct']",
            "pts = run.cloud()\nnp.round(np.ptp(pts, axis=0), 1)",
            "for a in (0, 90):\n    move_to(a)\n    print(a, snap().frame.mean())\n",
            "rig", "views = int(input('views for the next scan? '))"))
        box = app.panel(ConsoleInput)
        await pilot.press(*"12")
        await shoot(pilot, "tui-console")
        await pilot.press("enter")
        await settle(pilot)
        await pilot.press("question_mark")
        await shoot(pilot, "tui-keys")
        await pilot.press("escape")
        await pilot.press("ctrl+p")
        await pilot.press(*"scan")
        await shoot(pilot, "tui-palette")
        await pilot.press("escape")
        await pilot.press("ctrl+g")
        await settle(pilot)
        await shoot(pilot, "tui-plugins")
        await pilot.press("escape")
        await pilot.press("ctrl+o")
        await shoot(pilot, "tui-profile-picker")
        await pilot.press("escape")
        box.text = ""
    server.shutdown("screenshots taken", abort=True)
    server.wait(120)
    os.chdir(ROOT)
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
