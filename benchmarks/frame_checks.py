"""What the frame-integrity checks (dotshell/run/integrity.py) cost per view: a 44-frame
Gray-code view (white, black, 21 pattern/inverse pairs) at the reference camera's 1280×1024,
12 bit, against one pass over the same frames (their sum in float32: the peer, measured in the
same run). Prints the figures; asserts nothing."""

from __future__ import annotations

import time

import numpy as np

from dotshell.run.integrity import check_view


def view(height: int = 1024, width: int = 1280, pairs: int = 21, seed: int = 0
         ) -> tuple[list[np.ndarray], list[str]]:
    """A synthetic view whose pairs add up to white + black (it passes the checks)."""
    rng = np.random.default_rng(seed)
    white = rng.integers(1500, 3000, (height, width)).astype(np.uint16)
    black = rng.integers(0, 50, (height, width)).astype(np.uint16)
    frames, names = [white, black], ["white", "black"]
    for k in range(pairs):
        lit = rng.random((height, width)) > 0.5
        frames += [np.where(lit, white, black), np.where(lit, black, white)]
        names += [f"col_{k:02d}", f"col_{k:02d}_inv"]
    return frames, names


def best_of(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    frames, names = view()
    checks = best_of(lambda: check_view(frames, names, 4095.0))
    one_pass = best_of(lambda: sum(f.astype(np.float32) for f in frames))
    print(f"frame checks of a {len(frames)}-frame 1280x1024 view: {checks:.3f} s; one pass over "
          f"its frames {one_pass:.3f} s ({checks / one_pass:.1f}x)")


if __name__ == "__main__":
    main()
