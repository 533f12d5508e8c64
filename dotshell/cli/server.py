"""The rig server's commands: ``dotshell serve``, ``tui``, ``attach``, ``status``, ``stop`` and
``scan --detach`` (docs/server.md). Each is a thin client of :mod:`dotshell.server`."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape

from dotshell.errors import DotshellError
from dotshell.events import Event, ScanFinished, ViewCaptured
from dotshell.server.describe import LEVELS, describe_event
from dotshell.runtime.paths import HANGUP_CHOICES, alive, server_name, socket_path, user_config
from dotshell.server.progress import ScanTracker, format_seconds
from dotshell.server.protocol import ServerError, event_from_wire

out = Console(highlight=False, soft_wrap=True)
err = Console(stderr=True, highlight=False, soft_wrap=True)

NO_TTY_HINT = ("dotshell tui needs a terminal (its stdin and stdout must be a TTY). Over SSH "
               "use ssh -t HOST dotshell tui ...; without a terminal run the scan with "
               "dotshell scan PROFILE (or dotshell scan PROFILE --detach, then dotshell "
               "attach).")


def _which(args: argparse.Namespace) -> Path | None:
    from dotshell.server.launch import locate

    return locate(getattr(args, "profile", None), args.server, args.socket)


def _require_server(args: argparse.Namespace) -> Path:
    sock = _which(args)
    if sock is None or not alive(sock):
        where = f" on {sock}" if sock else ""
        raise ServerError(f"no rig server runs{where}; start one with dotshell serve PROFILE "
                          "--detach (or dotshell tui PROFILE).")
    return sock


def _describe_progress(t: ScanTracker, now_s: float) -> str:
    text = f"views {t.views_done}/{t.n_views}, frames {t.frames_done}/{t.frames_total}"
    if t.active:
        view = f", view {t.current_view + 1}" if t.current_view >= 0 else ""
        text += (f"{view}, step {t.step or '…'}, elapsed {format_seconds(t.active_seconds(now_s))}"
                 f", ETA {t.eta_text(now_s)}")
    return text


# ---- serve ------------------------------------------------------------------------------------

def cmd_serve(args: argparse.Namespace) -> int:
    from dotshell.server.launch import start_server

    sock = Path(args.socket) if args.socket else socket_path(args.server or server_name(args.profile))
    if not sock.parent.is_dir():
        raise ServerError(f"--socket {sock}: its directory {sock.parent} does not exist; create "
                          "it (private to you: mkdir -m 700) or give a socket path in an "
                          "existing directory.")
    on_hangup = args.on_hangup or user_config()["server"]["on_hangup"]
    _refuse_a_second_server(sock)
    if args.detach:
        pid = start_server(args.profile, sock=sock, out=args.out or "runs", overrides=args.set,
                           exit_when_idle=args.exit_when_idle,
                           strict_plugins=args.strict_plugins)
        out.print(escape(f"rig server {sock.stem} started (pid {pid}) on {sock}"))
        return 0
    from dotshell.runtime.paths import history_path, server_log_dir
    from dotshell.server.server import RigServer
    from dotshell.server.supervisor import WorkerSession

    # the session (plugins, profile, rig, console) lives in a worker process (docs/server.md)
    session = WorkerSession(args.profile, out_dir=args.out or "runs", overrides=args.set,
                            strict_plugins=args.strict_plugins, history_file=history_path())
    server = RigServer(session, sock, name=sock.stem, log_dir=server_log_dir(sock.stem),
                       on_hangup=on_hangup, exit_when_idle=args.exit_when_idle,
                       history_file=history_path(), echo=True)
    server.start()
    return server.serve_forever()


def _refuse_a_second_server(sock: Path) -> None:
    """A ServerError naming the holder when a server holds ``sock``'s lock (even one that does
    not answer at the moment) or answers on it."""
    from dotshell.runtime.locks import describe, holder, server_lock_path

    info = holder(server_lock_path(sock))
    if info is not None:
        raise ServerError(f"a rig server already runs on {sock}: {describe(info)}; see "
                          "dotshell status, or stop it with dotshell stop.")
    if alive(sock):
        raise ServerError(f"a rig server already answers on {sock}; see dotshell status.")


# ---- tui --------------------------------------------------------------------------------------

def cmd_tui(args: argparse.Namespace) -> int:
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        err.print(f"[red]error:[/] {escape(NO_TTY_HINT)}", soft_wrap=True)
        return 2
    signal.signal(signal.SIGHUP, signal.SIG_DFL)  # a terminal that goes away ends the client
    from dotshell.server.client import RemoteSession
    from dotshell.server.launch import spawn_server, wait_listening

    sock = _which(args) or socket_path("default")
    starting = None
    if alive(sock):
        notice = f"attached to the running rig server {sock.stem}"
        if args.set:
            notice += f" (--set {' '.join(args.set)} ignored: change keys with set(...) in the console)"
    else:
        err.print(f"starting a rig server for {args.profile or 'no profile'} …")
        starting = spawn_server(args.profile, sock=sock, out=args.out or "runs",
                                overrides=args.set,
                                strict_plugins=args.strict_plugins)
    # Imported before the app starts (it probes the terminal) and while a new server starts:
    # the server's imports, profile and rig and these imports overlap on two cores.
    from dotshell.tui.app import run_tui

    if starting is not None:
        pid = wait_listening(starting)
        notice = (f"started the rig server {sock.stem} (pid {pid}); it keeps running a scan "
                  "when this terminal closes and exits when idle with nobody attached")
    session = RemoteSession(sock, client="tui", control=True)
    if starting is None and args.out:
        notice += "; " + apply_out_dir(session, args.out)
    return run_tui(session, notice)


def apply_out_dir(session: Any, out_dir: str) -> str:
    """``--out`` for a server that runs already: its output folder is changed (the next scan
    and snapshots go there), or the notice says why not — never ignored."""
    wanted = Path(out_dir).expanduser().resolve()
    if Path(session.state.get("out_dir", "")) == wanted:
        return f"output folder {wanted}"
    try:
        session.configure(out_dir=str(wanted))
    except DotshellError as exc:
        return (f"--out {out_dir} NOT applied, runs still go to {session.state.get('out_dir')}: "
                f"{exc}")
    later = " (the running scan keeps its folder)" if session.scanning else ""
    return f"output folder changed to {wanted} as asked with --out{later}"


# ---- attach -----------------------------------------------------------------------------------

class AttachView:
    """Prints a scan's events as log lines (``--level`` and up) with its progress."""

    def __init__(self, tracker: ScanTracker, level: str) -> None:
        self.tracker = tracker
        self.floor = LEVELS.index(level)

    def show(self, ev: Event) -> None:
        self.tracker.update(ev)
        level, text = describe_event(ev)
        if LEVELS.index(level if level in LEVELS else "info") < self.floor:
            return
        if isinstance(ev, ViewCaptured):
            text += f"  [{_describe_progress(self.tracker, ev.time)}]"
        stamp = time.strftime("%H:%M:%S", time.localtime(ev.time))
        style = {"warning": "yellow", "error": "red"}.get(level, "")
        out.print(f"{stamp} " + (f"[{style}]{escape(text)}[/]" if style else escape(text)))


def cmd_attach(args: argparse.Namespace) -> int:
    import queue

    from dotshell.server.client import RemoteSession

    session = RemoteSession(_require_server(args), client="attach")
    inbox: queue.Queue[dict[str, Any]] = queue.Queue()
    session.subscribe(inbox.put)
    t = session.tracker
    profile = session.profile
    out.print(escape(f"attached to rig server {session.server_name}: profile "
                     f"{profile['name'] if profile else 'none'}, {session.session_state}"
                     + (f"; {_describe_progress(t, time.time())}" if t.active else "")))
    if not t.active and not args.follow:
        run = session.state.get("run")
        if run is None and t.run_dir:  # the scan just ended: the state may not say so yet
            run = {"dir": t.run_dir, "status": t.shown_status}
        out.print(escape(f"no scan is running; last run: {run['dir']} ({run['status']})") if run
                  else "no scan is running.")
        session.close()
        return 0
    view = AttachView(t, args.level)
    code = 0
    try:
        while True:
            message = inbox.get()
            kind = message.get("type")
            if kind == "event":
                ev = event_from_wire(message["event"])
                view.show(ev)
                if isinstance(ev, ScanFinished) and not args.follow:
                    code = 0 if t.shown_status == "completed" else 1
                    break
            elif kind == "closed":
                out.print(f"[yellow]{escape(message.get('reason', 'the server went away'))}[/]")
                code = 1
                break
    except KeyboardInterrupt:
        out.print("detached; the server and its scan go on (dotshell status).")
    session.close()
    return code


# ---- status, stop -----------------------------------------------------------------------------

def _status_of(sock: Path) -> dict[str, Any]:
    from dotshell.server.client import RemoteSession

    session = RemoteSession(sock, client="status")
    try:
        reply = session.refresh()
    finally:
        session.close()
    return {"state": reply["state"], "tracker": reply["tracker"]}


def _print_status(info: dict[str, Any]) -> None:
    s, t = info["state"], ScanTracker.from_dict(info["tracker"])
    srv, profile = s["server"], s["profile"]
    out.print(f"[b]{escape(srv['name'])}[/] (pid {srv['pid']}, up "
              f"{format_seconds(time.time() - srv['started'])}) on {escape(srv['socket'])}")
    shown = f"{profile['name']} — {profile['source']}" if profile else "none"
    rig = "connected" if s["connected"] else "not connected"
    out.print(f"  profile    {escape(shown)}")
    out.print(f"  session    {s['session']}, rig {rig}")
    w = s.get("worker")  # None: a server holding its session in its own process
    if w:
        health = (f"[red]hung[/] in {escape(w['hung'])} (silent {w['silent_s']} s)"
                  if w["state"] == "hung" else w["state"])
        again = f"; restarted {w['restarts']}×" if w["restarts"] else ""
        out.print(f"  worker     pid {w['pid']}, {health}{again}")
    if t.status != "idle":
        out.print(f"  scan       {t.shown_status}: {_describe_progress(t, time.time())}")
        out.print(f"  run        {escape(t.run_dir)}")
    elif s["run"]:
        out.print(f"  last run   {escape(s['run']['dir'])} ({s['run']['status']})")
    c = s["controller"]
    who = f"{c['client']}#{c['id']} pid {c['pid']}" if c else "nobody"
    out.print(f"  control    {escape(who)}; {len(s['clients'])} client(s) attached")
    out.print(f"  log        {escape(srv['log'])}")


def cmd_status(args: argparse.Namespace) -> int:
    from dotshell.runtime.paths import running_servers

    chosen = _which(args) if (args.profile or args.server or args.socket) else None
    socks = [chosen] if chosen is not None else running_servers()
    infos = [_status_of(s) for s in socks if alive(s)]
    answered = {Path(i["state"]["server"]["socket"]) for i in infos}
    silent = _silent_servers([s for s in socks if s not in answered])
    if args.json:
        out.print_json(json.dumps(infos))
        return 0
    if not infos and not silent:
        out.print("no rig server is running.")
    for info in infos:
        _print_status(info)
    _print_silent(silent)
    return 0


def _silent_servers(socks: list[Path]) -> list[tuple[Path, dict[str, Any]]]:
    """Of ``socks`` (none answered), the servers that hold their lock: busy or stalled."""
    from dotshell.runtime.locks import holder, server_lock_path

    return [(s, info) for s in socks if (info := holder(server_lock_path(s))) is not None]


def _print_silent(servers: list[tuple[Path, dict[str, Any]]]) -> None:
    from dotshell.runtime.locks import describe

    for sock, info in servers:
        out.print(escape(f"{sock.stem}: held by {describe(info)} on {sock}, but it does not "
                         "answer at the moment (busy or stalled); try again shortly."))


def cmd_stop(args: argparse.Namespace) -> int:
    from dotshell.server.client import RemoteSession

    sock = _which(args)
    if sock is None or not alive(sock):
        out.print("no rig server is running there." if sock else "no rig server is running.")
        return 0
    session = RemoteSession(sock, client="stop")
    if args.restart_worker:
        try:
            pid = session.call("restart_worker")["pid"]
        finally:
            session.close()
        out.print(f"rig server {sock.stem}: session worker restarted (pid {pid}); the rig is "
                  "not connected.")
        return 0
    try:
        session.shutdown(abort=args.abort)
        if session.scanning:
            out.print("aborting the scan (frames kept) and stopping the devices …")
        session.closed.wait()  # the server says bye when it has stopped
    finally:
        session.close()
    out.print(f"rig server {sock.stem} stopped.")
    return 0


def scan_detached(args: argparse.Namespace) -> int:
    """``dotshell scan PROFILE --detach``: start the scan on the profile's server (started if
    none runs, exiting when idle afterwards) and return with its run directory."""
    from dotshell.server.client import RemoteSession
    from dotshell.server.launch import start_server

    sock = socket_path(server_name(args.profile))
    if alive(sock):
        if args.set:
            raise DotshellError(f"a rig server for {args.profile} runs already; --set would "
                                "change its live profile: change keys there (set(...) in the "
                                "console) or stop it first (dotshell stop PROFILE).")
        started = ""
    else:
        pid = start_server(args.profile, sock=sock, out=args.out, overrides=args.set,
                           strict_plugins=args.strict_plugins)
        started = f"started the rig server {sock.stem} (pid {pid}); "
    session = RemoteSession(sock, client="scan --detach")
    try:
        run_dir = session.scan(out=args.out, calibration=args.calibration)["run_dir"]
    finally:
        session.close()
    out.print(escape(f"{started}scan running: {run_dir}"))
    out.print(escape(f"follow it: dotshell attach {args.profile}   stop it: dotshell stop "
                     f"{args.profile} --abort   status: dotshell status"))
    return 0


# ---- parsers ----------------------------------------------------------------------------------

def add_server_parsers(sub: Any) -> None:
    """Register serve, tui, attach, status and stop, and ``scan --detach``."""

    def which_args(sp: argparse.ArgumentParser, profile_help: str) -> None:
        sp.add_argument("profile", nargs="?", help=profile_help)
        sp.add_argument("--server", metavar="NAME", help="the server's name (dotshell status "
                        "lists them)")
        sp.add_argument("--socket", metavar="PATH", help="the server's socket")

    def session_args(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a profile key (TOML value), e.g. --set scan.views=24")
        sp.add_argument("--out", help="parent directory of runs (default: runs; for a server "
                        "that runs already, its output folder is changed, or why not is said)")

    sp = sub.add_parser("serve", help="run a rig server: one session (rig, scans, console) "
                        "that the TUI and CLI attach to over a Unix socket")
    which_args(sp, "profile TOML file to load (omit to load one later)")
    session_args(sp)
    sp.add_argument("--detach", action="store_true", help="run in the background and return")
    sp.add_argument("--on-hangup", choices=HANGUP_CHOICES, help="on SIGHUP: abort the scan and "
                    "exit (default), or keep running; also [server] on_hangup in the user config")
    sp.add_argument("--exit-when-idle", action="store_true",
                    help="exit when no client is attached and no scan runs")
    sp.set_defaults(func=cmd_serve)

    sp = sub.add_parser("tui", help="terminal UI attached to the profile's rig server (started "
                        "if none runs): rig, scan, previews, log, Python console")
    which_args(sp, "profile TOML file (omit to attach to the running server, or pick one)")
    session_args(sp)
    sp.set_defaults(func=cmd_tui)

    sp = sub.add_parser("attach", help="follow the scan running on a rig server (progress and "
                        "log lines) until it ends; ctrl+c detaches")
    which_args(sp, "profile whose server to attach to (omit: the only running one)")
    sp.add_argument("--follow", action="store_true", help="keep following after the scan")
    sp.add_argument("--level", choices=LEVELS, default="info", help="lowest level shown")
    sp.set_defaults(func=cmd_attach)

    sp = sub.add_parser("status", help="rig servers: profile, session, scan progress and ETA, "
                        "who controls")
    which_args(sp, "profile whose server to show (omit: every running one)")
    sp.add_argument("--json", action="store_true", help="machine-readable")
    sp.set_defaults(func=cmd_status)

    sp = sub.add_parser("stop", help="stop a rig server (closes the rig)")
    which_args(sp, "profile whose server to stop (omit: the only running one)")
    sp.add_argument("--abort", action="store_true",
                    help="also when a scan runs: abort it cleanly (frames kept) first")
    sp.add_argument("--restart-worker", action="store_true",
                    help="keep the server: end its session worker (a scan aborted, frames kept) "
                    "and start a new one on the same profile, e.g. after a driver hung")
    sp.set_defaults(func=cmd_stop)

    sub.choices["scan"].add_argument(
        "--detach", action="store_true", help="run the scan on the profile's rig server (started "
        "if none runs) and return; follow it with dotshell attach")
