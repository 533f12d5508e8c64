"""The person at the rig (issue 29): the stop key never aborts, abort always asks and is the
controller's, the end-of-scan previews show, a reattached console tells its true state, the
Scan tab's settings are the scan's, and the smaller things an operator trips over. Driven with
Textual's Pilot against a real rig server on the simulated rig, like tests/test_tui.py."""

import pytest
from textual.command import CommandPalette

from dotshell.tui.widgets.confirm import ConfirmScreen
from dotshell.tui.widgets.scan_panel import ScanPanel
from rig_server import attach, served, user_dirs  # noqa: F401 (a fixture)
from test_tui import (Gate, app_for, running, server, settle, show_tab,  # noqa: F401
                      static_text, truecolor, wait_until)

pytestmark = pytest.mark.asyncio

TABS = ("rig", "scan", "preview", "log", "console")


async def escape_on_every_tab(pilot, session):
    """Press escape on each tab; a scan it pauses is resumed. Returns the states seen."""
    seen = []
    for tab in TABS:
        await show_tab(pilot, tab)
        await pilot.press("escape")
        await settle(pilot)
        seen.append(session.state)
        assert session.state in ("running", "paused"), f"escape on {tab}: {session.state}"
        session.resume()
    return seen


async def test_escape_from_any_tab_and_any_client_never_aborts(server):
    """The bug: one escape on the Rig tab, also from a watching client, aborted a young scan.
    Now escape pauses it before its next frame (motion stops, nothing is lost) and the scan,
    resumed, completes."""
    session = server.session
    gate = Gate(session, 0, 1)
    controller = attach(server)
    controller.scan()
    try:
        assert gate.reached.wait(60)  # no app runs yet: blocking here holds nothing up
        watcher = app_for(server)
        async with running(watcher, (80, 24)) as pilot:
            await wait_until(pilot, lambda: watcher.session.scanning)
            assert not watcher.session.in_control
            seen = await escape_on_every_tab(pilot, session)
            assert seen == ["paused"] * 5  # the stop key works for a watcher: it pauses
            # a watcher cannot abort: x says so, and the server refuses the request itself
            await show_tab(pilot, "scan")
            await pilot.press("x")
            await settle(pilot)
            assert not isinstance(watcher.screen, ConfirmScreen)
            assert "only the front end in control" in static_text(watcher, "#scan-error")
            with pytest.raises(Exception, match="controls the rig"):
                watcher.session.abort()
            assert session.state == "running"
        controller.close()
        mine = app_for(server)
        async with running(mine, (80, 24)) as pilot:
            assert mine.session.in_control
            assert await escape_on_every_tab(pilot, session) == ["paused"] * 5
            # x asks first on every tab but the console (where it is text), however young the
            # scan; no, n and escape keep scanning
            for tab, answer in (("rig", "n"), ("scan", "escape"), ("preview", "n"),
                                ("log", "escape")):
                await show_tab(pilot, tab)
                await pilot.press("x")
                await wait_until(pilot, lambda: isinstance(mine.screen, ConfirmScreen))
                await pilot.press(answer)
                await settle(pilot)
                assert session.state == "running"
            # the palette: Enter on the opened palette never aborts; searched for, it asks
            await pilot.press("ctrl+p")
            await wait_until(pilot, lambda: isinstance(mine.screen, CommandPalette))
            palette = mine.screen
            await wait_until(pilot, lambda: palette.query_one("CommandList").option_count > 0)
            listed = [str(palette.query_one("CommandList").get_option_at_index(i).prompt)
                      for i in range(palette.query_one("CommandList").option_count)]
            assert not any("Abort" in p for p in listed)
            await pilot.press(*"abort the scan")
            await wait_until(pilot, lambda: any(
                "Abort" in str(palette.query_one("CommandList").get_option_at_index(i).prompt)
                for i in range(palette.query_one("CommandList").option_count)))
            await pilot.press("enter")
            await wait_until(pilot, lambda: isinstance(mine.screen, ConfirmScreen))
            await pilot.press("n")
            await settle(pilot)
            assert session.state == "running"
            gate.opened.set()
            await wait_until(pilot, lambda: not session.scanning, timeout_s=120)
        assert session.run.status == "completed"
    finally:
        gate.opened.set()


async def test_abort_asks_then_ends_the_scan_with_frames_kept(server):
    session = server.session
    gate = Gate(session, 0, 1)
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "scan")
        await pilot.press("s")
        await gate.wait(pilot)
        await wait_until(pilot, lambda: app.session.scanning)
        await pilot.press("x")
        await wait_until(pilot, lambda: isinstance(app.screen, ConfirmScreen))
        await pilot.press("y")
        await wait_until(pilot, lambda: session.state in ("stopping", "idle"))
        gate.opened.set()
        await wait_until(pilot, lambda: not session.scanning, timeout_s=120)
        assert session.run.status == "aborted" and session.run.frame_count() == 2
        await wait_until(pilot, lambda: "aborted" in static_text(app, "#scan-state"))
        assert isinstance(app.panel(ScanPanel), ScanPanel)
