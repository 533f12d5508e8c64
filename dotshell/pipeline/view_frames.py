"""A view's frames kept, as they are captured, as what the view needs afterwards: one image
per pattern for its reconstruction (with PDI, ``|I∥ − I⊥|`` made as soon as a pattern's second
frame arrives), the first frame for its preview, and the pixel samples and repeats its
integrity check reads (:func:`dotshell.run.integrity.check_view`).

Why (issue 33): the acquisition held every frame of the view being captured and then made the
pattern images from them, 84 frames and 42 images of a full-resolution PDI view (~0.3 GB) at
the hand-over. The frames themselves are on disk as they come (the acquisition's writer);
this holds at most one image per pattern (42 of 2.5 MiB) and samples of 0.2 MiB a frame.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from dotshell.pipeline.pdi import Shot, difference
from dotshell.run.integrity import ViewIntegrity, check_view, sample

#: (one image per pattern, the view's first frame): what a view's reconstruction needs
PatternImages = tuple[list[np.ndarray], np.ndarray | None]


class ViewFrames:
    """The frames of one view as they are added in the shot order of ``shots``."""

    def __init__(self, shots: Sequence[Shot]) -> None:
        self.shots = list(shots)
        self._images: list[np.ndarray | None] = [None] * (max((s.pattern for s in shots),
                                                                default=-1) + 1)
        self._first: np.ndarray | None = None
        self._previous: np.ndarray | None = None
        self.samples: list[np.ndarray] = []  #: each frame's integrity sample
        self.repeats: list[int] = []  #: frames identical to the one before them

    def __len__(self) -> int:
        """Frames added so far."""
        return len(self.samples)

    def add(self, frame: np.ndarray) -> None:
        """The next frame of the shot plan (a frame beyond it raises IndexError)."""
        shot = self.shots[len(self)]
        if self._previous is not None and np.array_equal(frame, self._previous):
            self.repeats.append(len(self))
        self._previous = frame
        self.samples.append(sample(frame))
        if self._first is None:
            self._first = frame
        held = self._images[shot.pattern]
        self._images[shot.pattern] = frame if held is None else difference(held, frame)

    def integrity(self, full_scale: float, infos: Sequence[dict] | None = None
                  ) -> ViewIntegrity:
        """The view's integrity verdict (the same as :func:`check_view` of its frames)."""
        return check_view(self.samples, [s.name for s in self.shots], full_scale, infos,
                          repeats=self.repeats)

    def images(self) -> PatternImages:
        """(one image per pattern, the first frame) of the complete view, as
        :func:`dotshell.pipeline.pdi.combine` makes them from all its frames."""
        if len(self) != len(self.shots):
            raise ValueError(f"{len(self)} frames of a plan of {len(self.shots)}: the view is "
                             "incomplete")
        self._previous = None
        return [im for im in self._images if im is not None], self._first
