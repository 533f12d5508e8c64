"""Snapshot tests of the main screens at 60×20, 80×24 and 120×40 (the app attached to a rig
server on the tiny simulated bench): the SVG Textual exports is compared with the reference
under tests/snapshots/tui/, with the volatile parts (run-directory time stamps, clocks,
Textual's per-render id) masked.

A difference fails the test and leaves the new SVG next to the test's tmp dir. When a change
is intended, regenerate the references with ``DOTSHELL_UPDATE_SNAPSHOTS=1 pytest
tests/test_tui_snapshots.py`` and review them (open the SVGs in a browser) before committing.
"""

import difflib
import html
import os
import re
import threading
from pathlib import Path

import pytest

import textual.constants

from conftest import write_test_profile
from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.session.console import Session
from dotshell.events import FrameCaptured
from dotshell.plugins import PluginLoadError, PluginManager
from dotshell.tui.app import DotshellApp
from dotshell.tui.widgets.console_input import ConsoleInput
from dotshell.tui.widgets.keys_screen import KeysScreen
from dotshell.tui.widgets.plugins_screen import PluginsScreen
from rig_server import attach, served, user_dirs  # noqa: F401 (a fixture)
from test_tui import show_tab_when_up

pytestmark = pytest.mark.asyncio

REFERENCES = Path(__file__).parent / "snapshots" / "tui"
UPDATE = os.environ.get("DOTSHELL_UPDATE_SNAPSHOTS") == "1"
SIZES = ((60, 20), (80, 24), (120, 40))


def masked(svg: str) -> str:
    svg = re.sub(r"terminal-\d+", "terminal-X", svg)
    svg = re.sub(r"\d{8}-\d{6}", "YYYYmmdd-HHMMSS", svg)
    return re.sub(r"\d+:\d\d:\d\d", "H:MM:SS", svg)


def svg_text(svg: str) -> list[str]:
    """The text runs of an exported screen, in order (for a readable diff)."""
    return [html.unescape(t).replace("\xa0", " ")
            for t in re.findall(r"<text[^>]*>([^<]*)</text>", svg)]


def check(app, name: str, tmp_path: Path) -> None:
    width, height = app.size
    got = masked(app.export_screenshot(title=f"dotshell tui — {name}"))
    ref = REFERENCES / f"{name}-{width}x{height}.svg"
    if UPDATE:
        ref.parent.mkdir(parents=True, exist_ok=True)
        ref.write_text(got)
        return
    assert ref.is_file(), (f"no reference {ref}; create it with DOTSHELL_UPDATE_SNAPSHOTS=1 "
                           "and review it")
    want = ref.read_text()
    if got != want:
        out = tmp_path / ref.name
        out.write_text(got)
        diff = "\n".join(list(difflib.unified_diff(svg_text(want), svg_text(got), "reference",
                                                   "now", lineterm="", n=1))[:40])
        pytest.fail(f"{name} at {width}×{height} differs from {ref} (new screen: {out}); "
                    f"text diff:\n{diff or '(same text: colours or layout changed)'}\nIf "
                    "intended, re-run with DOTSHELL_UPDATE_SNAPSHOTS=1 and review the SVGs.")


async def check_sizes(pilot, name, tmp_path):
    for width, height in SIZES:
        await pilot.resize_terminal(width, height)
        await settle(pilot)
        check(pilot.app, name, tmp_path)


async def settle(pilot):
    for _ in range(400):
        if all(w.is_finished for w in pilot.app.workers):
            break
        await pilot.pause(0.02)
    await pilot.pause()
    await pilot.pause()


@pytest.fixture
def server(tmp_path, monkeypatch, user_dirs):
    monkeypatch.chdir(tmp_path)  # paths on screen are relative: runs/..., p.toml
    monkeypatch.setattr(textual.constants, "COLOR_SYSTEM", "truecolor")
    pm = PluginManager()
    pm.load_entry_points()
    session = Session(write_test_profile(tmp_path), pm=pm, out_dir="runs")
    with served(session, poll_s=0.1) as srv:
        yield srv
    session.close()


async def until(pilot, condition):
    for _ in range(1200):
        if condition():
            return
        await pilot.pause(0.05)
    raise AssertionError("the screen never got there")


async def show_tab(pilot, tab):
    """``tab`` shown once the main screen is up (test_tui.show_tab)."""
    await until(pilot, lambda: pilot.app.main_ready and pilot.app.focused is not None)
    await show_tab_when_up(pilot, tab)


async def test_rig_screen(server, tmp_path):
    app = DotshellApp(attach(server))
    async with app.run_test(size=SIZES[1]) as pilot:
        await until(pilot, lambda: app.focused is not None)
        await pilot.press("c")
        await settle(pilot)
        await pilot.press("right_square_bracket", "right_square_bracket")
        await settle(pilot)
        await until(pilot, lambda: any(r["status"].get("angle_deg") == 10.0
                                       for r in app.session.rows))
        await check_sizes(pilot, "rig", tmp_path)


async def test_scan_screen_paused_midway(server, tmp_path):
    session = server.session
    reached, opened = threading.Event(), threading.Event()

    def hold(ev):
        if isinstance(ev, FrameCaptured) and (ev.view, ev.index) == (0, 2):
            reached.set()
            opened.wait(60)

    session.bus.subscribe(hold)
    app = DotshellApp(attach(server))
    async with app.run_test(size=SIZES[1]) as pilot:
        await show_tab(pilot, "scan")
        await pilot.press("s")
        await until(pilot, reached.is_set)
        await until(pilot, lambda: app.session.scanning)  # p pauses a scan the TUI knows of
        await pilot.press("p")
        await until(pilot, lambda: session.state == "paused")
        opened.set()
        await until(pilot, lambda: app.tracker.status == "paused"
                    and app.session.session_state == "paused")
        await check_sizes(pilot, "scan-paused", tmp_path)
        session.abort()
        await until(pilot, lambda: not session.scanning)


async def test_console_screen(server, tmp_path):
    app = DotshellApp(attach(server))
    async with app.run_test(size=SIZES[1]) as pilot:
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        box.cursor_blink = False
        for source in ("connect(); jog(12.5)", "rig.stage.position * 2",
                       "for name in patterns()[:3]:\n    print(name)\n", "1 / 0", "rig"):
            box.text = source
            box.move_cursor(box.document.end)
            await pilot.press("enter")
            await settle(pilot)
            await until(pilot, lambda: not box.busy)
        await check_sizes(pilot, "console", tmp_path)


async def check_screen(server, key, screen, name, tmp_path):
    """The app with ``screen`` opened by ``key``, at every size."""
    app = DotshellApp(attach(server))
    async with app.run_test(size=SIZES[1]) as pilot:
        await until(pilot, lambda: app.focused is not None)
        await pilot.press(key)
        await until(pilot, lambda: isinstance(app.screen, screen))
        await check_sizes(pilot, name, tmp_path)


async def test_keys_overlay(server, tmp_path):
    await check_screen(server, "question_mark", KeysScreen, "keys", tmp_path)


class FixedPlugin:
    """Two made-up backends, so the plugins screen does not change with the installed ones."""

    @hookimpl
    def dotshell_cameras(self):
        return [Backend("lab-cam", lambda settings, context: None, {}, "a made-up camera")]

    @hookimpl
    def dotshell_stages(self):
        return [Backend("lab-stage", lambda settings, context: None, {}, "a made-up stage")]


async def test_plugins_screen(server, tmp_path):
    pm = PluginManager()
    pm.register(FixedPlugin(), name="lab", distribution="dotshell-lab 1.2")
    pm.load_errors.append(PluginLoadError("broken", "dotshell-broken 0.1",
                                          "ImportError: needs libfoo.so"))
    server.session.pm = pm
    await check_screen(server, "ctrl+g", PluginsScreen, "plugins", tmp_path)
