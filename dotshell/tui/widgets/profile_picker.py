"""The profile picker: profiles found next to the current one, in ./profiles, in the
directories the user's config lists (``profile_dirs``, docs/server.md) and the shipped ones
(:mod:`dotshell.shipped`), or any path typed in;
Enter loads it."""

from __future__ import annotations

from pathlib import Path

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.screen import ModalScreen
from textual.widgets import Input, OptionList, Static

from dotshell.server.describe import short_path


def find_profiles(current: str | Path | None, extra_dirs: list[Path] | tuple[Path, ...] = ()) -> list[str]:
    """``*.toml`` next to ``current``, in ./profiles and in ``extra_dirs`` (sorted), then the
    shipped profiles by their bare names (sorted), each file once."""
    from dotshell.shipped import shipped_dir

    dirs = [Path("profiles"), *extra_dirs]
    if current is not None:
        dirs.insert(0, Path(current).parent)
    found: dict[Path, str] = {}
    for d in dirs:
        if d.is_dir():
            for p in sorted(d.glob("*.toml")):
                found.setdefault(p.resolve(), short_path(p))
    shipped = {p.resolve(): p.stem for p in shipped_dir("profiles").glob("*.toml")}
    return sorted(found.values()) + sorted(name for path, name in shipped.items()
                                           if path not in found)


class ProfilePicker(ModalScreen[str | None]):
    """Dismisses with the chosen profile path, or None."""

    BINDINGS = [Binding("escape", "cancel", "Cancel")]

    def __init__(self, current: str | None, extra_dirs: list[Path] | tuple[Path, ...] = ()) -> None:
        super().__init__()
        self.paths = find_profiles(current, list(extra_dirs))
        self.current = short_path(current) if current else None

    def compose(self) -> ComposeResult:
        with Vertical(classes="dialog", id="picker"):
            yield Static("[b]Load a profile[/] — choose one, or type a path and press Enter",
                         classes="question")
            yield OptionList(*self.paths, id="profile-list")
            yield Input(placeholder="path/to/profile.toml", id="profile-path")

    def on_mount(self) -> None:
        options = self.query_one(OptionList)
        if self.current in self.paths:
            options.highlighted = self.paths.index(self.current)
        (options if self.paths else self.query_one(Input)).focus()

    def on_option_list_option_selected(self, event: OptionList.OptionSelected) -> None:
        self.dismiss(self.paths[event.option_index])

    def on_input_submitted(self, event: Input.Submitted) -> None:
        self.dismiss(event.value.strip() or None)

    def action_cancel(self) -> None:
        self.dismiss(None)
