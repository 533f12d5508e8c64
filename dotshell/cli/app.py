"""The ``dotshell`` command. Thin: parses arguments, calls the core API, shows events.

Exit codes: 0 success, 2 user error (bad profile, unknown backend, missing file, device or
calibration problem — one paragraph on stderr, no traceback), 130 interrupted (frames kept).
"""

from __future__ import annotations

import argparse
import sys
import threading
from functools import lru_cache
from pathlib import Path

from rich.markup import escape

from dotshell import __version__
from dotshell.cli.common import ScanProgress, err, out, plugin_manager as _pm, print_as_is
from dotshell.cli.report import print_report as _print_report
from dotshell.cli.report import table as _table
from dotshell.errors import DotshellError
from dotshell.events import EventBus, Message


def _scan_outcome(result) -> int:
    _print_report(result.report, result.run_dir)
    if result.status != "completed":
        err.print(f"[yellow]{result.status}[/]: {escape(result.reason)}. Continue it with "
                  f"`dotshell resume {result.run_dir}`.")
    return 0 if result.status == "completed" else 1


def cmd_scan(args: argparse.Namespace) -> int:
    from dotshell.pipeline.scan import scan
    from dotshell.profile.loader import load_profile

    if args.detach:
        from dotshell.cli.server import scan_detached

        return scan_detached(args)
    pm = _pm(args)
    profile = load_profile(args.profile, pm, args.set)
    bus = EventBus()
    view = ScanProgress(err)
    bus.subscribe(view)
    with view.progress:
        result = scan(profile, pm, args.out, bus=bus, stop=threading.Event(),
                      calibration_file=args.calibration)
    return _scan_outcome(result)


def cmd_resume(args: argparse.Namespace) -> int:
    from dotshell.pipeline.scan import resume_run

    pm = _pm(args)
    bus = EventBus()
    view = ScanProgress(err)
    bus.subscribe(view)
    with view.progress:
        result = resume_run(args.run, pm, bus=bus, stop=threading.Event(), views=args.view)
    return _scan_outcome(result)


def cmd_inspect(args: argparse.Namespace) -> int:
    from dotshell.run.frames import damaged_views, frames_on_disk
    from dotshell.run.generations import current_number, generation_numbers
    from dotshell.run.store import RunStore

    store = RunStore.open(Path(args.run))
    m = store.manifest
    status, reason = store.status()
    views = m["views"]
    on_disk = frames_on_disk(store.root, m)
    damaged = damaged_views(store.root, m)
    from dotshell.run.lost import is_lost, lost_views

    lost = sum(is_lost(v) for v in views)
    done = sum(v["complete"] and not is_lost(v) for v in views) - len(damaged)
    print_as_is(out, f"run: {store.root}")
    out.print(f"status: [bold]{status}[/]" + (f" — {escape(reason)}" if reason else ""))
    out.print(f"profile: {escape(str(m.get('profile', '?')))}, created {m.get('created', '?')}")
    out.print(f"views: {done} of {len(views)} complete" + (f", {lost} lost" if lost else "") +
              f", {sum(on_disk)} frames on disk")
    for v, n, recorded in damaged:
        print_as_is(out, f"view {v}: {n} of its {recorded} frames on disk (cut or deleted "
                    f"after the scan); re-capture it with `dotshell resume {store.root} "
                    f"--view {v}`, or mark it lost: `dotshell lose-view {store.root} {v} "
                    "--reason TEXT`")
    for gone in lost_views(m):
        print_as_is(out, f"view {gone['view']}: lost ({gone['reason']}); the run is processed "
                    "without it")
    cur = current_number(store.root)
    gens = generation_numbers(store.root)
    out.print(f"generations: {', '.join(f'{g:03d}' for g in gens) or 'none'}; published: "
              f"{'none' if cur is None else f'{cur:03d}'}")
    t = _table(title="jobs")
    for col in ("command", "status", "generation", "finished", "reason"):
        t.add_column(col)
    for j in m.get("jobs", []):
        gen = j.get("generation")
        t.add_row(str(j.get("command", "")), str(j.get("status", "")),
                  "" if gen is None else f"{gen:03d}", str(j.get("finished", "")),
                  escape(str(j.get("reason", ""))))
    out.print(t)
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    from dotshell.pipeline.compare import COLUMNS, compare_runs

    rows, csv_path, png_path = compare_runs(args.runs, args.out)
    t = _table(title="Validation across runs (paper's Table 1 layout)")
    heads = {"mean_rel_error_pct": "mean rel. err %", "std_rel_error_pct": "std %",
             "rms_radius_error_mm": "RMS µm", "coverage_pct": "coverage %",
             "decoded_pct": "decoded %", "rejected_pct": "rejected %"}
    cols = [c for c in COLUMNS if c != "run"]
    for c in cols:
        t.add_column(heads.get(c, c))
    for r in rows:
        t.add_row(*(f"{r[c] * 1000:.1f}" if c == "rms_radius_error_mm" else
                    f"{r[c]:.3f}" if isinstance(r[c], float) else escape(str(r[c])) for c in cols))
    out.print(t)
    print_as_is(out, f"table: {csv_path}\nplot: {png_path}")
    return 0


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from dotshell.pipeline.commands import reconstruct_run

    pm = _pm(args)
    if args.captures or args.run is None:
        from dotshell.cli.calibration import reconstruct_captures_command

        return reconstruct_captures_command(args, pm, out)
    bus = EventBus()
    view = ScanProgress(err)
    bus.subscribe(view)
    with view.progress:
        result = reconstruct_run(args.run, pm, bus, calibration_file=args.calibration)
    _print_report(result.report, result.run_dir)
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from dotshell.profile.loader import DEVICE_ROLES, load_profile
    from dotshell.rig.assembly import Rig

    pm = _pm(args)
    profile = load_profile(args.profile, pm, args.set)
    out.print(f"[green]profile OK[/]: {profile.source} ({profile.name})")
    for role in (*DEVICE_ROLES, "coding"):
        sec = profile.role(role)
        if sec:
            info = pm.backend(role, sec["backend"])
            out.print(f"  {role:<13} {sec['backend']:<16} from {info.distribution}")
    second = profile.role("camera2")
    if second:
        out.print(f"  camera2       {second['backend']:<16} a second camera: "
                  "scan and --connect use camera 1 only (docs/profiles.md)")
    out.print(f"  views         {len(profile.angles_deg())}")
    if args.connect or args.latency:
        from dotshell.run.lifecycle import connected
        from dotshell.rig.checks import check_resolutions, measure_latency, refused_controls

        with connected(Rig(profile, pm)) as rig:  # stopped by Ctrl-C while homing, too
            for role, status in rig.status().items():
                out.print(f"  [green]connected[/] {role:<13} {escape(str(status))}")
            cal = rig.calibration(args.calibration)
            out.print(f"  calibration   {cal.source}: baseline {cal.baseline_mm:.2f} mm")
            check_resolutions(rig, cal, str(profile.source))
            for line in refused_controls(rig):
                out.print(f"  [yellow]warning[/] {escape(line)}")
            if args.latency:
                lat = measure_latency(rig, profile.scan.exposure_ms)
                out.print(f"  display latency: the full pattern is seen {lat.shortest_ms:.0f} ms "
                          f"after show() ({len(lat.trials)} trials, step "
                          f"{lat.contrast_dn:.0f} DN)")
                out.print(f"settle_ms = {lat.settle_ms:g}")
        out.print("[green]all devices opened and closed[/]")
    return 0


def cmd_plugins(args: argparse.Namespace) -> int:
    """List every backend from the plugins' manifests (importing none of them); ``--check``
    imports each and names those that fail (exit 2), ``--settings`` imports each to list its
    settings."""
    from dotshell.backends import ROLES

    pm = _pm(args)
    t = _table(title="dotshell backends")
    for col in ("role", "name", "plugin", "distribution", "summary"):
        t.add_column(col)
    for role in ROLES:
        for name, info in sorted(pm.backends(role).items()):
            t.add_row(role, name, info.plugin, info.distribution, escape(info.summary))
    out.print(t)
    broken = pm.check_backends() if args.check or args.settings else []
    if args.settings:
        _print_settings(pm, ROLES)
    if pm.load_errors:
        out.print("[red]plugins that failed to load:[/]")
        for e in pm.load_errors:
            out.print(f"  {escape(str(e))}")
    if broken:
        out.print("[red]backends that failed to load:[/]")
        for e in broken:
            out.print(f"  {escape(e.reason)}")
        return 2
    if args.check:
        out.print(f"[green]all {sum(len(pm.qualified[r]) for r in ROLES)} backends load[/]")
    return 1 if pm.load_errors else 0


def _print_settings(pm, roles) -> None:
    """Each backend's ``[ROLE.settings]`` table (after ``check_backends``: the broken ones,
    still not loaded, are skipped)."""
    from dotshell.settings import describe

    for role in roles:
        for name, info in sorted(pm.backends(role).items()):
            if not info.loaded:
                continue
            st = _table(title=escape(f"[{role}] backend = \"{name}\" — [{role}.settings]"))
            for col in ("key", "type", "default", "help"):
                st.add_column(col)
            for row in describe(info.backend.settings_schema):
                st.add_row(*map(escape, row))
            out.print(st)


def cmd_script(args: argparse.Namespace) -> int:
    from dotshell.session.console import Session, run_script, split_script_args

    opts, script_argv = split_script_args(args.args)  # options may also follow FILE
    session = Session(opts["profile"] or args.profile, pm=_pm(args),
                      out_dir=opts["out"] or args.out, overrides=args.set + opts["set"])
    view = ScanProgress(err)
    # log lines from the session's log_level() on, as in the console; progress bars always
    session.bus.subscribe(lambda ev: view(ev) if not isinstance(ev, Message)
                          or session.shows(ev.level) else None)
    with session, view.progress:
        run_script(args.file, session, script_argv)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="dotshell", description=(
        "Instrument shell for structured-light surface scans on DOT rigs. Every command and "
        "file format is documented: `dotshell docs` prints where the installed documentation "
        "is (and the built documentation site); `dotshell profiles` lists the shipped "
        "profiles."))
    p.add_argument("--version", action="version", version=f"dotshell {__version__}")
    from dotshell.cli.log_setup import add_logging_args

    add_logging_args(p)
    p.add_argument("--strict-plugins", action="store_true",
                   help="fail when any plugin fails to load (for plugin authors and CI)")
    p.add_argument("--debug", action="store_true",
                   help="show the Python traceback of any error (for bug reports)")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def profile_args(sp):
        sp.add_argument("profile", help="profile TOML file, or the name of a shipped profile "
                        "(`dotshell profiles`), e.g. sim-metal-cylinder")
        sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a profile key (TOML value), e.g. --set scan.views=24")
        sp.add_argument("--calibration", metavar="FILE",
                        help="use this calibration.json instead of the profile's")

    sp = sub.add_parser("scan", help="run a scan and process it")
    profile_args(sp)
    sp.add_argument("--out", default="runs", help="parent directory of the run (default: runs)")
    sp.set_defaults(func=cmd_scan)

    sp = sub.add_parser("resume", help="finish an interrupted, aborted or failed scan (the "
                        "views it misses, then the processing)")
    sp.add_argument("run", help="run directory")
    sp.add_argument("--view", type=int, action="append", metavar="N",
                    help="also capture view N again (frames/view_NNN.tif cut or deleted; "
                         "the old frames are kept aside; a view marked lost is no longer "
                         "lost once captured); repeat for several views")
    sp.set_defaults(func=cmd_resume)
    from dotshell.cli.lost import add_lose_view_parser

    add_lose_view_parser(sub, _pm)

    sp = sub.add_parser("inspect", help="a run's true status, views, generations and jobs")
    sp.add_argument("run", help="run directory")
    sp.set_defaults(func=cmd_inspect)

    sp = sub.add_parser("reconstruct", help="re-process a run from its frames on disk, or "
                        "reconstruct captures from another rig (--captures)")
    sp.add_argument("run", nargs="?", help="run directory")
    sp.add_argument("--calibration", metavar="FILE", help="use this calibration instead")
    from dotshell.cli.calibration import add_captures_args, add_calibrate_parser
    from dotshell.cli.decode import add_decode_parser

    add_captures_args(sp)
    sp.set_defaults(func=cmd_reconstruct)

    add_calibrate_parser(sub, profile_args)
    add_decode_parser(sub)

    sp = sub.add_parser("validate", help="compare the accuracy of runs (Table 1, CSV, PNG plot)")
    sp.add_argument("runs", nargs="+", help="run directories")
    sp.add_argument("--out", default=".", help="where validation.csv and validation.png go")
    sp.set_defaults(func=cmd_validate)

    sp = sub.add_parser("check", help="validate a profile (and open every device with --connect)")
    profile_args(sp)
    sp.add_argument("--connect", action="store_true", help="connect and close every device; "
                    "check the calibration against the devices' resolutions")
    sp.add_argument("--latency", action="store_true", help="with the devices connected, "
                    "measure the display latency and print a settle_ms for the profile")
    sp.set_defaults(func=cmd_check)

    sp = sub.add_parser("plugins", help="list backends by role and plugin load errors")
    sp.add_argument("--settings", action="store_true", help="also list each backend's settings")
    sp.add_argument("--check", action="store_true", help="import every backend and name the "
                    "ones that fail to load (exit 2)")
    sp.set_defaults(func=cmd_plugins)

    from dotshell.cli.mesh import add_mesh_parsers

    add_mesh_parsers(sub, _pm)
    from dotshell.cli.normalize import add_normalize_parser

    add_normalize_parser(sub, _pm)
    from dotshell.cli.devices import add_device_parsers; add_device_parsers(sub, _pm)  # noqa: E702
    from dotshell.cli.frames import add_frames_parser; add_frames_parser(sub)  # noqa: E702
    from dotshell.cli.batch import add_batch_parser

    add_batch_parser(sub, _pm)

    def session_args(sp):
        sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a profile key (TOML value), e.g. --set scan.views=24")
        sp.add_argument("--out", default="runs", help="parent directory of runs (default: runs)")

    from dotshell.cli.server import add_server_parsers

    add_server_parsers(sub)  # serve, tui, attach, status, stop, scan --detach
    from dotshell.cli.shipped import add_shipped_parsers

    add_shipped_parsers(sub)  # profiles [copy], docs
    from dotshell.cli.completion import add_completion_parser

    add_completion_parser(sub, p)
    sp = sub.add_parser("script", help="run a Python script against a live session, headless")
    sp.add_argument("file", help="the Python script (rig, profile, run, scan(), np, ... are "
                    "defined; see docs/tui.md)")
    sp.add_argument("--profile", help="profile TOML file to load before the script runs")
    session_args(sp)
    sp.add_argument("args", nargs=argparse.REMAINDER,
                    help="arguments for the script (sys.argv[1:]); put them after --")
    sp.set_defaults(func=cmd_script)
    from dotshell.cli.log_setup import add_logging_args_to_commands

    add_logging_args_to_commands(sub)  # -v/-q/--log-level after the command too
    return p


@lru_cache(maxsize=1)
def _parser() -> argparse.ArgumentParser:
    """The parser, built once per process: its ~30 sub-parsers take 20-50 ms to build (argparse
    looks up translations and the terminal's size for each), paid at every :func:`main` call
    of a script or a test run otherwise. Parsing does not change it (``append`` arguments copy
    their default list)."""
    return build_parser()


#: commands that run a user's code or hold a session: they end with Python's own exit, which
#: flushes and closes whatever those left open
NORMAL_EXIT = frozenset({"script", "serve", "tui", "attach", "emulate"})


def main(argv: list[str] | None = None) -> int:
    """The ``dotshell`` command on ``argv``; its exit status. Run as the command (``argv``
    None), the process ends here once the work is done, without the interpreter's teardown
    (:func:`dotshell.runtime.process.exit_now`; not for :data:`NORMAL_EXIT`); called with ``argv``
    (tests, scripts) it returns."""
    args = parse_args(argv)
    code = run_command(args)
    if argv is None and args.command not in NORMAL_EXIT:
        from dotshell.runtime.process import exit_now

        exit_now(code)
    return code


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    argv = list(sys.argv[1:] if argv is None else argv)
    head = argv[:argv.index("--")] if "--" in argv else argv  # --debug anywhere before `--`
    debug = "--debug" in head
    argv = [a for a in head if a != "--debug"] + argv[len(head):]
    args = _parser().parse_args(argv)
    args.debug = args.debug or debug
    return args


def run_command(args: argparse.Namespace) -> int:
    from dotshell.run.lifecycle import interrupt_reason, interrupts
    from dotshell.runtime.process import configure_process

    configure_process()  # BLAS on one thread, large blocks unmapped when freed
    from dotshell.cli.log_setup import configure_logging

    configure_logging(args)  # -v/-q/--log-level; library warnings only with -v
    try:
        with interrupts(notify=lambda text: err.print(f"[yellow]{escape(text)}[/]")):
            return args.func(args)
    except DotshellError as exc:
        return _fail(args, exc, str(exc), exc.exit_code)
    except KeyboardInterrupt as exc:
        err.print(f"[yellow]interrupted[/]: {interrupt_reason(exc)}; devices were stopped and "
                  "frames captured so far are kept in the run directory (`dotshell resume RUN` "
                  "continues a scan).")
        return 130
    except MemoryError as exc:
        return _fail(args, exc, "out of memory" + limits_in_force() + ". Lower the camera or "
                     "projector resolution (e.g. --set camera.settings.width=... --set "
                     "camera.settings.height=...), scan fewer views, or use a machine with more "
                     "memory.", 2)
    except OSError as exc:
        if exc.errno is None and "shared object" in str(exc):  # dlopen refused: no address space
            return _fail(args, exc, "could not load a library" + limits_in_force() + f" ({exc})"
                         ": the process's memory limit is too small for it. Raise the limit, "
                         "or close other programs.", 2)
        return _fail(args, exc, os_error_message(exc), 2)
    except RuntimeError as exc:
        if "can't start new thread" not in str(exc):
            return _fail(args, exc, _internal(exc), 1)
        return _fail(args, exc, "could not start a thread" + limits_in_force() + ": the "
                     "process's memory or thread limit is reached. Raise the limit, or close "
                     "other programs.", 2)
    except Exception as exc:  # a bug: one paragraph, the traceback with --debug
        return _fail(args, exc, _internal(exc), 1)


def _internal(exc: BaseException) -> str:
    return (f"internal error: {type(exc).__name__}: {exc}. This is a bug in dotshell or a "
            "plugin; run again with --debug for the traceback and report it.")


def limits_in_force() -> str:
    """The process's address-space and thread limits, when set (`` (ulimit -v 700000 kB)``),
    or '' — what a user raises after running out of memory or threads."""
    import resource

    parts = []
    for name, limit, unit in (("ulimit -v", resource.RLIMIT_AS, 1024),
                              ("ulimit -u", resource.RLIMIT_NPROC, 1)):
        soft = resource.getrlimit(limit)[0]
        if soft != resource.RLIM_INFINITY:
            parts.append(f"{name} {soft // unit}" + (" kB" if unit > 1 else " processes"))
    return f" (limits: {', '.join(parts)})" if parts else ""


def _fail(args: argparse.Namespace, exc: BaseException, text: str, code: int) -> int:
    if getattr(args, "debug", False):
        import traceback

        err.print("".join(traceback.format_exception(exc)), markup=False, highlight=False)
    err.print(f"[red]error:[/] {escape(text)}", soft_wrap=True)
    return code


def os_error_message(exc: OSError) -> str:
    """One paragraph for a file-system error: what, where, and the fix."""
    import errno

    where = f" {exc.filename}" if exc.filename else ""
    fixes = {
        errno.ENOSPC: "free disk space or write to another drive (--out)",
        errno.EDQUOT: "free space within your quota or write to another drive (--out)",
        errno.EACCES: "write somewhere you may write (--out) or fix the directory's permissions",
        errno.EPERM: "write somewhere you may write (--out) or check the directory's owner and "
                     "permissions",
        errno.EROFS: "write to another drive (--out), or copy a run there (cp -a) to "
                     "process it",
        errno.EFBIG: "the file is larger than this process may write (`ulimit -f`) or than the "
                     "file system allows: raise the limit or write to another drive (--out)",
        errno.ENOENT: "check the path",
        errno.ENOTDIR: "a part of the path is a file: give a directory",
        errno.EISDIR: "give a file, not a directory",
        errno.EMFILE: "raise the open-file limit (ulimit -n)",
        errno.ENOMEM: "close other programs or scan at a lower resolution",
    }
    fix = fixes.get(exc.errno or 0, "check the path, the disk and the permissions")
    return f"could not read or write{where}: {exc.strerror or exc} — {fix}."


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
