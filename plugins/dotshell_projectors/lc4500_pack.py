"""``python -m dotshell_projectors.lc4500_pack PROFILE OUT_DIR``: write the packed images of
PROFILE's coding at 912 × 1140 as ``OUT_DIR/lc4500_NN.png`` (24-bit RGB) for a LightCrafter
4500's flash, and print the ``flash_images`` line for the profile (docs/hardware.md)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

from dotshell_projectors.dlpc350 import HEIGHT, WIDTH
from dotshell_projectors.lc4500_images import pack, save


def main(argv: Sequence[str] | None = None) -> int:
    from dotshell.plugins import get_plugin_manager
    from dotshell.profile.loader import load_profile

    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 2:
        print("usage: python -m dotshell_projectors.lc4500_pack PROFILE OUT_DIR", file=sys.stderr)
        return 2
    pm = get_plugin_manager()
    profile = load_profile(args[0], pm)
    c = profile.role("coding")
    coding = pm.create("coding", c["backend"], c["settings"], None, profile.source)
    patterns = [p.image for p in coding.patterns((WIDTH, HEIGHT))]
    paths = save(pack(patterns), Path(args[1]))
    print(f"{len(patterns)} patterns in {len(paths)} images:")
    print("flash_images = [" + ", ".join(f'"{p}"' for p in paths) + "]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
