"""CLI front end of ``dotshell decode`` (thin: parses arguments, calls
:mod:`dotshell.pipeline.decode_maps`, prints the counts)."""

from __future__ import annotations

import argparse
from typing import Any

from rich.console import Console

from dotshell.cli.common import print_as_is
# a loss of at least NOTE_SHARE_PCT of the pixels (%) gets its meaning and fix printed (the
# share a scanned view's notes use), reversals from NOTE_REVERSALS_PCT of the decoded pixels
from dotshell.pipeline.decode_quality import NOTE_REVERSALS_PCT, NOTE_SHARE_PCT

#: Reasons a pixel is lost, in the order they are printed.
LOSS_ORDER = ("shadow", "low_contrast", "uncertain", "out_of_range", "low_modulation",
              "phase_inconsistent", "grazing", "row_rejected")


def pixel_counts(counts: dict[str, Any]) -> str:
    """One line: decoded pixels and every non-zero loss, each with its share of all pixels."""
    total = max(int(counts.get("pixels", 0)), 1)

    def share(key: str) -> str:
        return f"{key.replace('_', ' ')} {counts[key]} ({100 * counts[key] / total:.1f} %)"

    losses = [share(k) for k in LOSS_ORDER if counts.get(k)]
    return (f"{share('decoded')} of {counts.get('pixels', 0)} pixels; lost: "
            f"{', '.join(losses) or 'none'}")


def refuse_layout_overrides(overrides: list[str], layout: str | None) -> None:
    """``--set layout.KEY=…`` is refused with the way that works: a layout is a file, so copy
    it, change the key there and pass the copy with ``--layout``."""
    from dotshell.errors import ProfileError

    keys = [o.split("=", 1)[0] for o in overrides if o.strip().startswith(("layout.", "decoder."))]
    if not keys:
        return
    source = "the layout file"
    if layout:
        from dotshell.errors import RunError
        from dotshell.run.capture_layouts import resolve_layout_path

        try:
            source = str(resolve_layout_path(layout))
        except RunError:
            pass
    raise ProfileError(
        f"--set {keys[0]}=…: layout keys are not settings of the command; they live in the "
        f"layout file. Copy {source} to a file of your own (cp {source} my-layout.toml), set "
        f"{keys[0].split('.', 1)[1]} there and pass --layout my-layout.toml.")


def loss_notes(counts: dict[str, Any], quality: dict[str, Any] | None = None) -> list[str]:
    """What each large loss means and what would fix it (one line each; row rejections at any
    share, since each is a code the calibration contradicts), and what many neighbour
    reversals in ``quality`` mean (:func:`dotshell.pipeline.decode_quality.view_quality`)."""
    from dotshell.pipeline.reconstruct import LOSSES, note_text

    total = max(int(counts.get("pixels", 0)), 1)
    out = []
    for key in LOSS_ORDER:
        share = 100 * int(counts.get(key) or 0) / total
        if key in LOSSES and (share >= NOTE_SHARE_PCT or (key == "row_rejected" and share > 0)):
            out.append(note_text(key, share))
    pct = (quality or {}).get("reversals_pct", 0.0)
    if pct >= NOTE_REVERSALS_PCT:
        out.append(note_text("reversals", pct))
    return out


def quality_line(q: dict[str, Any]) -> str:
    """``decoded 41.2 % of the image; estimated wrong codes: 3 neighbour reversals (0.01 % of
    the decoded pixels)``."""
    return (f"decoded {q['decoded_pct']:.1f} % of the image; estimated wrong codes: "
            f"{q['reversals']} neighbour reversals ({q['reversals_pct']:.2f} % of the decoded "
            "pixels)")


def add_layout_arg(sp: argparse.ArgumentParser, what: str = "the sequence") -> None:
    """``--layout LAYOUT``: a layout TOML or the name of a shipped one."""
    from dotshell.shipped import shipped_names

    shipped = ", ".join(shipped_names("layouts"))
    sp.add_argument("--layout", metavar="LAYOUT",
                    help=f"layout TOML of {what}, or a shipped one: {shipped}")


def add_decode_parser(sub) -> None:
    sp = sub.add_parser("decode", help="decode without triangulating: per-pixel projector column "
                        "and row maps (TIFF/NPY), the mask with reasons, counts, previews")
    sp.add_argument("run", nargs="?", help="run directory: decodes every view with the run's "
                    "coding (the run is only read)")
    sp.add_argument("--captures", metavar="DIR",
                    help="decode the image sequence in DIR (made by another rig or program); "
                         "needs --layout")
    add_layout_arg(sp)
    sp.add_argument("--format", choices=("tiff", "npy"), default="tiff",
                    help="map file format: float32 TIFF (default) or NumPy .npy; NaN = not decoded")
    sp.add_argument("--out", default="runs", metavar="DIR",
                    help="parent directory of the new output directory (default: runs)")
    sp.set_defaults(func=cmd_decode)


def cmd_decode(args: argparse.Namespace) -> int:
    from dotshell.cli.common import out, plugin_manager
    from dotshell.errors import RunError
    from dotshell.pipeline.decode_maps import decode_captures, decode_run

    pm = plugin_manager(args)
    if args.captures:
        if not args.layout:
            raise RunError("dotshell decode --captures DIR needs --layout LAYOUT (a layout TOML "
                           "or a shipped one: slstudio-graycode, opencv-graycode).")
        res = decode_captures(args.captures, args.layout, pm, args.out, args.format)
        print_view(res.report, out)
    elif args.run:
        res = decode_run(args.run, pm, args.out, args.format)
        for name, view in res.report["views"].items():
            out.print(f"{name} ({view['angle_deg']:g}°):", end=" ")
            print_view(view, out)
        for name, why in res.report["skipped"].items():
            out.print(f"[yellow]skipped {name}:[/] {why}")
    else:
        raise RunError("dotshell decode needs a RUN directory, or --captures DIR --layout LAYOUT.")
    print_as_is(out, f"output: {res.out_dir}  (column/row maps, mask.png, report.json, previews/)")
    return 0


def print_view(view: dict[str, Any], out: Console) -> None:
    out.print(pixel_counts(view["counts"]))
    q = view.get("quality")
    if q:
        out.print(f"  {quality_line(q)}")
    for line in loss_notes(view["counts"], q):
        print_as_is(out, f"  {line}")
