"""The Textual UI driven by Textual's Pilot on the simulated rig: every test asserts on the
session, the run directory and what the panels show — not just that nothing crashed."""

import io
import threading
import time

import numpy as np
import pytest
from PIL import Image
from rich.console import Console
from textual.content import Content

from conftest import write_test_profile
from dotshell.console import Session
from dotshell.events import FrameCaptured
from dotshell.store import RunStore
from dotshell.tui.app import DotshellApp
from dotshell.tui.widgets.choice import ChoiceScreen
from dotshell.tui.widgets.confirm import ConfirmScreen
from dotshell.tui.widgets.console_input import ConsoleInput
from dotshell.tui.widgets.console_panel import ConsolePanel
from dotshell.tui.widgets.log_panel import LogPanel
from dotshell.tui.widgets.plugins_screen import PluginsScreen, backend_rows
from dotshell.tui.widgets.preview_panel import PreviewPanel
from dotshell.tui.widgets.profile_picker import ProfilePicker
from dotshell.tui.widgets.scan_panel import ScanPanel

pytestmark = pytest.mark.asyncio


@pytest.fixture
def session(tmp_path, pm, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = Session(write_test_profile(tmp_path), pm=pm, out_dir="runs")
    yield s
    s.close()


async def settle(pilot):
    """Let every running worker finish and the UI process what they posted."""
    await wait_until(pilot, lambda: all(w.is_finished or w.group == "scan"
                                        for w in pilot.app.workers))
    await pilot.pause()
    await pilot.pause()


async def show_tab(pilot, tab):
    await pilot.pause()  # the tabs take their initial state first
    pilot.app.action_show_tab(tab)
    await pilot.pause()
    await pilot.pause()


async def wait_until(pilot, condition, timeout_s=60.0):
    t0 = time.monotonic()
    while not condition():
        assert time.monotonic() - t0 < timeout_s, "timed out waiting for the UI"
        await pilot.pause(0.05)


def static_text(app, selector):
    """The plain text a widget on the main screen shows (Textual content or a Rich table)."""
    content = app.screen_stack[0].query_one(selector).content
    if isinstance(content, str):
        return Content.from_markup(content).plain
    if hasattr(content, "plain"):
        return content.plain
    console = Console(width=200, record=True, file=io.StringIO())
    console.print(content)
    return console.export_text()


async def test_connect_jog_snap_from_the_rig_panel(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        assert session.connected
        assert "connected" in static_text(app, "#rig-table")

        await pilot.press("right", "right", "left")  # 3 jogs of the 5° step: net +5°
        await settle(pilot)
        assert session.rig.stage.position == pytest.approx(5.0)
        await pilot.press("plus")  # step 10°
        await pilot.press("right")
        await settle(pilot)
        assert session.rig.stage.position == pytest.approx(15.0)
        app.refresh_status()
        await settle(pilot)
        assert "angle 15.00°" in static_text(app, "#rig-table")

        await pilot.press("space")
        await settle(pilot)
        snaps = sorted((session.out_dir / "snapshots").glob("snap_*.png"))
        assert [p.name for p in snaps] == ["snap_0001.png", "snap_0001_preview.png"]
        raw = np.asarray(Image.open(snaps[0]))
        w, h = session.rig.camera.resolution
        assert raw.shape == (h, w) and raw.dtype == np.uint16
        assert "snapshots/snap_0001.png" in static_text(app, "#rig-result")
        # the preview pane shows the snapshot and names its PNG
        preview = app.panel(PreviewPanel)
        assert preview.current.kind == "snap"
        assert preview.current.path.endswith("snap_0001_preview.png")
        assert preview.current.image.size == (w, h)
        assert "snap_0001_preview.png" in static_text(app, "#preview-title")


async def test_project_a_chosen_pattern_and_set_exposure(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        await pilot.press("p")
        await pilot.pause()
        assert isinstance(app.screen, ChoiceScreen)
        await pilot.press("enter")  # the first pattern: "white"
        await settle(pilot)
        assert session.projected == session.patterns()[0] == "white"
        await pilot.press("e")
        await pilot.pause()
        app.screen.query_one("Input").value = "7.5"
        await pilot.press("enter")
        await settle(pilot)
        assert session.rig.camera.status()["exposure_ms"] == 7.5
        await pilot.press("space")
        await settle(pilot)
        white = np.asarray(Image.open(session.out_dir / "snapshots" / "snap_0001.png"))
        session.project("black")
        dark = session.snap().frame
        assert white.mean() > 5 * dark.mean()  # the projected pattern lights the scene


async def test_short_scan_runs_to_the_end(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await show_tab(pilot, "scan")
        assert app.focused is app.panel(ScanPanel)
        await pilot.press("s")
        await wait_until(pilot, lambda: app.tracker.status in ("completed", "aborted", "failed"))
        await wait_until(pilot, lambda: not session.scanning)
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
        # the latest frame of each view was previewed, saved in the run
        preview = app.panel(PreviewPanel)
        assert [i.view for i in preview.items if i.kind == "frame"] == [0, 1]
        assert (run.root / "previews" / "latest_frame.png").is_file()
        # the log has the run's events
        texts = [e.text for e in app.panel(LogPanel).entries]
        assert any(t.startswith("scan completed") for t in texts)


class Gate:
    """Holds the scan thread right after frame ``index`` of ``view`` is captured until the test
    opens it, so keys pressed meanwhile land at a known point of the scan, however busy the
    machine is."""

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


async def test_pause_resume_then_abort_midway_keeps_frames(tmp_path, pm, monkeypatch):
    monkeypatch.chdir(tmp_path)
    session = Session(write_test_profile(tmp_path, views=3), pm=pm, out_dir="runs")
    first, second = Gate(session, 0, 2), Gate(session, 1, 4)
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await show_tab(pilot, "scan")
        await pilot.press("s")
        await first.wait(pilot)
        await pilot.press("p")
        assert session.state == "paused"
        first.opened.set()  # the scan goes on to the next frame boundary and waits there
        await wait_until(pilot, lambda: app.tracker.status == "paused")
        assert app.tracker.frames_done == 3
        await pilot.pause(0.3)
        assert app.tracker.frames_done == 3  # nothing is captured while paused
        assert "paused" in static_text(app, "#scan-state")
        await pilot.press("p")
        assert session.state == "running"
        await second.wait(pilot)
        await pilot.press("p")  # pause again, then abort from the pause
        second.opened.set()
        await wait_until(pilot, lambda: app.tracker.status == "paused")
        await pilot.press("x")
        await wait_until(pilot, lambda: not session.scanning)
        await settle(pilot)
        run = session.run
        assert run.status == "aborted" and app.tracker.status == "aborted"
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
        assert "aborted" in static_text(app, "#scan-state")
    session.close()


async def test_console_evaluates_against_the_live_session(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        assert app.focused is box
        panel = app.panel(ConsolePanel)

        async def enter(source):
            box.text = source
            box.move_cursor(box.document.end)
            await pilot.press("enter")
            await settle(pilot)

        await enter("connect(); jog(30)")
        assert session.rig.stage.position == pytest.approx(30.0)
        await pilot.press(*"rig.stage.position")  # typed key by key
        await pilot.press("enter")
        await settle(pilot)
        assert panel.transcript[-1] == ("result", "30.0")
        await enter("for a in (40, 50):\n    move_to(a)\n")  # a block, ended by a blank line
        assert session.rig.stage.position == pytest.approx(50.0)
        await enter("frame = snap().frame\nframe.shape")
        w, h = session.rig.camera.resolution
        assert panel.transcript[-1] == ("result", repr((h, w)))
        await enter("print('mean', int(frame.mean() > 0), np.pi > 3)")
        assert "mean 1 True\n" in panel.output_text
        await pilot.press("up")  # history: the last input comes back
        assert box.text.startswith("print('mean'")


async def test_console_errors_show_the_traceback_and_the_app_lives_on(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        panel = app.panel(ConsolePanel)
        for source in ("def broken():\n    return 1 / 0\n", "broken()", "def f(:",
                       "jog(5)"):  # jog before connect: a DeviceError with the fix
            box.text = source
            box.move_cursor(box.document.end)
            await pilot.press("enter")
            await settle(pilot)
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
        assert "connect the rig first" in shown
        # the app lives on: the console and the rig still work
        box.text = "connect(); jog(5)"
        await pilot.press("enter")
        await settle(pilot)
        assert session.rig.stage.position == pytest.approx(5.0)
        assert app.is_running


async def test_console_interrupts_a_long_call(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        panel = app.panel(ConsolePanel)
        box.text = "n = 0\nwhile True:\n    n += 1\n"
        box.move_cursor(box.document.end)
        await pilot.press("enter")
        await wait_until(pilot, lambda: panel.interpreter.namespace.get("n", 0) > 1000)
        assert panel.busy
        await pilot.press("ctrl+c")
        await settle(pilot)
        assert not panel.busy
        assert panel.transcript[-1][0] == "error" and "KeyboardInterrupt" in panel.transcript[-1][1]
        box.text = "n > 1000"
        await pilot.press("enter")
        await settle(pilot)
        assert panel.transcript[-1] == ("result", "True")


async def test_quitting_during_a_scan_asks_then_stops_it_keeping_frames(session):
    gate = Gate(session, 0, 2)
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await show_tab(pilot, "scan")
        await pilot.press("s")
        await gate.wait(pilot)
        await pilot.press("ctrl+q")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen)
        await pilot.press("n")
        await pilot.pause()
        assert session.state == "running" and app.is_running  # "no" keeps scanning
        await pilot.press("ctrl+q")
        await pilot.pause()
        await pilot.press("y")
        await pilot.pause()
        assert session.state == "stopping"
        gate.opened.set()
        await wait_until(pilot, lambda: not app.is_running)
    run = session.run
    assert run.status == "aborted"
    assert run.frame_count() == 3  # frames 0..2 of view 0, all kept
    assert not session.scanning and not session.rig.connected


async def test_profile_picker_loads_a_profile_and_plugins_screen_lists_backends(
        tmp_path, pm, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "profiles").mkdir()
    write_test_profile(tmp_path / "profiles", views=4, name="four.toml")
    session = Session(pm=pm, out_dir="runs")  # no profile: the picker opens at start
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.pause()
        assert isinstance(app.screen, ProfilePicker)
        assert app.screen.paths == ["profiles/four.toml"]
        await pilot.press("enter")
        await settle(pilot)
        assert session.profile is not None and len(session.profile.angles_deg()) == 4
        assert "profiles/four.toml" in app.sub_title
        assert "sim-turntable" in static_text(app, "#rig-table")

        await pilot.press("ctrl+g")
        await pilot.pause()
        assert isinstance(app.screen, PluginsScreen)
        table = app.screen.query_one("DataTable")
        rows = backend_rows(pm)
        assert table.row_count == len(rows) > 0
        assert ("camera", "sim-camera") in {(r[0], r[1]) for r in rows}
        await pilot.press("escape")
        await pilot.pause()
        assert not isinstance(app.screen, PluginsScreen)
    session.close()


async def test_log_filters_by_level(session):
    app = DotshellApp(session)
    async with app.run_test(size=(80, 24)) as pilot:
        session.bus.warn("lens cap still on?")
        session.bus.info("hello")
        await pilot.press("space")  # snap before connect: an error, shown in place and logged
        await settle(pilot)
        assert "not connected" in static_text(app, "#rig-error")
        log = app.panel(LogPanel)
        assert {"warning", "info", "error"} <= {e.level for e in log.visible()}
        await show_tab(pilot, "log")
        await pilot.press("l", "l")  # info → warning → error
        await pilot.pause()
        assert log.min_level == "error" and log.query_one("Select").value == "error"
        assert {e.level for e in log.visible()} == {"error"}
        shown = "".join(strip.text for strip in log.query_one("#log-view").lines)
        assert "connect the rig first" in shown
        assert "lens cap" not in shown and "hello" not in shown
        log.set_level("debug")
        assert len(log.visible()) == len(log.entries)
