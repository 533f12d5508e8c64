"""Layout files and the capture sequences they describe (frames made elsewhere: another rig,
another program).

A *layout file* (TOML, see ``docs/layouts.md`` and ``layouts/*.toml``) says how a sequence was
made: the file names, the frame order (white, black, column bits, row bits), bit order,
inverse patterns, dropped low bits, whether the code is centred, the bit polarity and the
projector resolution. :func:`read_sequence` reads a directory's frames in that order and puts
them in the order the layout's coding expects (bit 1 = lit); a missing, extra, unreadable or odd
frame is an error naming it. :func:`read_gray` reads one frame file as one grey channel.
Reconstructing such a sequence is :func:`dotshell.pipeline.captures.reconstruct_captures`;
calibrating from sequences, :mod:`dotshell.calibration.captures`.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dotshell.errors import RunError
from dotshell.settings import Setting, validate_settings

if TYPE_CHECKING:  # numpy and OpenCV load when frames are read
    import numpy as np

BLOCKS = ("white", "black", "columns", "rows")

LAYOUT_SCHEMA: dict[str, Setting] = {
    "layout": Setting("table", schema={
        "name": Setting("str", help="short name"),
        "description": Setting("str", default="", help="one line for humans"),
        "coding": Setting("str", default="graycode", help="coding backend that decodes the frames"),
        "files": Setting("str", help="file-name pattern with {index}, e.g. frameSeq_{index:02d}.bmp"),
        "first_index": Setting("int", default=0, min=0, help="{index} of the first frame"),
        "projector_width": Setting("int", min=2, unit="px", help="projector width"),
        "projector_height": Setting("int", min=2, unit="px", help="projector height"),
        "order": Setting("list[str]", help="blocks in capture order: white, black, columns, rows"),
        "inverse": Setting("bool", default=False, help="each bit is followed by its inverse"),
        "msb_first": Setting("bool", default=True, help="coarsest bit first"),
        "drop_low_bits": Setting("int", default=0, min=0, max=15,
                                 help="finest bits not projected"),
        "centred": Setting("bool", default=False,
                           help="code centred on the projector (dotshell's own sequence)"),
        "bright_is_one": Setting("bool", default=True,
                                 help="a lit stripe in the (first) pattern image means bit 1"),
    }),
    "decoder": Setting("table", default={}, help="extra settings for the coding backend"),
}


@dataclass(frozen=True)
class Layout:
    """A validated layout file."""

    source: str
    name: str
    description: str
    coding: str
    files: str
    first_index: int
    projector_size: tuple[int, int]
    order: tuple[str, ...]
    inverse: bool
    msb_first: bool
    drop_low_bits: int
    centred: bool
    bright_is_one: bool
    decoder: dict[str, Any]

    @property
    def axes(self) -> str:
        return "both" if "rows" in self.order else "columns"

    def coding_settings(self) -> dict[str, Any]:
        """Settings for the coding backend (gray code) that decode frames in its own order."""
        return {**self.decoder, "axes": self.axes, "inverse": self.inverse,
                "drop_low_bits": self.drop_low_bits, "centred": self.centred}

    def file_name(self, position: int) -> str:
        return self.files.format(index=self.first_index + position)

    def as_dict(self) -> dict[str, Any]:
        """The layout's TOML tables (``layout``, ``decoder``), as :func:`layout_from_dict`
        reads them."""
        return {"layout": {
            "name": self.name, "description": self.description, "coding": self.coding,
            "files": self.files, "first_index": self.first_index,
            "projector_width": self.projector_size[0], "projector_height": self.projector_size[1],
            "order": list(self.order), "inverse": self.inverse, "msb_first": self.msb_first,
            "drop_low_bits": self.drop_low_bits, "centred": self.centred,
            "bright_is_one": self.bright_is_one}, "decoder": dict(self.decoder)}


def resolve_layout_path(name_or_path: str | Path) -> Path:
    """A layout file path; a bare name (``slstudio-graycode``) that is not a file means a shipped
    layout (:mod:`dotshell.shipped`)."""
    from dotshell.shipped import resolve, unknown_hint

    path = resolve("layouts", name_or_path)
    if path.is_file():
        return path
    raise RunError(f"layout {name_or_path} does not exist. {unknown_hint('layouts')}")


def load_layout(name_or_path: str | Path) -> Layout:
    """Read and validate a layout file (raises :class:`ProfileError` / :class:`RunError`)."""
    path = resolve_layout_path(name_or_path)
    where = str(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RunError(f"{where}: not valid TOML ({exc}). Fix the layout file at that "
                       "place.") from None
    return layout_from_dict(raw, where)


def layout_from_dict(raw: dict[str, Any], where: str) -> Layout:
    """A layout from its parsed TOML tables (``layout``, ``decoder``), validated."""
    data = validate_settings(LAYOUT_SCHEMA, raw, where)
    lay = data["layout"]
    order = tuple(lay["order"])
    bad = [b for b in order if b not in BLOCKS]
    if bad or len(set(order)) != len(order) or "columns" not in order:
        raise RunError(f"{where}: [layout] order = {list(order)} is invalid: use each of "
                       f"{', '.join(BLOCKS)} at most once, with 'columns' present "
                       "(white and black are needed to find shadows).")
    if "white" not in order or "black" not in order:
        raise RunError(f"{where}: [layout] order must contain 'white' and 'black' frames.")
    _check_files_pattern(lay["files"], where)
    return Layout(where, lay["name"], lay["description"], lay["coding"], lay["files"],
                  lay["first_index"], (lay["projector_width"], lay["projector_height"]), order,
                  lay["inverse"], lay["msb_first"], lay["drop_low_bits"], lay["centred"],
                  lay["bright_is_one"], dict(data["decoder"]))


def _check_files_pattern(files: str, where: str) -> None:
    """``files`` has the one field ``{index}`` (with an integer format, if any), so every
    frame's name can be made from it."""
    import string

    def refuse(what: str) -> RunError:
        return RunError(f"{where}: [layout] files = {files!r} is not a file-name pattern: "
                        f"{what}. Use only {{index}}, e.g. frameSeq_{{index:02d}}.bmp (a brace "
                        "that is part of the name is written twice).")

    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(files) if f is not None]
    except ValueError as exc:
        raise refuse(str(exc)) from None
    others = sorted({f"{{{f}}}" for f in fields if f != "index"})
    if others:
        raise refuse(f"{', '.join(others)} {'is' if len(others) == 1 else 'are'} not {{index}}")
    if not fields:
        raise refuse("it needs an {index} field")
    try:
        files.format(index=0)
    except (ValueError, TypeError) as exc:
        raise refuse(f"{{index}} cannot be formatted ({exc})") from None


def capture_order(layout: Layout, coding_names: list[str]) -> list[str]:
    """Coding frame names (``white``, ``col_00``, ``col_00_inv`` ...) in capture order."""
    prefix = {"columns": "col", "rows": "row"}
    out: list[str] = []
    for block in layout.order:
        if block in ("white", "black"):
            out.append(block)
            continue
        bits = sorted(n for n in coding_names
                      if n.startswith(prefix[block] + "_") and not n.endswith("_inv"))
        if not layout.msb_first:
            bits = bits[::-1]
        for b in bits:
            out += [b, b + "_inv"] if layout.inverse else [b]
    return out


def _glob_pattern(files: str) -> re.Pattern:
    parts = re.split(r"\{index[^}]*\}", files)
    return re.compile("^" + r"\d+".join(re.escape(p) for p in parts) + "$")


def read_gray(path: Path) -> tuple[np.ndarray, str]:
    """The frame as one grey channel, and what the file held (e.g. ``uint16, 1 channel``)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise RunError(f"{path}: cannot be read as an image (is it a PNG/BMP/TIFF?).")
    channels = img.shape[2] if img.ndim == 3 else 1
    kind = f"{img.dtype}, {channels} channel{'s' if channels > 1 else ''}"
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return img, kind


def _one_kind(directory: Path, kinds: dict[str, str]) -> None:
    """All frames of a sequence have one bit depth and one channel count: a 16-bit frame among
    8-bit ones would be decoded against thresholds of the wrong scale, without a word."""
    first_name, first = next(iter(kinds.items()))
    odd = [f"{fn} ({k})" for fn, k in kinds.items() if k != first]
    if odd:
        raise RunError(f"{directory}: frames differ in bit depth or channels: {first_name} is "
                       f"{first} but {', '.join(odd[:6])}{' …' if len(odd) > 6 else ''}. All "
                       "frames of a sequence must come from one camera in one pixel format; "
                       "capture or convert them again alike.")


def _nothing_matches(directory: Path, layout: Layout, first: str) -> str:
    """The error when no file of ``directory`` matches the layout's ``files`` pattern: what the
    pattern expects, what the directory holds, and the two keys that say it."""
    held = sorted(p.name for p in directory.iterdir() if p.is_file())
    shown = ", ".join(held[:5]) + (" …" if len(held) > 5 else "") if held else "no files"
    return (f"{directory}: no file matches the files = {layout.files!r} of layout "
            f"{layout.name!r} "
            f"(its first frame would be {first}, from first_index = {layout.first_index}); the "
            f"directory holds {shown}. Set [layout] files (and first_index, the number of the "
            f"first frame) to your files' names in a copy of {layout.source} and pass it with "
            "--layout.")


def sequence_files(directory: Path, layout: Layout, order: list[str]) -> list[Path]:
    """The files of the sequence in ``directory``, in capture order; a missing frame or a file
    matching the layout's pattern that the layout does not expect is an error naming them."""
    directory = Path(directory)
    if not directory.is_dir():
        raise RunError(f"captures directory {directory} does not exist.")
    rx = _glob_pattern(layout.files)
    present = sorted(p.name for p in directory.iterdir() if rx.match(p.name))
    expected = [layout.file_name(i) for i in range(len(order))]
    if not present:
        raise RunError(_nothing_matches(directory, layout, expected[0]))
    missing = [n for n in expected if n not in present]
    extra = [n for n in present if n not in expected]
    if missing or extra:
        raise RunError(
            f"{directory}: layout {layout.name!r} ({layout.source}) expects {len(order)} frames "
            f"{expected[0]} … {expected[-1]} ({', '.join(order)}), but the directory has "
            f"{len(present)} files matching {layout.files!r}"
            + (f"; missing: {', '.join(missing[:6])}{' …' if len(missing) > 6 else ''}" if missing else "")
            + (f"; not in the layout: {', '.join(extra[:6])}{' …' if len(extra) > 6 else ''}" if extra else "")
            + ". Check the layout's files and first_index (the names), order, inverse, "
            "drop_low_bits and projector size.")
    return [directory / fn for fn in expected]


def read_captures(directory: Path, layout: Layout, coding_names: list[str]) -> dict[str, np.ndarray]:
    """The frames of ``directory`` by coding frame name; checks count, names, sizes, bit depth
    and channel count."""
    order = capture_order(layout, coding_names)
    files = sequence_files(directory, layout, order)
    expected = [f.name for f in files]
    read = {name: read_gray(f) for name, f in zip(order, files)}
    _one_kind(directory, {fn: read[name][1] for name, fn in zip(order, expected)})
    frames = {name: img for name, (img, _) in read.items()}
    shapes = {fn: frames[name].shape for name, fn in zip(order, expected)}
    first = shapes[expected[0]]
    odd = [f"{fn} ({s[1]}x{s[0]})" for fn, s in shapes.items() if s != first]
    if odd:
        raise RunError(f"{directory}: frames differ in size: {expected[0]} is "
                       f"{first[1]}x{first[0]} px but {', '.join(odd[:6])}. All frames of a "
                       "sequence must come from one camera at one resolution.")
    return frames


def to_coding_frames(frames: dict[str, np.ndarray], layout: Layout,
                     coding_names: list[str]) -> list[np.ndarray]:
    """Frames in the coding's order with bit 1 = lit (the layout's polarity undone)."""
    if not layout.bright_is_one:
        if layout.inverse:  # swapping pattern and inverse flips every bit
            frames = dict(frames)
            for n in [n for n in frames if n.startswith(("col_", "row_")) and not n.endswith("_inv")]:
                frames[n], frames[n + "_inv"] = frames[n + "_inv"], frames[n]
        else:  # mirror each bit frame about the pixel's (white + black) / 2
            import numpy as np

            wb = frames["white"].astype(np.int64) + frames["black"].astype(np.int64)
            top = np.iinfo(frames["white"].dtype).max if frames["white"].dtype.kind in "ui" else None
            frames = {n: f if n in ("white", "black") else
                      np.clip(wb - f, 0, top).astype(f.dtype) for n, f in frames.items()}
    return [frames[n] for n in coding_names]


@dataclass
class CaptureSequence:
    """One capture sequence read through its layout: the coding that decodes it and its frames
    in the coding's order (bit 1 = lit)."""

    layout: Layout
    coding: Any
    frames: list[np.ndarray]

    @property
    def camera_size(self) -> tuple[int, int]:
        h, w = self.frames[0].shape[:2]
        return (w, h)


def coding_frame_names(coding, projector_size: tuple[int, int]) -> list[str]:
    """The coding's frame names in its own order, without rendering the patterns."""
    if hasattr(coding, "frame_names"):
        return list(coding.frame_names(projector_size))
    return [f.name for f in coding.patterns(projector_size)]


def layout_coding(layout: Layout, pm, axes: str | None = None):
    """The coding backend the layout names, set up to decode its frames."""
    settings = layout.coding_settings()
    if axes is not None:
        settings["axes"] = axes
    return pm.create("coding", layout.coding, settings, None, layout.source)


def read_sequence(captures: Path | str, layout: Layout, pm) -> CaptureSequence:
    """Read a capture directory through its layout (see :func:`read_captures`)."""
    coding = layout_coding(layout, pm)
    names = coding_frame_names(coding, layout.projector_size)
    frames = to_coding_frames(read_captures(Path(captures), layout, names), layout, names)
    return CaptureSequence(layout, coding, frames)
