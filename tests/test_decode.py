"""`dotshell decode`: per-pixel projector column and row maps (float32 TIFF / NPY, NaN where not
decoded), the mask with reasons, the counts and previews — for captures made elsewhere (through
a layout) and for every view of a dotshell run."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import opencv_graycode
from conftest import ROOT
from dotshell.cli.app import main
from dotshell.pipeline.decode_maps import decode_captures, decode_run, read_map

SKULL = next((p / "shared" / "data" / "slstudio-skull" for p in (ROOT.parent, ROOT.parents[1])
              if (p / "shared" / "data" / "slstudio-skull").is_dir()), None)


def _opencv_captures(tmp: Path, proj=(100, 37), cam=(160, 60)) -> tuple[Path, Path, np.ndarray]:
    """OpenCV's sequence seen by a camera that sees the projector stretched, with a dark
    (unlit) band on the left; returns the directory, a layout for it and the true columns."""
    d = tmp / "caps"
    truth = opencv_graycode.write_stretched(d, proj, cam, dark_columns=12)
    return d, opencv_graycode.layout_file(tmp / "opencv.toml", proj), truth


@pytest.mark.parametrize("fmt", ["tiff", "npy"])
def test_decode_captures_writes_maps_mask_and_previews(tmp_path, pm, fmt):
    d, layout, truth = _opencv_captures(tmp_path)
    res = decode_captures(d, layout, pm, tmp_path / "out", fmt)
    r = json.loads((res.out_dir / "report.json").read_text())
    column = read_map(res.out_dir / r["files"]["column"])
    row = read_map(res.out_dir / r["files"]["row"])
    mask = cv2.imread(str(res.out_dir / "mask.png"), cv2.IMREAD_UNCHANGED)
    assert column.dtype == row.dtype == np.float32 and column.shape == mask.shape == (60, 160)
    names = {int(k): v for k, v in r["reasons"].items()}
    assert names[0] == "decoded"
    shadow = [k for k, v in names.items() if v == "shadow"][0]
    assert (mask[:, :10] == shadow).all()
    ok = mask == 0
    assert np.isnan(column[~ok]).all() and np.isnan(row[~ok]).all()
    assert np.isfinite(column[ok]).all() and ok.sum() == r["counts"]["decoded"]
    assert np.abs(column - truth[None, :])[ok].max() < 1.0
    counts = np.bincount(mask.ravel(), minlength=len(names))
    assert all(counts[k] == r["counts"][v] for k, v in names.items())
    for p in ("frame", "columns", "rows", "mask"):
        assert cv2.imread(str(res.out_dir / r["previews"][p])) is not None


def test_decode_cli_prints_every_loss(tmp_path, capsys):
    d, layout, _ = _opencv_captures(tmp_path)
    assert main(["decode", "--captures", str(d), "--layout", str(layout), "--out",
                 str(tmp_path / "o"), "--format", "npy"]) == 0
    text = capsys.readouterr().out
    assert "decoded" in text and "shadow" in text and "column/row maps" in text
    assert main(["decode", "--captures", str(d)]) == 2
    assert "needs --layout" in capsys.readouterr().err


def test_decode_run_writes_every_view(small_scan, tmp_path, pm):
    run = small_scan[0].run_dir
    res = decode_run(run, pm, tmp_path / "decoded")
    assert res.out_dir.parent == tmp_path / "decoded" and run.name in res.out_dir.name
    views = res.report["views"]
    assert sorted(views) == [f"view_{i:03d}" for i in range(6)]
    v = views["view_000"]
    column = read_map(res.out_dir / "view_000" / v["files"]["column"])
    assert np.isfinite(column).sum() == v["counts"]["decoded"] > 1000
    report = json.loads((run / "report.json").read_text())
    assert v["counts"]["decoded"] == report["views"][0]["decoded"]  # the scan's own decode
    assert (res.out_dir / "view_005" / "row.tiff").is_file()


@pytest.mark.skipif(SKULL is None, reason="shared/data/slstudio-skull is not present")
def test_decode_slstudio_skull(tmp_path, pm):
    res = decode_captures(SKULL / "skull_gray", "slstudio-graycode", pm, tmp_path)
    r = res.report
    column = read_map(res.out_dir / "column.tiff")
    assert column.shape == (1352, 1688) and "row" not in r["files"]  # SLStudio: columns only
    assert np.isfinite(column).sum() == r["counts"]["decoded"] == 431698
    assert np.nanmin(column) >= 0 and np.nanmax(column) <= 1823
