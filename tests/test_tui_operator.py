"""The person at the rig (issue 29): the stop key never aborts, abort always asks and is the
controller's, the end-of-scan previews show, a reattached console tells its true state, the
Scan tab's settings are the scan's, and the smaller things an operator trips over. Driven with
Textual's Pilot against a real rig server on the simulated rig, like tests/test_tui.py."""

import os
import re
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
import textual.constants
from PIL import Image
from rich.color import Color as RichColor
from rich.color import ColorSystem
from textual import events
from textual.color import Color
from textual.command import CommandPalette
from textual.filter import Monochrome, NoColor
from textual.keys import _character_to_key
from textual.widgets import Input
from textual.widgets._footer import FooterKey
from textual.widgets._toast import Toast

from conftest import write_test_profile
from dotshell.cli.server import apply_out_dir
from dotshell.session.console import Session
from dotshell.run.generations import link_top_level, point_current
from dotshell.server import repl
from dotshell.tui.widgets.confirm import ConfirmScreen
from dotshell.tui.widgets.console_input import ConsoleInput
from dotshell.tui.widgets.console_panel import STYLES as CONSOLE_STYLES
from dotshell.tui.widgets.console_panel import ConsolePanel
from dotshell.tui.widgets.keys_footer import KeyRow
from dotshell.tui.widgets.keys_screen import KeysScreen
from dotshell.tui.widgets.log_panel import LEVEL_STYLE as LOG_STYLES
from dotshell.tui.widgets.log_panel import LogPanel
from dotshell.tui.widgets.preview_panel import PreviewPanel
from dotshell.tui.widgets.prompt import PromptScreen
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
            # under a dialog (the keys overlay) x and p do nothing
            await pilot.press("question_mark")
            await wait_until(pilot, lambda: isinstance(mine.screen, KeysScreen))
            await pilot.press("x", "p")
            await settle(pilot)
            assert isinstance(mine.screen, KeysScreen) and session.state == "running"
            await pilot.press("escape")
            await wait_until(pilot, lambda: not isinstance(mine.screen, KeysScreen))
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


async def test_the_preview_after_a_server_scan_shows_the_cloud(tmp_path, pm, monkeypatch,
                                                               truecolor, user_dirs):
    """The bug: the live frame preview made RUN/previews a real folder, so the link to the
    current generation's previews was never made and the Preview tab said "cannot read preview
    …/previews/cloud.png" after every server scan."""
    monkeypatch.chdir(tmp_path)
    session = Session(write_test_profile(tmp_path, previews=True), pm=pm, out_dir="runs")
    with served(session, poll_s=0.1) as server:
        await preview_after_scan(server, session)
    session.close()


async def preview_after_scan(server, session):
    app = app_for(server)
    async with running(app, (100, 30)) as pilot:
        await show_tab(pilot, "scan")
        await scan_to_the_end(pilot, session)
        await wait_until(pilot, lambda: any(i.kind == "cloud" for i in app.panel(
            PreviewPanel).items) or "cannot read" in static_text(app, "#preview-title"))
        await show_tab(pilot, "preview")
        assert "cannot read" not in static_text(app, "#preview-title")
        run = session.run
        assert run.status == "completed"
        link = run.root / "previews"
        assert link.is_symlink() and os.readlink(link) == "current/previews"
        cloud = next(i for i in app.panel(PreviewPanel).items if i.kind == "cloud")
        assert Path(cloud.path) == (run.root / "current").resolve() / "previews" / "cloud.png"
        with Image.open(link / "cloud.png") as im:
            assert cloud.size == im.size
            pixels = np.asarray(im.convert("L"))
        assert pixels.std() > 5  # a rendering of the cloud, not a blank image
        assert np.asarray(cloud.image.convert("L")).std() > 5
        assert "cloud" in static_text(app, "#preview-title")
        assert (run.root / "live" / "latest_frame.png").is_file()


async def test_a_reattached_console_shows_its_transcript_and_that_it_is_busy(server):
    """The bug: a console reattached while its scan() ran said "ready", showed nothing of what
    came before, and threw away what was typed."""
    session = server.session
    gate = Gate(session, 0, 1)
    first = attach(server)
    first.console_run("print('before the scan', 6 * 7)")
    wait_for_idle_console(server)
    first.console_run("connect(); r = scan()")
    assert gate.reached.wait(60)
    first.close()  # the terminal that started it is gone; the scan goes on
    try:
        app = app_for(server)
        async with running(app, (100, 30)) as pilot:
            await show_tab(pilot, "console")
            panel = app.panel(ConsolePanel)
            shown = panel.output_text
            assert "before the scan 42" in shown and "connect(); r = scan()\n" in shown
            assert panel.busy
            assert "running" in static_text(app, "#console-status")
            box = app.panel(ConsoleInput)
            box.text = "1 + 1"
            box.move_cursor(box.document.end)
            await pilot.press("enter")
            await settle(pilot)
            assert box.text == "1 + 1"  # kept, not sent, and said so
            assert "not run" in static_text(app, "#console-status")
            assert session.state == "running"
            gate.opened.set()
            await wait_until(pilot, lambda: not panel.busy, timeout_s=120)
            assert session.run.status == "completed"
            assert "ready" in static_text(app, "#console-status")
            await pilot.press("enter")
            await wait_until(pilot, lambda: panel.output_text.rstrip().endswith("2"))
    finally:
        gate.opened.set()


def wait_for_idle_console(server, timeout_s=60.0):
    t0 = time.monotonic()
    while server.console.busy:
        assert time.monotonic() - t0 < timeout_s
        time.sleep(0.02)


async def test_the_console_transcript_is_bounded(server, monkeypatch):
    monkeypatch.setattr(repl, "TRANSCRIPT_CHARS", 1000)
    client = attach(server)
    client.console_run("for i in range(300): print(f'line {i:04d}')")
    wait_for_idle_console(server)
    client.close()
    late = attach(server, "late", control=False)
    try:
        text = "".join(m.get("text", "") for m in late.console_transcript)
        assert len(text) <= 1000 and "line 0299" in text and "line 0000" not in text
        assert late.console_transcript[-1]["type"] == "console_done"
    finally:
        late.close()


async def answer(pilot, key, value):
    """Press ``key`` and answer its prompt with ``value``."""
    await pilot.press(key)
    await wait_until(pilot, lambda: isinstance(pilot.app.screen, PromptScreen))
    pilot.app.screen.query_one(Input).value = value
    await pilot.press("enter")
    await settle(pilot)


async def scan_to_the_end(pilot, session):
    """``s`` on the Scan tab, then wait until the scan has ended."""
    await pilot.press("s")
    await wait_until(pilot, lambda: pilot.app.tracker.status in ("completed", "aborted",
                                                                  "failed"), timeout_s=120)
    await wait_until(pilot, lambda: not session.scanning)


async def test_the_scan_tab_edits_the_settings_the_scan_uses(server, tmp_path):
    """The bug: exposure set with e was not what the scan used (it used the profile's), and
    views, exposure and the output folder could only be changed with set(...)."""
    session = server.session
    app = app_for(server)
    async with running(app, (100, 30)) as pilot:
        await show_tab(pilot, "scan")
        for key, value in (("v", "3"), ("e", "7.5"), ("n", "10, 100"), ("o", "elsewhere")):
            await answer(pilot, key, value)
        await answer(pilot, "v", "three")
        assert "views: 'three' is not a whole number" in static_text(app, "#scan-error")
        await wait_until(pilot, lambda: "3 views, exposure 7.5 ms" in static_text(
            app, "#scan-plan") and "elsewhere/" in static_text(app, "#scan-plan"))
        await scan_to_the_end(pilot, session)
    run = session.run
    assert run.status == "completed" and run.root.parent == tmp_path / "elsewhere"
    assert len(run.manifest["views"]) == 3
    recorded = tomllib.loads((run.root / "profile.toml").read_text())["scan"]
    assert recorded["exposure_ms"] == 7.5 and recorded["pdi_angles_deg"] == [10.0, 100.0]
    assert session.rig.camera.status()["exposure_ms"] == 7.5  # what the camera took


async def test_e_on_the_rig_tab_is_the_exposure_the_scan_uses(server):
    session = server.session
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        await answer(pilot, "e", "3.25")
        assert session.rig.camera.status()["exposure_ms"] == 3.25
        assert session.profile.data["scan"]["exposure_ms"] == 3.25
        assert session.connected  # the rig was kept, not rebuilt
        await show_tab(pilot, "scan")
        await scan_to_the_end(pilot, session)
    recorded = tomllib.loads((session.run.root / "profile.toml").read_text())["scan"]
    assert recorded["exposure_ms"] == 3.25


async def test_out_for_a_running_server_is_applied_or_said(server, tmp_path):
    """`dotshell tui PROFILE --out DIR` attaching to a running server ignored --out silently."""
    first = attach(server)
    watcher = attach(server, "tui", control=True)  # first controls: this one watches
    try:
        said = apply_out_dir(watcher, str(tmp_path / "mine"))
        assert "NOT applied" in said and "controls the rig" in said
        assert Path(server.session.out_dir).resolve() != tmp_path / "mine"
        said = apply_out_dir(first, str(tmp_path / "mine"))
        assert said == f"output folder changed to {tmp_path / 'mine'} as asked with --out"
        assert server.session.out_dir.resolve() == tmp_path / "mine"
    finally:
        watcher.close()
        first.close()


# ---- the smaller things ----------------------------------------------------------------------

async def test_keys_overlay_scrolls_at_once_and_keys_mean_one_thing(server):
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.press("question_mark")
        await wait_until(pilot, lambda: isinstance(app.screen, KeysScreen))
        box = app.screen.query_one("#keys")
        await wait_until(pilot, lambda: box.max_scroll_y > 0)  # more keys than lines
        await pilot.press("pagedown")  # the bug: nothing scrolled until Tab
        await wait_until(pilot, lambda: box.scroll_y > 0)
        meaning = {}
        for where, rows in app.key_sections():
            if where == "Console":  # keys typed into the console's input box
                continue
            for keys, what in rows:
                for key in keys.split():
                    assert meaning.setdefault(key, what) == what, \
                        f"{key} is {meaning[key]!r} and {what!r} ({where})"


async def test_the_footer_keeps_the_stop_key_at_80x24(server):
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        for tab in TABS:
            await show_tab(pilot, tab)
            await pilot.pause()
            keys = [k for row in app.query(KeyRow) if row.display for k in row.query(FooterKey)]
            stop = next(k for k in keys if k.action == "stop")
            palette = next(k for k in keys if "-command-palette" in k.classes)
            assert stop.region.right <= palette.region.x and stop.region.width > 0, tab


async def test_notifications_leave_the_console_input_visible(server):
    app = app_for(server)
    async with app.run_test(size=(80, 24), notifications=True) as pilot:
        await wait_until(pilot, lambda: app.focused is not None)
        await show_tab(pilot, "console")
        app.notify("a notice that would have covered the input " * 3, timeout=30)
        await wait_until(pilot, lambda: len(app.screen.query(Toast)) > 0)
        await pilot.pause()
        box = app.panel(ConsoleInput).region
        for toast in app.screen.query(Toast):
            assert not toast.region.overlaps(box), (toast.region, box)
        await show_tab(pilot, "scan")  # elsewhere they keep off the scan's counts
        await pilot.pause()
        counts = [app.screen.query_one(s).region for s in ("#views-count", "#frames-count",
                                                           "#scan-state")]
        for toast in app.screen.query(Toast):
            assert not any(toast.region.overlaps(r) for r in counts), (toast.region, counts)


async def test_empty_enter_adds_nothing_and_a_paste_keeps_its_indentation(server):
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await show_tab(pilot, "console")
        box, panel = app.panel(ConsoleInput), app.panel(ConsolePanel)
        before = len(panel.transcript)
        await pilot.press("enter", "enter", "enter")
        await settle(pilot)
        assert box.text == "" and len(panel.transcript) == before  # nothing sent, no newline
        # a paste without bracketed paste: keys in one burst (as a terminal sends them)
        source = ("total = 0\nfor i in range(3):\n    if i:\n        total += i\n"
                  "    total += 10\nprint('total', total)\n")
        for ch in source:
            key = "enter" if ch == "\n" else _character_to_key(ch)
            box.post_message(events.Key(key, None if ch == "\n" else ch))
        await wait_until(pilot, lambda: box.text == source)  # not run midway, not re-indented
        await pilot.press("enter")
        await wait_until(pilot, lambda: "total 33" in panel.output_text)
        assert "Error" not in panel.output_text


async def test_no_color_marks_errors_without_greying_them(server, monkeypatch):
    monkeypatch.setenv("NO_COLOR", "1")
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        assert any(isinstance(f, NoColor) for f in app._filters)
        assert not any(isinstance(f, Monochrome) for f in app._filters)  # red became dark grey
        for selector in ("#rig-error", "#scan-error"):
            assert app.screen_stack[0].query_one(selector).styles.text_style.bold
        assert "bold" in LOG_STYLES["error"] and "bold" in CONSOLE_STYLES["error"]
        await pilot.pause()


async def test_sixteen_colours_keep_headings_apart_from_errors(server, monkeypatch):
    monkeypatch.setattr(textual.constants, "COLOR_SYSTEM", "standard")
    app = app_for(server)
    async with running(app, (120, 40)) as pilot:
        await pilot.pause()
        assert app.theme == "dotshell-16"

        def ansi(color):
            return RichColor.parse(color.hex[:7]).downgrade(ColorSystem.STANDARD).number

        title = app.screen_stack[0].query(".summary-title").first()
        error = app.screen_stack[0].query_one("#rig-error")
        numbers = {"heading": ansi(title.styles.color), "error": ansi(error.styles.color),
                   "warning": ansi(Color.parse(app.theme_variables["warning"])),
                   "footer key": ansi(Color.parse(app.theme_variables["footer-key-foreground"]))}
        assert len({numbers["heading"], numbers["error"], numbers["warning"]}) == 3, numbers
        assert numbers["footer key"] != numbers["error"], numbers


async def test_a_dark_snap_says_why_and_lines_and_output_can_be_copied(server):
    session = server.session
    app = app_for(server)
    async with running(app, (100, 30)) as pilot:
        await pilot.press("c")
        await settle(pilot)
        await pilot.press("space")
        await settle(pilot)
        await wait_until(pilot, lambda: "snap at" in static_text(app, "#rig-result"))
        assert "shows no pattern" in static_text(app, "#rig-result")
        session.project("white")
        await wait_until(pilot, lambda: app.session.projected == "white")
        await pilot.press("space")
        await settle(pilot)
        await wait_until(pilot, lambda: "snap at" in static_text(app, "#rig-result"))
        assert "no pattern" not in static_text(app, "#rig-result")
        # the Log tab: y copies the newest line shown, Y every line shown
        await show_tab(pilot, "log")
        log = app.panel(LogPanel)
        await pilot.press("y")
        await pilot.pause()
        assert app.clipboard == log.plain(log.visible_entries()[-1]) + "\n"
        await pilot.press("Y")
        await pilot.pause()
        assert app.clipboard.splitlines() == [log.plain(e) for e in log.visible_entries()]
        # the console: ctrl+y copies the last input's output
        await show_tab(pilot, "console")
        box = app.panel(ConsoleInput)
        box.text = "print('copy me'); 6 * 7"
        box.move_cursor(box.document.end)
        await pilot.press("enter")
        await wait_until(pilot, lambda: "42" in app.panel(ConsolePanel).output_text)
        await wait_until(pilot, lambda: not app.panel(ConsolePanel).busy)
        await pilot.press("ctrl+y")
        await pilot.pause()
        assert app.clipboard == "copy me\n42\n"


# ---- docs/tui.md ---------------------------------------------------------------------------------

def documented_keys() -> set[tuple[str, str]]:
    """(where, key) of every row of docs/tui.md's keys table (keys: the backticked words of its
    first column, ``ctrl+x`` written as the app shows it, ``^x``)."""
    text = (Path(__file__).parent.parent / "docs" / "tui.md").read_text(encoding="utf-8")
    table = text[text.index("| key | where | what |"):]
    table = table[:table.index("\n\n")]
    rows = set()
    for line in table.splitlines()[2:]:
        key_cell, where, what = [c.strip() for c in line.strip("|").split("|")][:3]
        for key in re.findall(r"`([^`]+)`", key_cell):
            rows.add((where, re.sub(r"^ctrl\+", "^", key), what.lower()))
    return rows


async def test_the_docs_keys_table_matches_the_app(server):
    app = app_for(server)
    async with running(app, (80, 24)) as pilot:
        await pilot.pause()
        in_app = {(where, key, what) for where, rows in app.key_sections()
                  for keys, what in rows for key in keys.split()}
    docs = documented_keys()
    assert {(w, k) for w, k, _ in in_app} == {(w, k) for w, k, _ in docs}
    # and each row says what the key does in the app's own first word
    said = {(w, k): what for w, k, what in docs}
    for where, key, what in in_app:
        word = re.split(r"[ /]", what.lower())[0]
        assert word in said[where, key], f"{where} {key}: {what!r} vs docs {said[where, key]!r}"


async def test_a_run_with_the_old_live_preview_folder_gets_its_previews_link(tmp_path):
    """Runs served before RUN/live/ hold latest_frame.png in a real previews/ folder: the next
    publication moves it to live/ and makes the link."""
    root = tmp_path / "run"
    (root / "previews").mkdir(parents=True)
    (root / "previews" / "latest_frame.png").write_bytes(b"frame")
    gen = root / "gen" / "002"
    (gen / "previews").mkdir(parents=True)
    (gen / "previews" / "cloud.png").write_bytes(b"cloud")
    point_current(root, 2)
    link_top_level(root, gen)
    assert os.readlink(root / "previews") == "current/previews"
    assert (root / "previews" / "cloud.png").read_bytes() == b"cloud"
    assert (root / "live" / "latest_frame.png").read_bytes() == b"frame"
    # a previews/ folder with someone's own files is left alone
    other = tmp_path / "other"
    (other / "previews").mkdir(parents=True)
    (other / "previews" / "notes.txt").write_text("mine")
    link_top_level(other, gen)
    assert not (other / "previews").is_symlink()
    assert (other / "previews" / "notes.txt").read_text() == "mine"
