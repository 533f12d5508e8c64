"""The Textual UI driven by Textual's Pilot, attached over a real socket to a rig server that
holds the simulated rig: every test asserts on the server's session, the run directory and what
the panels show — not just that nothing crashed."""

import io
import threading
import time
from contextlib import asynccontextmanager
from pathlib import Path

import numpy as np
import pytest
import textual.constants
from PIL import Image
from rich.console import Console
from textual.command import CommandPalette
from textual.content import Content
from textual.widgets import Sparkline, TabbedContent
from textual.widgets._footer import FooterKey

import dotshell.tui.app
from conftest import write_test_profile
from dotshell.session.console import Session
from dotshell.events import FrameCaptured, Message, ScanFinished, ScanStarted
from dotshell.runtime.paths import config_path
from dotshell.run.store import RunStore
from dotshell.tui.app import DotshellApp
from dotshell.tui.messages import ServerMessage
from dotshell.tui.widgets.choice import ChoiceScreen
from dotshell.tui.widgets.confirm import ConfirmScreen
from dotshell.tui.widgets.console_input import ConsoleInput
from dotshell.tui.widgets.console_panel import ConsolePanel
from dotshell.tui.widgets.keys_footer import KeyRow
from dotshell.tui.widgets.keys_screen import KeysScreen
from dotshell.tui.widgets.log_panel import LogPanel
from dotshell.tui.widgets.plugins_screen import PluginsScreen
from dotshell.tui.widgets.preview_panel import PreviewPanel
from dotshell.tui.widgets.profile_picker import ProfilePicker
from dotshell.tui.widgets.prompt import PromptScreen
from dotshell.tui.widgets.quit_screen import QuitScreen
from dotshell.tui.widgets.reflow_log import ReflowLog
from dotshell.tui.widgets.rig_panel import RigPanel
from dotshell.tui.widgets.scan_panel import ScanPanel
from rig_server import attach, served, user_dirs  # noqa: F401 (a fixture)

pytestmark = pytest.mark.asyncio


@pytest.fixture
def truecolor(monkeypatch):
    monkeypatch.setattr(textual.constants, "COLOR_SYSTEM", "truecolor")


@pytest.fixture
def server(tmp_path, pm, monkeypatch, truecolor, user_dirs):
    """A rig server on the tiny simulated bench; ``server.session`` is its Session."""
    monkeypatch.chdir(tmp_path)
    session = Session(write_test_profile(tmp_path), pm=pm, out_dir="runs")
    with served(session, poll_s=0.1) as srv:
        yield srv
    session.close()


def app_for(server, **kwargs):
    return DotshellApp(attach(server), **kwargs)


@asynccontextmanager
async def running(app, size):
    """``app.run_test`` once the app is up and a panel has the focus (keys reach it)."""
    async with app.run_test(size=size) as pilot:
        await wait_until(pilot, lambda: app.focused is not None or len(app.screen_stack) > 1)
        yield pilot


async def settle(pilot):
    """Let every running request finish and the UI process what came back."""
    await wait_until(pilot, lambda: all(w.is_finished for w in pilot.app.workers))
    await pilot.pause()
    await pilot.pause()


async def wait_until(pilot, condition, timeout_s=60.0):
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout_s, "timed out waiting for the UI"
        await pilot.pause(0.05)


def static_text(app, selector):
    """The plain text a widget on the main screen shows (Textual content or a Rich renderable)."""
    content = app.screen_stack[0].query_one(selector).content
    if isinstance(content, str):
        return Content.from_markup(content).plain
    if hasattr(content, "plain"):
        return content.plain
    console = Console(width=200, record=True, file=io.StringIO())
    console.print(content)
    return console.export_text()


def actions(session, prefix):
    """Log lines the session wrote for rig actions starting with ``prefix``."""
    seen = []
    session.bus.subscribe(lambda ev: seen.append(ev.text) if isinstance(ev, Message)
                          and ev.text.startswith(prefix) else None)
    return seen


class Gate:
    """Holds the scan thread right after frame ``index`` of ``view`` is captured until the test
    opens it, so keys pressed meanwhile land at a known point of the scan."""

    def __init__(self, session, view, index):
        self.at = (view, index)
        self.reached = threading.Event()
        self.opened = threading.Event()
        session.bus.subscribe(self)

    def __call__(self, ev):
        if isinstance(ev, FrameCaptured) and (ev.view, ev.index) == self.at:
            self.reached.set()
            self.opened.wait(60)

    async def wait(self, pilot):
        await wait_until(pilot, self.reached.is_set)


# ---- the rig -------------------------------------------------------------------------------------

async def test_connect_jog_snap_from_the_rig_panel(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        assert session.connected
        await wait_until(pilot, lambda: "connected" in static_text(app, "#rig-table"))

        await pilot.press("right_square_bracket", "right_square_bracket", "left_square_bracket")
        await settle(pilot)
        await wait_until(pilot, lambda: not app.panel(RigPanel).jogs.moving)
        assert session.rig.stage.position == pytest.approx(5.0)  # 3 jogs of 5°: net +5°
        await pilot.press("plus")  # step 10°
        await pilot.press("right_square_bracket")
        await settle(pilot)
        assert session.rig.stage.position == pytest.approx(15.0)
        await wait_until(pilot, lambda: "angle 15.00°" in static_text(app, "#rig-table"))

        await pilot.press("space")
        await settle(pilot)
        snaps = sorted((session.out_dir / "snapshots").glob("snap_*.png"))
        assert [p.name for p in snaps] == ["snap_0001.png", "snap_0001_preview.png"]
        raw = np.asarray(Image.open(snaps[0]))
        w, h = session.rig.camera.resolution
        assert raw.shape == (h, w) and raw.dtype == np.uint16
        assert "snapshots/snap_0001.png" in static_text(app, "#rig-result")
        # the preview: the snapshot, its raw frame's figures and histogram, its aspect ratio
        preview = app.panel(PreviewPanel)
        await wait_until(pilot, lambda: preview.current is not None)
        assert preview.current.kind == "snap" and preview.current.size == (w, h)
        await show_tab(pilot, "preview")  # its histogram and image are drawn when shown
        assert f"{w}×{h}" in static_text(app, "#preview-title")
        stats = preview.current.stats
        assert stats["max"] == raw.max() and stats["min"] == raw.min()
        assert stats["saturated_pct"] == pytest.approx(100 * np.mean(raw >= 4095))
        assert f"max {raw.max():g}" in static_text(app, "#preview-stats")
        assert preview.query_one(Sparkline).data == stats["histogram"]
        image = preview.query_one("#preview-image").region
        drawn = (image.width * 1.0) / (image.height * 2.0)  # cells are twice as tall as wide
        assert drawn == pytest.approx(w / h, rel=0.08)
        # every action was logged by the session (server log and Log tab)
        log = server.log_path.read_text()
        assert "stage jogged +5.00° from 0.00° to 5.00°" in log
        assert "stage jogged +10.00° from 5.00° to 15.00°" in log and "snap at 15.00°" in log
        assert any("stage jogged +10.00°" in e.text for e in app.panel(LogPanel).entries)


async def test_prompts_start_from_current_values_and_project_highlights_the_pattern(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        session.move_to(33.5)
        session.set_exposure(12.0)
        await wait_until(pilot, lambda: "angle 33.50°" in static_text(app, "#rig-table"))
        await pilot.press("g")
        await pilot.pause()
        assert isinstance(app.screen, PromptScreen)
        assert app.screen.query_one("Input").value == "33.5"
        app.screen.query_one("Input").value = "40"
        await pilot.press("enter")
        await settle(pilot)
        assert session.rig.stage.position == pytest.approx(40.0)
        await pilot.press("h")  # home: back to the reference
        await settle(pilot)
        assert session.rig.stage.position == 0.0 and "stage at 0.00°" in static_text(app, "#rig-result")
        session.move_to(40.0)
        await pilot.press("e")
        await pilot.pause()
        assert app.screen.query_one("Input").value == "12"
        app.screen.query_one("Input").value = "7.5"
        await pilot.press("enter")
        await settle(pilot)
        assert session.rig.camera.status()["exposure_ms"] == 7.5

        await pilot.press("t")  # t: project a pattern (p is pause on every tab)
        await settle(pilot)
        await wait_until(pilot, lambda: isinstance(app.screen, ChoiceScreen))
        await pilot.press("enter")  # the first pattern: "white"
        await settle(pilot)
        assert session.projected == "white"
        await wait_until(pilot, lambda: app.session.projected == "white")
        await pilot.press("t")
        await wait_until(pilot, lambda: isinstance(app.screen, ChoiceScreen))
        assert app.screen.query_one("OptionList").highlighted == 0  # the pattern shown now
        await pilot.press("escape")
        log = server.log_path.read_text()
        assert "stage moved to 40.00°" in log and "camera exposure set to 7.5 ms" in log
        assert "stage homed: at 0.00°" in log
        assert "projector shows pattern white" in log


async def test_navigation_keys_never_move_hardware(server):
    session = server.session
    moves = actions(session, "stage ")
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        navigation = ["left", "right", "up", "down", "home", "end", "pageup", "pagedown",
                      "tab", "shift+tab", "left", "left", "right"]
        for tab in ("1", "2", "3"):  # the tabs with keys that act (Rig, Scan, Preview)
            await pilot.press(tab, *navigation)  # the bug: shift+tab, ←, ← on Scan jogged to −5°
        await pilot.press("1", "shift+tab", "left", "left", "right", "right", "enter")
        await settle(pilot)
        assert moves == [] and session.rig.stage.position == 0.0
        assert session.connected  # the keys reached the app: the rig was connected by "c"


async def test_key_repeat_collapses_into_one_move_and_escape_stops(server, monkeypatch):
    session = server.session
    jogs = actions(session, "stage jogged")
    stops = []
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        stage = session.rig.stage
        move, moving = stage.move_to, threading.Event()
        monkeypatch.setattr(stage, "move_to", lambda deg: (moving.wait(30), move(deg)))  # slow
        monkeypatch.setattr(session.rig, "stop", lambda: stops.append(time.monotonic()))
        await pilot.press(*["right_square_bracket"] * 20)  # 20 presses of the 5° step...
        moving.set()  # ...all while the first move was under way
        await wait_until(pilot, lambda: not app.panel(RigPanel).jogs.moving)
        await settle(pilot)
        assert stage.position == pytest.approx(100.0)
        assert jogs == ["stage jogged +5.00° from 0.00° to 5.00°",  # the first step, then the
                        "stage jogged +95.00° from 5.00° to 100.00°"]  # rest at once: 2, not 20
        # the stop key: pending presses are dropped and the rig is told to stop
        moving.clear()
        await pilot.press(*["right_square_bracket"] * 5, "escape")
        await wait_until(pilot, lambda: len(stops) == 1)
        moving.set()
        await wait_until(pilot, lambda: not app.panel(RigPanel).jogs.moving)
        await settle(pilot)
        assert stage.position == pytest.approx(105.0)  # the move under way, nothing after it
        assert any("stop: every device" in e.text for e in app.panel(LogPanel).entries)


async def test_a_narrow_terminal_stacks_the_device_table(server):
    app = app_for(server)
    async with running(app, (60, 20)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        await wait_until(pilot, lambda: "angle 0.00°" in static_text(app, "#rig-table"))
        lines = static_text(app, "#rig-table").splitlines()
        assert lines[0] == "● camera sim-camera" and lines[1].startswith("  exposure")
        assert lines[2] == "● projector sim-projector" and "backend" not in lines[0]
        await pilot.resize_terminal(120, 40)
        await pilot.pause()
        await wait_until(pilot, lambda: "backend" in static_text(app, "#rig-table"))


def lines_of(table):
    """Lines the content of the device table takes at the width it has."""
    console = Console(width=table.content_size.width, record=True, file=io.StringIO())
    console.print(table.content)
    return len(console.export_text().splitlines())


def screen_lines(app):
    """The text the terminal shows, line by line (what a person sees, clipping included)."""
    return [strip.text for strip in app.screen._compositor.render_strips()]


async def test_the_device_table_is_as_tall_as_its_rows_whatever_was_drawn_before(server):
    """The device table is repainted without a screen layout only when its rows take exactly
    the lines it was laid out with. A row list that was drawn but never laid out (the server
    pushes a partial list while the profile's devices are made, the full one right after)
    must not leave the table at the older list's height, clipping devices off the screen.
    Nor may a list drawn while the table's layout is due (the pty tests' 'sim-turntable
    never shown' on a loaded machine): the table drawn, the screen laid out for another
    widget's sake before the table's own layout request went out (sizing the table by that
    content), then the full list. Textual kept the size computed for the older content, 2
    lines for the 6 of three devices; the screen layout in between is forced here by the
    calls Textual's own makes."""
    app = app_for(server)
    async with running(app, (120, 40)) as pilot:
        await wait_until(pilot, lambda: "sim-turntable" in static_text(app, "#rig-table"))
        panel = app.panel(RigPanel)
        table = app.screen_stack[0].query_one("#rig-table")
        rows = list(panel.rows)
        assert [r["role"] for r in rows] == ["camera", "projector", "stage"]
        for drawn in ([], rows[:1], rows[:2], rows, rows[:1], [], rows):
            panel.show_rows(drawn)
            await pilot.pause()
            assert table.size.height == lines_of(table)
            assert table.size.height >= len(drawn) + 2  # header, rows, the absent devices line
        # the list before was drawn but never laid out, and took as many lines as this one
        full = table.size.height
        panel.show_rows([])
        await pilot.pause()
        table.update("\n".join(["never laid out"] * full), layout=False)
        panel.show_rows(rows)
        await pilot.pause()
        assert table.size.height == lines_of(table) == full
        shown = "\n".join(screen_lines(app))
        assert all(r["backend"] in shown for r in rows) and "never laid out" not in shown
        for before in ([], rows[:1]):  # the interleaving a loaded machine made, forced:
            panel.show_rows(rows)
            await pilot.pause()
            panel.show_rows(before)  # fewer lines: the table's layout due
            panel._clear_arrangement_cache()  # a sibling's layout request, then the screen's
            app.screen._refresh_layout()  # layout: the table sized by ``before``
            panel.show_rows(rows)  # the full list, the table's layout still due
            await pilot.pause()
            await pilot.pause()
            assert table.size.height == lines_of(table) >= len(rows) + 2
            shown = "\n".join(screen_lines(app))
            assert all(r["backend"] in shown for r in rows)


async def test_what_the_server_says_before_the_screen_is_mounted_is_shown(server):
    """The app subscribes to the server in its ``on_mount``, before Textual has mounted the
    main screen; the server's next messages can be handled then (seen in a real terminal on a
    loaded machine: the device list came then, was dropped, and the table stayed empty until
    the next change). They are shown like any other."""
    session = attach(server)
    deadline = time.monotonic() + 60
    while not session.rows and time.monotonic() < deadline:  # the server's first device list
        time.sleep(0.02)
    rows = list(session.rows)
    assert [r["role"] for r in rows] == ["camera", "projector", "stage"]
    session.rows = []  # the app starts from an empty list, as before the server made the rig
    mounted_then = []

    class HearsAtOnce(DotshellApp):
        CSS_PATH = str(Path(dotshell.tui.app.__file__).with_name(DotshellApp.CSS_PATH))

        def on_mount(self) -> None:
            super().on_mount()
            mounted_then.append(self.screen_stack[0].is_mounted)
            for message in ({"type": "devices", "rows": rows[:1]},
                            {"type": "event", "event": Message("info", "said early").to_dict()},
                            {"type": "devices", "rows": rows}):
                self.on_server_message(ServerMessage(message))

    app = HearsAtOnce(session)
    async with running(app, (120, 40)) as pilot:
        await pilot.pause()
        assert mounted_then == [False]  # what the messages met
        assert app.panel(RigPanel).rows == rows
        shown = "\n".join(screen_lines(app))
        assert all(r["backend"] in shown for r in rows)
        assert "said early" in [e.text for e in app.panel(LogPanel).entries]


# ---- tabs, focus, keys ---------------------------------------------------------------------------

async def show_tab(pilot, tab):
    """Show ``tab`` once the main screen is up (``action_show_tab`` does nothing before: a
    snapshot taken then showed the rig tab under a loaded CI host) and wait until it shows."""
    app = pilot.app
    await wait_until(pilot, lambda: app.main_ready and app.focused is not None)
    await show_tab_when_up(pilot, tab)


async def show_tab_when_up(pilot, tab):
    """``action_show_tab`` until ``tab`` shows: on a loaded host the main screen's first focus
    (AUTO_FOCUS, the rig panel) can land after the switch and take the tabs back to rig."""
    app = pilot.app
    for _ in range(200):
        app.action_show_tab(tab)
        for _ in range(10):
            await pilot.pause(0.02)
            if app.panel(TabbedContent).active == tab:
                await pilot.pause()
                if app.panel(TabbedContent).active == tab:
                    return
    raise AssertionError(f"the {tab} tab never showed")


#: A key the footer shows while each tab's panel has the focus.
FOOTER_KEYS = {"rig": "Jog +", "scan": "Start scan", "preview": "Previous"}


def footer_keys(app):
    """The descriptions of the keys the footer shows now."""
    return [key.description for row in app.query(KeyRow) if row.display
            for key in row.query(FooterKey)]


async def switched(pilot, switches, count):
    """Wait for the ``count``-th tab switch, then until the UI is idle: a bounce — the switch
    back that reacts to it — has happened by then (it would be switch ``count + 1``)."""
    await wait_until(pilot, lambda: len(switches) >= count)
    await pilot.pause()
    await pilot.pause()


async def test_leaving_the_console_with_f_keys_never_bounces_back(server):
    """The bounce: the tab switched first, hiding the focused console input; Textual handed the
    focus to a hidden sibling in the console pane and TabbedContent switched back to it. Now the
    focus moves first: whenever the tab changes, the focus is already in the new pane."""
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        tabs = app.panel(TabbedContent)
        focus_at_switch = []
        app.watch(tabs, "active", lambda active: focus_at_switch.append(
            (active, app.screen.focused)), init=False)
        for i in range(9):  # each tab 3 times; the focus at every switch is checked below
            await pilot.press("f6")
            await switched(pilot, focus_at_switch, 2 * i + 1)
            assert tabs.active == "console" and app.focused is app.panel(ConsoleInput)
            assert not set(FOOTER_KEYS.values()) & set(footer_keys(app))  # no panel keys
            key, tab = [("f2", "rig"), ("f3", "scan"), ("f4", "preview")][i % 3]
            await pilot.press(key)
            await switched(pilot, focus_at_switch, 2 * i + 2)
            assert tabs.active == tab, f"repetition {i + 1}: {key} bounced to {tabs.active}"
            pane = app.screen.query_one(f"TabPane#{tab}")
            assert pane in app.focused.ancestors_with_self
            assert FOOTER_KEYS[tab] in footer_keys(app) and "Quit" in footer_keys(app)
            active, focused = focus_at_switch[-1]
            assert active == tab and pane in focused.ancestors_with_self, \
                f"repetition {i + 1}: the tab switched while {focused} had the focus"
        assert len(focus_at_switch) == 18  # every switch was seen, none bounced
        # the footer made one row of keys per tab and showed it again on each return
        assert len(app.query(KeyRow)) == 4
        # number keys do the same, and the console takes digits as text
        await pilot.press("5")
        await pilot.pause()
        await pilot.press("4", "2")
        assert tabs.active == "console" and app.panel(ConsoleInput).text == "42"


async def test_text_written_while_hidden_wraps_to_the_pane(server):
    app = app_for(server)
    async with running(app, (100, 30)) as pilot:
        await show_tab(pilot, "rig")
        long = "the quick brown fox jumps over the lazy dog " * 4
        for i in range(5):
            app.panel(LogPanel).add("info", f"{i} {long}")
            app.panel(ConsolePanel).write("out", f"{i} {long}\n")
        for tab, selector in (("log", "#log-view"), ("console", "#console-out")):
            await show_tab(pilot, tab)
            view = app.screen.query_one(selector, ReflowLog)
            await wait_until(pilot, lambda: view.laid_out_for == view.size.width > 0)
            widths = [strip.cell_length for strip in view.lines]
            assert max(widths) > 60  # wrapped at the pane's width, not at 20 columns
            assert max(widths) <= view.size.width
        await pilot.resize_terminal(70, 30)  # and again for a new width
        await pilot.pause()
        view = app.screen.query_one("#console-out", ReflowLog)
        await wait_until(pilot, lambda: view.laid_out_for == view.size.width)
        assert max(strip.cell_length for strip in view.lines) <= view.size.width


async def test_keys_overlay_and_the_command_palette(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        for key in ("question_mark", "f1"):
            await pilot.press(key)
            await pilot.pause()
            assert isinstance(app.screen, KeysScreen)
            shown = {(where, keys, what) for where, rows in app.screen.sections
                     for keys, what in rows}
            assert ("Rig", "]", "Jog +") in shown and ("anywhere", "x", "Abort") in shown
            assert ("anywhere", "1 F2", "Rig") in shown and ("anywhere", "? F1", "Keys") in shown
            await pilot.press("escape")
            await pilot.pause()
            assert not isinstance(app.screen, KeysScreen)
        assert "1 Rig" in str(app.screen.query_one("ContentTab").label)
        await pilot.press("ctrl+p")
        await pilot.pause()
        assert isinstance(app.screen, CommandPalette)
        await pilot.press(*"start scan")
        palette = app.screen
        await wait_until(pilot, lambda: palette.query_one("CommandList").option_count > 0)
        first = palette.query_one("CommandList").get_option_at_index(0)
        assert "Start scan" in str(first.prompt)
        await pilot.press("enter")
        await wait_until(pilot, lambda: app.tracker.status != "idle")
        await wait_until(pilot, lambda: not session.scanning, timeout_s=120)


# ---- scans -------------------------------------------------------------------------------------------

async def test_short_scan_runs_to_the_end(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "scan")
        assert app.focused is app.panel(ScanPanel)
        await pilot.press("s")
        await wait_until(pilot, lambda: app.tracker.status in ("completed", "aborted", "failed"))
        await wait_until(pilot, lambda: not app.session.scanning)
        await settle(pilot)
        t = app.tracker
        assert t.status == "completed"
        assert t.frames_done == t.frames_total == 2 * t.frames_per_view > 0
        assert t.views_done == t.views_reconstructed == 2
        run = session.run
        assert run is not None and run.status == "completed"
        assert run.frame_count() == t.frames_total
        assert len(run.cloud()) == t.points > 1000
        assert "completed" in static_text(app, "#scan-state")
        assert static_text(app, "#frames-count") == f"{t.frames_total}/{t.frames_total}"
        preview = app.panel(PreviewPanel)
        assert [i.view for i in preview.items if i.kind == "frame"] == [0, 1]
        assert "latest frame (view 2)" in static_text(app, "#preview-title")  # 1-based
        assert (run.root / "live" / "latest_frame.png").is_file()
        texts = [e.text for e in app.panel(LogPanel).entries]
        assert any(t.startswith("scan completed") for t in texts)
        assert "view 1 captured at 0.0°" in " ".join(texts)
        assert "view 2 reconstructed" in " ".join(texts) and "view 0 " not in " ".join(texts)


async def test_pause_resume_then_abort_midway_keeps_frames(tmp_path, pm, monkeypatch, truecolor,
                                                           user_dirs):
    monkeypatch.chdir(tmp_path)
    session = Session(write_test_profile(tmp_path, views=3), pm=pm, out_dir="runs")
    first, second = Gate(session, 0, 2), Gate(session, 1, 4)
    with served(session, poll_s=0.1) as server:
        app = app_for(server)
        async with running(app, (80, 24)) as pilot:
            await show_tab(pilot, "scan")
            await pilot.press("s")
            await first.wait(pilot)
            await wait_until(pilot, lambda: app.session.scanning)  # p pauses a known scan
            await pilot.press("p")
            await wait_until(pilot, lambda: session.state == "paused")
            first.opened.set()  # the scan goes on to the next frame boundary and waits there
            await wait_until(pilot, lambda: app.tracker.status == "paused")
            assert app.tracker.frames_done == 3
            await pilot.pause(0.3)
            assert app.tracker.frames_done == 3  # nothing is captured while paused
            await wait_until(pilot, lambda: "paused" in static_text(app, "#scan-state"))
            assert "view 1/3" in static_text(app, "#scan-state")  # 1-based, as on the bar
            await pilot.press("p")
            await wait_until(pilot, lambda: session.state == "running")
            await second.wait(pilot)
            await pilot.press("p")  # pause again, then abort from the pause
            await wait_until(pilot, lambda: session.state == "paused")
            second.opened.set()
            await wait_until(pilot, lambda: app.tracker.status == "paused")
            await wait_until(pilot, lambda: app.session.session_state == "paused")
            await pilot.press("x")  # abort always asks
            await wait_until(pilot, lambda: isinstance(app.screen, ConfirmScreen))
            await pilot.press("y")
            await wait_until(pilot, lambda: not session.scanning)
            await wait_until(pilot, lambda: app.tracker.status == "aborted")
            run = session.run
            assert run.status == "aborted"
            fpv = app.tracker.frames_per_view
            assert app.tracker.frames_done == fpv + 5
            assert run.frame_count() == fpv + 5  # every captured frame is on disk
            store = RunStore.open(run.root)
            assert [store.frames(v).count() for v in range(3)] == [fpv, 5, 0]
            assert [(v["frames"], v["complete"]) for v in run.manifest["views"]] == [
                (fpv, True), (5, False), (0, False)]
            events = [(e["event"], e.get("view"), e.get("index")) for e in run.events()]
            assert [e for e in events if e[0] in ("ScanPaused", "ScanResumed")] == [
                ("ScanPaused", 0, 3), ("ScanResumed", 0, 3), ("ScanPaused", 1, 5)]
            await wait_until(pilot, lambda: "aborted" in static_text(app, "#scan-state"))
    session.close()


async def test_aborting_a_long_scan_asks_first(server):
    session = server.session
    gate = Gate(session, 0, 1)
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "scan")
        await pilot.press("s")
        await gate.wait(pilot)
        await wait_until(pilot, lambda: app.session.scanning and app.tracker.active)
        app.tracker.started_s -= 120  # as if it had run for two minutes
        await pilot.press("x")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen) and "2:0" in str(app.screen.question)
        await pilot.press("n")
        await pilot.pause()
        assert session.state == "running"
        await pilot.press("escape")  # the stop key never aborts: it pauses the scan
        await wait_until(pilot, lambda: session.state == "paused")
        assert not isinstance(app.screen, ConfirmScreen)
        await pilot.press("x")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen)
        await pilot.press("y")
        await wait_until(pilot, lambda: session.state in ("stopping", "idle"))
        gate.opened.set()
        await wait_until(pilot, lambda: not session.scanning)
        assert session.run.status == "aborted"


async def test_no_points_reads_failed_and_few_colours_are_said(server, monkeypatch):
    monkeypatch.setattr(textual.constants, "COLOR_SYSTEM", "256")
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "scan")
        for ev in (ScanStarted(run_dir="runs/x", profile="p", n_views=1, frames_per_view=2),
                   ScanFinished(status="completed", run_dir="runs/x", summary={"points": 0})):
            app.post_message(ServerMessage({"type": "event", "event": ev.to_dict()}))
        await wait_until(pilot, lambda: app.tracker.status == "completed")
        await pilot.pause()
        assert "state failed" in static_text(app, "#scan-state")
        assert "no points" in static_text(app, "#scan-error")
        assert app.panel(LogPanel).entries[-1].level == "error"
        # a 256-colour terminal is told that images are approximate
        assert any("shows 256 colours" in e.text for e in app.panel(LogPanel).entries)
        app.panel(PreviewPanel).add_preview("snap", str(write_png(server)), -1, {})
        await pilot.pause()
        assert "only 256 colours" in static_text(app, "#preview-title")


@pytest.mark.parametrize("choice", ["leave", "stop"])
async def test_quitting_during_a_scan_leaves_it_running_or_stops_it(server, choice):
    session = server.session
    gate = Gate(session, 0, 2)
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "scan")
        await pilot.press("s")
        await gate.wait(pilot)
        await wait_until(pilot, lambda: app.session.scanning)
        await pilot.press("ctrl+q")
        await pilot.pause()
        assert isinstance(app.screen, QuitScreen)
        await pilot.press("escape")  # stay
        await pilot.pause()
        assert app.is_running and session.state == "running"
        await pilot.press("ctrl+q")
        await pilot.pause()
        await pilot.press(choice[0])  # l: leave it running, s: stop it and quit
        if choice == "stop":
            await wait_until(pilot, lambda: session.state == "stopping")
        gate.opened.set()
        await wait_until(pilot, lambda: not app.is_running)
    run = session.job.wait(120)
    if choice == "leave":
        assert run.status == "completed"  # the scan went on without the front end
    else:
        assert run.status == "aborted" and run.frame_count() == 3  # frames 1..3, all kept
    assert session.rig.connected  # the server still holds the rig


async def test_a_second_front_end_watches_until_it_takes_control(server):
    session = server.session
    first = attach(server)
    app = app_for(server)
    async with running(app, (120, 40)) as pilot:
        await pilot.pause()
        assert "watching: tui#1 controls" in app.sub_title
        assert "tui#1 controls" in static_text(app, "#summary-server")
        await pilot.press("c")
        await settle(pilot)
        assert "tui#1" in static_text(app, "#rig-error") and not session.connected
        await pilot.press("ctrl+t")
        await settle(pilot)
        await wait_until(pilot, lambda: "in control" in app.sub_title)
        await pilot.press("c")
        await settle(pilot)
        assert session.connected
    first.close()


# ---- the console -------------------------------------------------------------------------------------

async def enter(pilot, source):
    box = pilot.app.panel(ConsoleInput)
    box.text = source
    box.move_cursor(box.document.end)
    await pilot.press("enter")
    await settle(pilot)
    await wait_until(pilot, lambda: not pilot.app.panel(ConsolePanel).busy)


async def test_console_evaluates_against_the_live_session(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        assert app.focused is box
        panel = app.panel(ConsolePanel)
        await enter(pilot, "connect(); jog(30)")
        assert session.rig.stage.position == pytest.approx(30.0)
        await pilot.press(*"rig.stage.position")  # typed key by key
        await pilot.press("enter")
        await wait_until(pilot, lambda: panel.transcript[-1] == ("result", "30.0"))
        await enter(pilot, "for a in (40, 50):\n    move_to(a)\n")  # a block, ended by a blank line
        assert session.rig.stage.position == pytest.approx(50.0)
        await enter(pilot, "frame = snap().frame\nframe.shape")
        w, h = session.rig.camera.resolution
        assert panel.transcript[-1] == ("result", repr((h, w)))
        await enter(pilot, "print('mean', int(frame.mean() > 0), np.pi > 3)")
        assert "mean 1 True\n" in panel.output_text
        await enter(pilot, "rig")  # a readable repr, not <... object at 0x...>
        assert panel.transcript[-1] == ("result", "<Rig of sim-metal-cylinder: camera "
                                        "sim-camera, projector sim-projector, stage sim-turntable>")
        await enter(pilot, "profile")
        assert panel.transcript[-1][1].startswith("<Profile sim-metal-cylinder from ")
        assert "2 views" in panel.transcript[-1][1]
        await pilot.press("up")  # history: the last input comes back
        assert box.text == "profile"
        # Tab completes the name before the cursor
        box.text = ""
        await pilot.press(*"rig.stag", "tab")
        await wait_until(pilot, lambda: box.text == "rig.stage")
        box.text = ""
        await pilot.press(*"set_", "tab")  # two matches: both shown, the shared part typed
        await wait_until(pilot, lambda: "set_analyzer(  set_exposure(" in panel.output_text)
        box.text = "for i in (1, 2):\n"
        box.move_cursor(box.document.end)
        await pilot.press("tab")  # no name before the cursor: Tab indents
        assert box.text.endswith("\n    ")


async def test_console_input_and_help_ask_in_the_console(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        panel = app.panel(ConsolePanel)
        box.text = "angle = float(input('angle? ')); connect(); move_to(angle)"
        await pilot.press("enter")
        await wait_until(pilot, lambda: box.waiting_prompt == "angle? ")
        assert "angle?" in static_text(app, "#console-status")
        await pilot.press("4", "5", "f3")  # digits are text here; an F-key is not
        assert box.text == "45"
        await show_tab(pilot, "console")
        await pilot.press("enter")
        await wait_until(pilot, lambda: not panel.busy)
        assert session.rig.stage.position == pytest.approx(45.0)
        assert "angle? 45\n" in panel.output_text
        # help() reads its topics through the console too; its text lands in the pane
        box.text = "help()"
        await pilot.press("enter")
        await wait_until(pilot, lambda: box.waiting_prompt == "help> ")
        await pilot.press(*"len", "enter")
        await wait_until(pilot, lambda: "Return the number of items" in panel.output_text)
        await wait_until(pilot, lambda: box.waiting_prompt == "help> ")
        await pilot.press(*"quit", "enter")
        await wait_until(pilot, lambda: not panel.busy)
        assert "ready" in static_text(app, "#console-status")
        # ctrl+c while input() waits
        box.text = "input('never? ')"
        await pilot.press("enter")
        await wait_until(pilot, lambda: box.waiting_prompt == "never? ")
        await pilot.press("ctrl+c")
        await wait_until(pilot, lambda: not panel.busy)
        assert panel.transcript[-1][0] == "error" and "KeyboardInterrupt" in panel.transcript[-1][1]


async def test_console_errors_and_interrupts_and_the_app_lives_on(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "console")
        panel = app.panel(ConsolePanel)
        for source in ("def broken():\n    return 1 / 0\n", "broken()", "def f(:",
                       "jog(5)"):  # jog before connect: a DeviceError with the fix
            await enter(pilot, source)
        errors = [t for k, t in panel.transcript if k == "error"]
        assert len(errors) == 3
        assert "Traceback (most recent call last)" in errors[0]
        assert 'File "<console#2>", line 1' in errors[0] and "return 1 / 0" in errors[0]
        assert errors[0].rstrip().endswith("ZeroDivisionError: division by zero")
        assert "SyntaxError" in errors[1] and "def f(:" in errors[1]
        assert "DeviceError" in errors[2] and "connect the rig first" in errors[2]
        assert "interpreter.py" not in "".join(errors)  # the engine's frames are hidden
        shown = "\n".join(strip.text for strip in panel.query_one("#console-out").lines)
        assert "ZeroDivisionError: division by zero" in shown
        await enter(pilot, "connect(); jog(5)")
        assert session.rig.stage.position == pytest.approx(5.0)
        assert app.is_running
        # ctrl+c interrupts a long call
        box = app.panel(ConsoleInput)
        box.text = "n = 0\nwhile True:\n    n += 1\n"
        box.move_cursor(box.document.end)
        await pilot.press("enter")
        namespace = server.console.interpreter.namespace
        await wait_until(pilot, lambda: namespace.get("n", 0) > 1000)
        assert panel.busy
        await pilot.press("ctrl+c")
        await wait_until(pilot, lambda: not panel.busy)
        assert panel.transcript[-1][0] == "error" and "KeyboardInterrupt" in panel.transcript[-1][1]
        await enter(pilot, "n > 1000")
        assert panel.transcript[-1] == ("result", "True")


# ---- profiles, plugins, log, colours -----------------------------------------------------------

async def test_profile_picker_lists_config_dirs_and_plugins_screen_lists_backends(
        tmp_path, pm, monkeypatch, truecolor, user_dirs):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "profiles").mkdir()
    write_test_profile(tmp_path / "profiles", views=4, name="four.toml")
    (tmp_path / "lab").mkdir()
    write_test_profile(tmp_path / "lab", views=3, name="lab-three.toml")
    config_path().parent.mkdir(parents=True)
    config_path().write_text(f'profile_dirs = ["{tmp_path / "lab"}"]\n')
    session = Session(pm=pm, out_dir="runs")  # no profile: the picker opens at start
    with served(session, poll_s=0.1) as server:
        app = app_for(server)
        async with running(app, (80, 24)) as pilot:
            await pilot.pause()
            assert isinstance(app.screen, ProfilePicker)
            assert app.screen.paths[:2] == ["lab/lab-three.toml", "profiles/four.toml"]
            assert "sim-metal-cylinder" in app.screen.paths[2:]  # the shipped ones, by name
            await pilot.press("down", "enter")
            await settle(pilot)
            await wait_until(pilot, lambda: app.session.profile is not None)
            assert session.profile is not None and len(session.profile.angles_deg()) == 4
            await wait_until(pilot, lambda: "sim-turntable" in static_text(app, "#rig-table"))
            assert "sim-metal-cylinder" in app.sub_title

            await pilot.press("ctrl+g")
            await settle(pilot)
            await wait_until(pilot, lambda: isinstance(app.screen, PluginsScreen))
            table = app.screen.query_one("DataTable")
            rows = app.screen.rows
            assert table.row_count == len(rows) > 0
            assert ["camera", "sim-camera"] in [r[:2] for r in rows]
            await pilot.press("escape")
            await pilot.pause()
            assert not isinstance(app.screen, PluginsScreen)
    session.close()


async def test_log_filters_by_level(server):
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        server.session.bus.warn("lens cap still on?")
        server.session.bus.info("hello")
        await pilot.press("space")  # snap before connect: an error, shown in place and logged
        await settle(pilot)
        assert "not connected" in static_text(app, "#rig-error")
        log = app.panel(LogPanel)
        await wait_until(pilot, lambda: {"warning", "info", "error"} <= {e.level for e in log.visible_entries()})
        await show_tab(pilot, "log")
        await pilot.press("l", "l")  # info → warning → error
        await pilot.pause()
        assert log.min_level == "error" and log.query_one("Select").value == "error"
        assert {e.level for e in log.visible_entries()} == {"error"}
        await pilot.pause()
        shown = "".join(strip.text for strip in log.query_one("#log-view").lines)
        assert "connect the rig first" in shown
        assert "lens cap" not in shown and "hello" not in shown
        log.set_level("debug")
        assert len(log.visible_entries()) == len(log.entries)

        # Scan progress and log lines while the Rig tab is shown lay the screen out not once
        # (the Scan and Log tabs and, at 80 columns, the sidebar are hidden); the Scan tab shows
        # the latest progress from the first layout that shows it on, the Log tab every line it
        # missed (also having been shown before at that width)
        await show_tab(pilot, "rig")
        view = log.query_one("#log-view", ReflowLog)
        frames_shown = []  # the frames count the Scan tab shows at each layout
        lay_out = app.screen._refresh_layout

        def counted(*args, **kwargs):
            frames_shown.append(static_text(app, "#frames-count"))
            return lay_out(*args, **kwargs)

        app.screen._refresh_layout = counted
        events = [ScanStarted(run_dir="runs/x", profile="p", n_views=2, frames_per_view=3)]
        events += [FrameCaptured(view=0, index=i, name=f"f{i}") for i in range(3)]
        events += [Message(level="warning", text=f"note {i}") for i in range(3)]
        entries = len(log.entries)
        for ev in events:
            app.post_message(ServerMessage({"type": "event", "event": ev.to_dict()}))
        await wait_until(pilot, lambda: len(log.entries) == entries + len(events))
        await pilot.pause()
        assert frames_shown == []
        await show_tab(pilot, "scan")
        assert frames_shown and set(frames_shown) == {"3/6"}
        await show_tab(pilot, "log")
        await wait_until(pilot, lambda: view.unwritten == 0)
        shown = [strip.text.rstrip() for strip in view.lines]
        assert [line[9:] for line in shown[-3:]] == [f"warning note {i}" for i in range(3)]
        assert sum("scan started" in line for line in shown) == 1


def write_png(server):
    path = server.session.out_dir / "gray.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.tile(np.arange(256, dtype=np.uint8), (64, 1))).save(path)
    return path
