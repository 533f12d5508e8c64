"""What each session request does in the server, and what its reply holds (JSON-ready).

Every handler takes the server's :class:`Context` and the request's arguments; errors are
raised (a :class:`~dotshell.errors.DotshellError` is the user's to fix) and become failed
replies. The request names and arguments are documented in docs/server.md.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Callable

from dotshell.session.console import Session
from dotshell.errors import DotshellError, RunError
from dotshell.events import ScanFinished, ScanStarted
from dotshell.server.repl import ServerConsole

@dataclass
class Context:
    session: Session
    console: ServerConsole


def _number(args: dict[str, Any], key: str) -> float:
    try:
        return float(args[key])
    except (KeyError, TypeError, ValueError):
        raise DotshellError(f"the request needs a number {key!r}, got {args.get(key)!r}.") from None


def _text(args: dict[str, Any], key: str) -> str:
    value = args.get(key)
    if not isinstance(value, str) or not value:
        raise DotshellError(f"the request needs a text {key!r}, got {value!r}.")
    return value


def profile_summary(session: Session) -> dict[str, Any] | None:
    """What front ends show of the loaded profile (None without one)."""
    p = session.profile
    if p is None:
        return None
    from dotshell.rig.owners import profile_device_ids
    from dotshell.profile.loader import DEVICE_ROLES

    return {"name": p.name, "source": str(p.source), "device_ids": profile_device_ids(p),
            "path": str(session.profile_path.resolve()) if session.profile_path else None,
            "views": len(p.angles_deg()), "exposure_ms": p.scan.exposure_ms,
            "pdi": p.scan.pdi, "pdi_angles_deg": list(p.scan.pdi_angles_deg),
            "coding": p.required_role("coding")["backend"],
            "roles": {r: p.required_role(r)["backend"] for r in DEVICE_ROLES
                      if p.role(r) is not None}}


def _load(ctx: Context, args: dict[str, Any]) -> Any:
    ctx.session.load(_text(args, "path"), list(args.get("overrides") or []))
    return profile_summary(ctx.session)


def _set(ctx: Context, args: dict[str, Any]) -> Any:
    ctx.session.set(*list(args.get("overrides") or []))
    return profile_summary(ctx.session)


def _configure(ctx: Context, args: dict[str, Any]) -> Any:
    """The next scan's settings (views, exposure_ms, pdi_angles_deg, out_dir; each optional)."""
    angles = args.get("pdi_angles_deg")
    if angles is not None and (not isinstance(angles, list) or len(angles) != 2):
        raise DotshellError(f"pdi_angles_deg needs two angles (parallel, perpendicular; "
                            f"degrees), got {angles!r}.")
    ctx.session.configure(
        views=int(_number(args, "views")) if args.get("views") is not None else None,
        exposure_ms=_number(args, "exposure_ms") if args.get("exposure_ms") is not None else None,
        pdi_angles_deg=angles, out_dir=args.get("out_dir"))
    return profile_summary(ctx.session)


def _snap(ctx: Context, args: dict[str, Any]) -> Any:
    s = ctx.session.snap()
    return {"path": str(s.path), "preview": str(s.preview), "angle_deg": s.angle_deg,
            "width": int(s.frame.shape[1]), "height": int(s.frame.shape[0]),
            "dtype": str(s.frame.dtype), "mean": float(s.frame.mean())}


def _decode(ctx: Context, args: dict[str, Any]) -> Any:
    d = ctx.session.decode()
    return {"decoded_pixels": d.decoded_pixels, "total_pixels": d.total_pixels,
            "preview": str(d.preview)}


def _scan(ctx: Context, args: dict[str, Any]) -> Any:
    """Start a scan in the background; answers with its run directory once the acquisition
    starts (the rig connects and the calibration loads first), or with the error that ended
    the scan before that."""
    started = threading.Event()
    seen: dict[str, str] = {}

    def watch(ev: Any) -> None:
        if isinstance(ev, ScanStarted):
            seen["run_dir"] = ev.run_dir
        if isinstance(ev, (ScanStarted, ScanFinished)):
            started.set()

    unsubscribe = ctx.session.bus.subscribe(watch)
    try:
        job = ctx.session.scan(wait=False, out=args.get("out"), calibration=args.get("calibration"))
        while not started.wait(0.1) and not job.done:
            pass
    finally:
        unsubscribe()
    if "run_dir" not in seen:
        job.thread.join()
        if job.error is not None:
            raise job.error
        raise RunError("the scan ended before its acquisition started; see the server log.")
    return {"run_dir": seen["run_dir"]}


def _normalize(ctx: Context, args: dict[str, Any]) -> Any:
    return ctx.session.normalize(args.get("run"), args.get("normalizer"))


def _plugins(ctx: Context, args: dict[str, Any]) -> Any:
    from dotshell.backends import ROLES

    pm = ctx.session.pm
    rows = [[role, name, info.plugin, info.distribution, info.summary]
            for role in ROLES for name, info in sorted(pm.backends(role).items())]
    return {"backends": rows, "errors": [str(e) for e in pm.load_errors]}


def _console(ctx: Context, args: dict[str, Any]) -> Any:
    return {"input": ctx.console.run(_text(args, "source"))}


def _console_reply(ctx: Context, args: dict[str, Any]) -> Any:
    line = args.get("text")
    if line is not None and not isinstance(line, str):
        raise DotshellError(f"console_reply needs a text or null, got {line!r}.")
    return {"delivered": ctx.console.reply(line)}


Handler = Callable[[Context, dict[str, Any]], Any]

#: Session requests by name (the server itself answers hello, state, control, release,
#: shutdown and bye).
COMMANDS: dict[str, Handler] = {
    "load": _load,
    "set": _set,
    "configure": _configure,
    "connect": lambda c, a: c.session.connect(),
    "disconnect": lambda c, a: c.session.disconnect(),
    "move": lambda c, a: c.session.move_to(_number(a, "degrees")),
    "jog": lambda c, a: c.session.jog(_number(a, "degrees")),
    "home": lambda c, a: c.session.home(str(a.get("role") or "stage")),
    "analyzer": lambda c, a: c.session.set_analyzer(_number(a, "degrees")),
    "exposure": lambda c, a: c.session.set_exposure(_number(a, "ms")),
    "project": lambda c, a: c.session.project(_text(a, "name")),
    "patterns": lambda c, a: c.session.patterns(),
    "snap": _snap,
    "decode": _decode,
    "scan": _scan,
    "pause": lambda c, a: c.session.pause(),
    "resume": lambda c, a: c.session.resume(),
    "abort": lambda c, a: c.session.abort(),
    "stop": lambda c, a: c.session.stop(),
    "halt": lambda c, a: c.session.halt(),
    "normalize": _normalize,
    "devices": lambda c, a: c.session.devices(),
    "plugins": _plugins,
    "history": lambda c, a: c.console.history,
    "console": _console,
    "console_reply": _console_reply,
    "console_interrupt": lambda c, a: {"interrupted": c.console.interrupt()},
    "complete": lambda c, a: c.console.complete(str(a.get("text", ""))),
}
