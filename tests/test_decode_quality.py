"""A view's decode quality (issue 27): the decoded share and the neighbour reversals, an estimate
of the wrong codes — one definition (dotshell.pipeline.decode_quality) for `dotshell decode`,
every view of a scan, resume and reconstruction, and `reconstruct --captures`; recorded in the
reports and printed per view with the fix when a share is poor."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import small_profile_dict

from dotshell.coding import Correspondence
from dotshell.pipeline.decode_quality import (NOTE_REVERSALS_PCT, REVERSAL_STEP_PX,
                                              neighbour_reversals, view_notes, view_quality)
from dotshell.runtime.parallel import threads


def reference_reversals(coord: np.ndarray, valid: np.ndarray) -> int:
    """The definition in plain numpy (docs/codings.md#decode-quality): per image axis the
    steps between adjacent valid pixels (float32), their sum in truncated 1/256 px; the axis of
    the larger mean |step| (x on a tie) counts the steps of more than 1.5 px against the sum's
    sign."""
    best: tuple[float, int] | None = None
    for axis in (1, 0):  # image x first: it wins a tie
        d = np.diff(coord.astype(np.float32), axis=axis)
        both = (valid[:, 1:] & valid[:, :-1]) if axis == 1 else (valid[1:] & valid[:-1])
        steps = d[both]
        if steps.size == 0:
            continue
        total = int(np.trunc(steps * np.float32(256.0)).astype(np.int64).sum())
        slope = abs(total) / steps.size
        if best is None or slope > best[0]:
            back = steps < -REVERSAL_STEP_PX if total >= 0 else steps > REVERSAL_STEP_PX
            best = (slope, int(np.count_nonzero(back)))
    return 0 if best is None else best[1]


def _ramp_with_noise(rng, shape=(97, 131), slope=(0.8, 0.05), wrong=0.02):
    """A column-like map (slope px per pixel along x and y) with ``wrong`` of its pixels
    given random codes and a ragged mask of decoded pixels (NaN elsewhere)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    coord = (slope[0] * x + slope[1] * y + rng.normal(0, 0.2, shape)).astype(np.float32)
    bad = rng.random(shape) < wrong
    coord[bad] = rng.uniform(0, slope[0] * w, int(bad.sum()))
    valid = rng.random(shape) > 0.15
    coord[~valid] = np.nan
    return coord, valid


def test_the_compiled_pass_counts_what_the_definition_says():
    """Against the plain-numpy definition: noisy ramps with random wrong codes and holes, the
    stripes along x or y, rising or falling, on one thread and on two (the bands' integer
    sums are the same in any order)."""
    rng = np.random.default_rng(27)
    for k in range(12):
        coord, valid = _ramp_with_noise(rng, slope=(0.8 + 0.3 * (k % 3), 0.05))
        if k % 2:
            coord = coord[:, ::-1].copy()
            valid = valid[:, ::-1].copy()
        if k % 4 >= 2:
            coord, valid = coord.T.copy(), valid.T.copy()
        want = reference_reversals(coord, valid)
        for n in (1, 2):
            with threads(n):
                assert neighbour_reversals(coord, valid) == want > 0, (k, n)
    empty = np.zeros((5, 5), bool)
    assert neighbour_reversals(np.full((5, 5), np.nan, np.float32), empty) == 0


def test_reversals_count_isolated_wrong_codes_and_a_patch_exactly():
    """On a clean ramp: none; each isolated wrong code one reversal; a patch of codes set back
    one per patch row (its leading edge) — whichever way and along whichever axis the stripes
    run."""
    col = np.tile(np.arange(60, dtype=np.float32) * 0.8, (40, 1))
    valid = np.ones(col.shape, bool)
    assert neighbour_reversals(col, valid) == 0
    bad = col.copy()
    bad[5, 10] += 30.0
    bad[12, 30] -= 25.0
    bad[20:27, 40:50] -= 20.0  # 7 rows
    for coord, ok in ((bad, valid), (bad[:, ::-1], valid), (bad.T, valid.T),
                      (-bad, valid)):
        assert neighbour_reversals(np.ascontiguousarray(coord), np.ascontiguousarray(ok)) == 9


def _decoded_view(run: Path, pm, view: int = 0) -> Correspondence:
    """A view of a run decoded as `dotshell decode` decodes it."""
    from dotshell.pipeline.decode_maps import _projector_size
    from dotshell.pipeline.pdi import combine, shots_from_manifest
    from dotshell.pipeline.scan import load_run_profile
    from dotshell.run.store import RunStore

    store = RunStore.open(run)
    c = load_run_profile(store, pm).required_role("coding")
    coding = pm.create("coding", c["backend"], c["settings"], None, None)
    frames = combine(store.read_frames(view), shots_from_manifest(store.manifest))
    return coding.decode(frames, _projector_size(store))


def _clean_spots(corr: Correspondence, n: int, margin: int = 3) -> list[tuple[int, int]]:
    """``n`` decoded pixels, 8 px apart or more, whose (2·margin+1)² neighbourhood is decoded
    and steps by less than 1 projector px in both maps (no reversal near them)."""
    from scipy.ndimage import binary_erosion

    smooth = corr.valid.copy()
    for m in (corr.column, corr.row):
        filled = np.where(corr.valid, m, 0.0)
        smooth[:, 1:] &= np.abs(np.diff(filled, axis=1)) < 1.0
        smooth[:, :-1] &= np.abs(np.diff(filled, axis=1)) < 1.0
        smooth[1:] &= np.abs(np.diff(filled, axis=0)) < 1.0
        smooth[:-1] &= np.abs(np.diff(filled, axis=0)) < 1.0
    inner = binary_erosion(smooth, np.ones((2 * margin + 1,) * 2, bool))
    spots: list[tuple[int, int]] = []
    for y, x in zip(*np.nonzero(inner)):
        if all(max(abs(y - a), abs(x - b)) >= 8 for a, b in spots):
            spots.append((int(y), int(x)))
            if len(spots) == n:
                return spots
    raise AssertionError(f"only {len(spots)} clean spots in the view")


def test_wrong_codes_injected_into_a_decoded_view_are_counted_exactly(small_scan, pm):
    """A decoded view of the simulated scan, then wrong codes put into its maps: 10 isolated
    column codes 40 px off, 5 isolated row codes, and a 6-row patch of columns set 50 px back.
    The reversals rise by exactly 10 + 5 + 6; the decoded share stays."""
    corr = _decoded_view(small_scan[0].run_dir, pm)
    clean = view_quality(corr)
    assert clean["decoded_pct"] == round(100 * corr.valid.mean(), 2)
    assert clean["reversals"] == (reference_reversals(corr.column, corr.valid)
                                  + reference_reversals(corr.row, corr.valid))
    spots = _clean_spots(corr, 16)
    column, row = corr.column.copy(), corr.row.copy()
    for y, x in spots[:10]:
        column[y, x] += 40.0
    for y, x in spots[10:15]:
        row[y, x] -= 40.0
    y, x = spots[15]
    column[y - 3:y + 3, x - 1:x + 2] -= 50.0  # 6 rows, 3 wide: one leading edge per row
    bad = view_quality(Correspondence(column, row, corr.valid))
    print(clean, bad)
    assert bad["reversals"] == clean["reversals"] + 21
    assert bad["decoded_pct"] == clean["decoded_pct"]


def test_every_view_of_a_scan_records_its_quality_as_decode_measures_it(small_scan, pm,
                                                                        tmp_path):
    """The scan's report and each view's record hold decoded_pct, reversals, reversals_pct;
    `dotshell decode` of the same run gives the same figures (one definition), and each
    ViewReconstructed event carries them; the time it took is in the view's seconds."""
    from dotshell.events import ViewReconstructed
    from dotshell.pipeline.decode_maps import decode_run

    result, events = small_scan
    report = json.loads((result.run_dir / "report.json").read_text())
    decoded = decode_run(result.run_dir, pm, tmp_path / "decoded").report["views"]
    seen = {ev.view: ev for ev in events if isinstance(ev, ViewReconstructed)}
    assert len(report["views"]) == len(seen) == 6
    for v in report["views"]:
        q = v["quality"]
        assert set(q) == {"decoded_pct", "reversals", "reversals_pct"}
        assert q["decoded_pct"] == round(100 * v["decoded"] / v["pixels"], 2) > 10
        assert q == decoded[f"view_{v['view']:03d}"]["quality"]
        ev = seen[v["view"]]
        assert (ev.decoded_pct, ev.reversals, ev.reversals_pct) == (
            q["decoded_pct"], q["reversals"], q["reversals_pct"])
        record = json.loads((result.run_dir / "views" / f"view_{v['view']:03d}.json")
                            .read_text())
        assert record["quality"] == q and "quality" in record["seconds"]
    assert "quality" in report["timings_s"]


def test_notes_name_the_fix_when_a_share_is_poor():
    """Around an object the unlit background is shadow: named only when almost nothing
    decoded; a decoder loss from 5 % of the image; reversals from 1 % of the decoded."""
    stats = {"pixels": 1000, "decoded": 400, "shadow": 500, "uncertain": 60, "row_rejected": 3}
    q = {"decoded_pct": 40.0, "reversals": 2, "reversals_pct": 0.5}
    assert view_notes(stats, q) == (("uncertain", 6.0),)
    dark = {"pixels": 1000, "decoded": 30, "shadow": 960}
    assert view_notes(dark, {"decoded_pct": 3.0, "reversals_pct": 0.0}) == (("shadow", 96.0),)
    wrong = {**q, "reversals": 8, "reversals_pct": 2.0}
    assert view_notes(stats, wrong) == (("uncertain", 6.0), ("reversals", 2.0))
    assert view_notes({"decoded": 5}, wrong) == (("reversals", 2.0),)  # no pixel count
    from dotshell.pipeline.decode_quality import _DECODE_LOSSES
    from dotshell.pipeline.reconstruct import LOSSES

    assert set(_DECODE_LOSSES) <= set(LOSSES)  # each note has its meaning and fix


def test_the_per_view_line_says_the_figures_and_the_fix_once():
    """The scan's progress prints each view's points, decoded share and reversals; a problem's
    meaning and fix the first time a view has it, its share on every view that has it."""
    from rich.console import Console

    from dotshell.cli.common import ScanProgress
    from dotshell.events import ViewReconstructed

    console = Console(file=io.StringIO(), width=80, highlight=False)
    progress = ScanProgress(console)
    notes = (("uncertain", 27.0), ("reversals", 1.25))
    for view in (0, 1):
        progress(ViewReconstructed(view=view, n_points=5120, decoded_pixels=9000,
                                   decoded_pct=38.1 + view, reversals=113,
                                   reversals_pct=1.25, notes=notes))
    progress(ViewReconstructed(view=2, n_points=10, decoded_pixels=20))  # an older event
    lines = console.file.getvalue().splitlines()
    assert lines[0] == ("  view   1:     5120 points; decoded 38.1 % of the image, 113 neighbour "
                        "reversals (1.25 % of decoded); uncertain 27.0 %")
    assert lines[1].startswith("    uncertain (27.0 %): the robust classification")
    assert '[coding.settings]' in lines[1]  # printed as it is, not read as markup
    assert lines[2].startswith("    neighbour reversals (1.25 % of the decoded pixels): ")
    assert 'classification = "contrast"' in lines[2]
    assert lines[3].startswith("  view   2:     5120 points; decoded 39.1 %")
    assert lines[4] == "  view   3:       10 points" and len(lines) == 5
    from dotshell.server.describe import describe_event  # a detached scan's log line

    line = ("view 1 reconstructed: 5120 points (9000 decoded pixels, 38.1 % of the image; "
            "113 neighbour reversals)")
    assert describe_event(ViewReconstructed(view=0, n_points=5120, decoded_pixels=9000,
                                            decoded_pct=38.1, reversals=113,
                                            reversals_pct=1.25)) == ("info", line)


def test_reconstruct_captures_records_and_prints_the_quality(tmp_path, capsys):
    """`reconstruct --captures` of a sequence made elsewhere (OpenCV's, rendered by the
    simulated rig at 0.12x) records the pose's quality and prints it; `decode --captures`
    of the same files gives the same figures."""
    import opencv_graycode
    from sim_sequences import connected_rig, render_sequence

    from dotshell.cli.app import main

    rig = connected_rig(small_profile_dict(factor=0.12, views=1))
    w, h = rig["projector"].resolution
    layout = opencv_graycode.layout_file(tmp_path / "layout.toml", (w, h))
    caps = render_sequence(rig, opencv_graycode.capture_sequence(w, h), tmp_path / "caps",
                           opencv_graycode.file_name)
    calib = tmp_path / "calibration.json"
    rig["camera"].ground_truth_calibration().save(calib)
    assert main(["reconstruct", "--captures", str(caps), "--calibration", str(calib),
                 "--layout", str(layout), "--out", str(tmp_path / "rec")]) == 0
    text = capsys.readouterr().out
    report = json.loads(next((tmp_path / "rec").rglob("report.json")).read_text())
    q = report["quality"]
    assert (f"decoded {q['decoded_pct']:.1f} % of the image; estimated wrong codes: "
            f"{q['reversals']} neighbour reversals") in " ".join(text.split())
    assert q["decoded_pct"] == round(100 * report["decode"]["decoded"]
                                     / report["decode"]["pixels"], 2)
    assert main(["decode", "--captures", str(caps), "--layout", str(layout), "--out",
                 str(tmp_path / "dec"), "--format", "npy"]) == 0
    decoded = json.loads(next((tmp_path / "dec").rglob("report.json")).read_text())
    assert decoded["quality"] == q
    assert report["timings_s"]["quality"] >= 0


@pytest.mark.parametrize("share", [0.5, 2.0])
def test_decode_prints_the_reversal_note_from_its_share(share):
    from dotshell.cli.decode import loss_notes

    counts = {"pixels": 1000, "decoded": 900}
    notes = loss_notes(counts, {"decoded_pct": 90.0, "reversals": 9, "reversals_pct": share})
    assert len(notes) == (share >= NOTE_REVERSALS_PCT)


def test_a_scan_prints_each_views_quality_and_the_fix_once(tmp_path, capsys):
    """`dotshell scan` of the tiny bench (2 views) under room light 1.5x the projector's with
    robust classification: a quarter of each view is left uncertain, so each view's line
    names the loss and the first one gives its meaning and fix; the report holds what the
    lines say."""
    from conftest import write_test_profile

    from dotshell.cli.app import main

    p = write_test_profile(tmp_path, views=2)
    assert main(["scan", str(p), "--out", str(tmp_path / "runs"), "--set",
                 'coding.settings.classification="robust"', "--set",
                 "camera.settings.ambient=1.5"]) == 0
    err = capsys.readouterr().err
    (run,) = (tmp_path / "runs").iterdir()
    report = json.loads((run / "report.json").read_text())
    for v in report["views"]:
        q, share = v["quality"], 100 * v["uncertain"] / v["pixels"]
        assert share >= 5.0  # measured 26.0 and 24.5 %
        assert (f"view {v['view'] + 1:3d}: {v['points']:8d} points; decoded "
                f"{q['decoded_pct']:.1f} % of the image, {q['reversals']} neighbour reversals "
                f"({q['reversals_pct']:.2f} % of decoded); uncertain {share:.1f} %") in err
    assert err.count("    uncertain (") == 1
    assert 'decode with classification = "adaptive"' in err
