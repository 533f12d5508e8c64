"""Regenerate the TUI screenshots of docs/tui.md (SVG, exported by Textual).

    .venv/bin/python docs/img/make_tui_screenshots.py

Drives `dotshell tui` with Textual's Pilot on a reduced simulated bench (in a temporary
directory) and writes docs/img/tui-*.svg at 120×40 (the rig also at 80×24).
"""

from __future__ import annotations

import asyncio
import os
import sys
import tempfile
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
    while loop.time() < end and not all(w.is_finished or w.group == "scan"
                                        for w in pilot.app.workers):
        await pilot.pause(0.05)
    await pilot.pause(0.2)


async def shoot(pilot, name: str, size=(120, 40)) -> None:
    await pilot.resize_terminal(*size)
    await settle(pilot)
    suffix = "" if size == (120, 40) else f"-{size[0]}x{size[1]}"
    pilot.app.save_screenshot(f"tui-{name}{suffix}.svg", str(OUT))
    print("wrote", OUT / f"tui-{name}{suffix}.svg")


async def main() -> None:
    from dotshell.console import Session
    from dotshell.tui.app import DotshellApp
    from dotshell.tui.widgets.console_input import ConsoleInput

    work = Path(tempfile.mkdtemp(prefix="dotshell-shots-"))
    os.chdir(work)
    (work / "profiles").mkdir()
    session = Session(bench_profile(work / "profiles" / "sim-metal-cylinder-small.toml"),
                      out_dir="runs")
    app = DotshellApp(session)
    async with app.run_test(size=(120, 40)) as pilot:
        await settle(pilot)
        await pilot.press("c")
        await settle(pilot)
        await pilot.press("right", "right", "space")
        await settle(pilot)
        await shoot(pilot, "rig")
        await shoot(pilot, "rig", (80, 24))
        app.action_show_tab("scan")
        await pilot.pause()
        await pilot.press("s")
        while app.tracker.frames_done < 40:
            await pilot.pause(0.05)
        await shoot(pilot, "scan-running")
        while session.scanning or app.tracker.status == "running":
            await pilot.pause(0.1)
        await shoot(pilot, "scan")
        app.action_show_tab("preview")
        await shoot(pilot, "preview")
        app.action_show_tab("log")
        await shoot(pilot, "log")
        app.action_show_tab("console")
        await pilot.pause()
        box = app.panel(ConsoleInput)
        box.cursor_blink = False
        for source in ("run", "run.report['validation']['mean_rel_error_pct']",
                       "pts = run.cloud()\nnp.round(np.ptp(pts, axis=0), 1)",
                       "for a in (0, 90):\n    move_to(a)\n    print(a, snap().frame.mean())\n",
                       "rig.analyzer.set_angle(45)"):
            box.text = source
            box.move_cursor(box.document.end)
            await pilot.press("enter")
            await settle(pilot)
        await shoot(pilot, "console")
        await pilot.press("ctrl+g")
        await shoot(pilot, "plugins")
        await pilot.press("escape")
        await pilot.press("ctrl+o")
        await shoot(pilot, "profile-picker")
        await pilot.press("escape")
    session.close()


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
