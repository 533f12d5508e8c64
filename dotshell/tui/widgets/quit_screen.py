"""What quitting during a scan does: leave it running on the server (this terminal detaches),
stop it (frames kept, run ``aborted``) and quit, or stay."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Static

CHOICES = ("leave", "stop")


class QuitScreen(ModalScreen[str | None]):
    """Dismisses with ``leave``, ``stop`` or None (stay)."""

    BINDINGS = [Binding("l", "choose('leave')", "Leave it running"),
                Binding("s", "choose('stop')", "Stop it and quit"),
                Binding("escape,n", "choose('')", "Stay")]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        with Vertical(classes="dialog"):
            yield Static(self.question, classes="question")
            with Horizontal(classes="buttons"):
                yield Button("Leave it running (l)", variant="primary", id="leave")
                yield Button("Stop it and quit (s)", variant="error", id="stop")
                yield Button("Stay (esc)", id="stay")

    def on_mount(self) -> None:
        self.query_one("#leave", Button).focus()

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id if event.button.id in CHOICES else None)

    def action_choose(self, choice: str) -> None:
        self.dismiss(choice or None)
