"""A view's frames kept as they come (`dotshell.pipeline.view_frames.ViewFrames`, issue 33):
the pattern images and the integrity verdict are those made from all the frames at once, while
at most one image per pattern is held (with PDI, half the view's frames)."""

from __future__ import annotations

import numpy as np
import pytest

from dotshell.coding import PatternFrame
from dotshell.pipeline.pdi import combine, plan_shots
from dotshell.pipeline.view_frames import ViewFrames
from dotshell.run.integrity import check_view

SHAPE = (512, 640)  # above SAMPLE_PIXELS: the checks compare every 3rd pixel


def _view(pdi: bool) -> tuple[list, list[np.ndarray]]:
    """(shot plan, frames in its order) of white, black and 4 column pairs: noisy, as a sensor's."""
    rng = np.random.default_rng(7)
    white = rng.integers(1500, 3000, SHAPE).astype(np.uint16)
    black = rng.integers(0, 50, SHAPE).astype(np.uint16)
    images = [white, black]
    names = ["white", "black"]
    for k in range(4):
        lit = np.broadcast_to((np.arange(SHAPE[1]) // (64 >> k)) % 2 == 0, SHAPE)
        images += [np.where(lit, white, black), np.where(lit, black, white)]
        names += [f"col_{k:02d}", f"col_{k:02d}_inv"]
    patterns = [PatternFrame(n, np.zeros((2, 2), np.uint8)) for n in names]
    shots = plan_shots(patterns, {"pdi": pdi, "pdi_angles_deg": [0.0, 90.0]})
    frames = []
    for s in shots:  # the crossed analyzer passes a little of the light, with its own noise
        scale = 0.3 if s.analyzer_deg == 90.0 else 1.0
        noise = rng.integers(0, 3, SHAPE)
        frames.append((images[s.pattern] * scale + noise).astype(np.uint16))
    return shots, frames


def _collect(shots, frames) -> tuple[ViewFrames, int]:
    """The frames added one by one; the most image bytes the collector held at once."""
    kept = ViewFrames(shots)
    most = 0
    for frame in frames:
        kept.add(frame)
        held = {id(a): a.nbytes for a in kept._images if a is not None}
        most = max(most, sum(held.values()))
    return kept, most


@pytest.mark.parametrize("pdi", [True, False])
def test_pattern_images_are_those_of_all_the_frames_with_one_image_per_pattern_held(pdi):
    shots, frames = _view(pdi)
    kept, most = _collect(shots, frames)
    images, first = kept.images()
    want = combine(frames, shots)
    assert first is frames[0] and len(images) == len(want) == 10
    assert all(got.dtype == w.dtype and np.array_equal(got, w) for got, w in zip(images, want))
    assert most <= len(want) * frames[0].nbytes  # with PDI: half of the view's 20 frames


def test_an_incomplete_view_has_no_images():
    shots, frames = _view(True)
    kept, _ = _collect(shots, frames[:-1])
    with pytest.raises(ValueError, match="19 frames of a plan of 20"):
        kept.images()


@pytest.mark.parametrize("spoil", ["clean", "stale pair", "repeat", "swap"])
def test_the_integrity_verdict_is_that_of_the_whole_frames(spoil):
    shots, frames = _view(True)
    names = [s.name for s in shots]
    at = names.index
    if spoil == "stale pair":
        frames[at("col_02.perp")] = frames[at("col_01.perp")].copy()
    elif spoil == "repeat":
        frames[at("col_03.par")] = frames[at("col_02_inv.par")]
    elif spoil == "swap":
        w, b = at("white.perp"), at("black.perp")
        frames[w], frames[b] = frames[b], frames[w]
    infos = [{"frame_id": i, "timestamp_s": float(i)} for i in range(len(frames))]
    kept, _ = _collect(shots, frames)
    got = kept.integrity(4095.0, infos)
    want = check_view(frames, names, 4095.0, infos)
    assert got.to_dict() == want.to_dict()
    assert got.ok == (spoil == "clean") and got.pairs == want.pairs > 0
