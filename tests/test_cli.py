"""The dotshell command: user errors are one paragraph with exit code 2, never a traceback."""

import json
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell.cli.app import main


def run_cli(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def _one_paragraph(err: str) -> str:
    assert "Traceback" not in err
    text = " ".join(err.split())
    assert text.startswith("error: ")
    return text


def test_missing_profile_file(capsys, tmp_path):
    code, _, err = run_cli(capsys, "check", str(tmp_path / "nope.toml"))
    assert code == 2 and "profile" in _one_paragraph(err) and "does not exist" in err


def test_toml_syntax_error_names_file(capsys, tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[scan\nviews = 3\n")
    code, _, err = run_cli(capsys, "check", str(p))
    assert code == 2 and "bad.toml: not valid TOML" in _one_paragraph(err)


@pytest.mark.parametrize("mutate, fragment", [
    (lambda r: r["scan"].update(viewz=3), "unknown key [scan.viewz]. Valid keys here: acquisition, angles_deg"),
    (lambda r: r["scan"].update(views="twelve"), "[scan.views] = 'twelve' is invalid: expected an integer"),
    (lambda r: r["camera"]["settings"].update(bit_depth=10), "[camera.settings.bit_depth] = 10 is not a valid choice"),
    (lambda r: r["camera"].update(backend="basler"), "[camera.backend] = 'basler' is not an installed camera backend. Valid choices: 'genicam', 'opencv', 'scientific', 'sim-camera'"),
    (lambda r: r.pop("stage"), "missing required key [stage]"),
    (lambda r: r["calibration"].update(source="file"), "[calibration] needs file ="),
])
def test_profile_errors_name_file_key_value_and_choices(capsys, tmp_path, mutate, fragment):
    raw = small_profile_dict()
    mutate(raw)
    p = write_profile(tmp_path / "p.toml", raw)
    code, _, err = run_cli(capsys, "check", str(p))
    text = _one_paragraph(err)
    assert code == 2 and str(p) in text and fragment in text


def test_missing_calibration_file(capsys, tmp_path):
    raw = small_profile_dict()
    raw["calibration"] = {"file": "cal/calibration.json"}
    p = write_profile(tmp_path / "p.toml", raw)
    code, _, err = run_cli(capsys, "check", str(p), "--connect")
    assert code == 2 and "calibration.json does not exist" in _one_paragraph(err)


def test_broken_plugin_warns_and_strict_mode_exits_2(capsys, tmp_path, broken_plugin):
    p = write_profile(tmp_path / "p.toml", small_profile_dict())
    code, out, err = run_cli(capsys, "check", str(p))
    assert code == 0 and "plugin 'broken'" in err and "needs libfoo.so" in err
    code, _, err = run_cli(capsys, "--strict-plugins", "check", str(p))
    assert code == 2 and "needs libfoo.so" in _one_paragraph(err)
    code, out, _ = run_cli(capsys, "plugins")
    assert code == 1 and "failed to load" in out and "sim-camera" in out


def test_check_connect_opens_every_device(capsys, tmp_path):
    p = write_profile(tmp_path / "p.toml", small_profile_dict())
    code, out, _ = run_cli(capsys, "check", str(p), "--connect")
    assert code == 0 and "all devices opened and closed" in out
    assert out.count("connected") >= 3 and "ground-truth" in out


def test_plugins_lists_roles_names_and_distributions(capsys):
    code, out, _ = run_cli(capsys, "plugins", "--settings")
    assert code == 0
    for word in ("camera", "sim-camera", "graycode", "dotshell 0.1.0", "focal_px"):
        assert word in out


def test_reconstruct_on_a_non_run_is_a_user_error(capsys, tmp_path):
    code, _, err = run_cli(capsys, "reconstruct", str(tmp_path))
    assert code == 2 and "not a dotshell run directory" in _one_paragraph(err)


def test_installed_command_scans_with_override_and_prints_table(tmp_path):
    """The real console script, as a user runs it (tiny bench, 3 views, 1 ray per pixel)."""
    raw = small_profile_dict(factor=0.2, views=3)
    raw["camera"]["settings"]["supersample"] = 1
    p = write_profile(tmp_path / "p.toml", raw)
    exe = [sys.executable, "-m", "dotshell.cli.app"]
    r = subprocess.run([*exe, "scan", str(p), "--out", str(tmp_path / "runs"),
                        "--set", "outputs.previews=false"],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Mean relative error" in r.stdout and "run:" in r.stdout
    runs = list((tmp_path / "runs").iterdir())
    assert len(runs) == 1 and (runs[0] / "cloud.ply").is_file()
    assert not (runs[0] / "previews").exists()


def test_installed_command_reconstructs_a_run_and_exits_with_its_status(small_scan, tmp_path):
    """`dotshell reconstruct` as a user runs it: the process ends without the interpreter's
    teardown (dotshell.runtime.process.exit_now), yet everything is there — the published report
    with the same cloud and figures, the previews, the printed table through a pipe — and a
    user error still exits 2. Paths print whole, one per line, as they are: longer than the
    pipe's 80 columns and with brackets (rich markup) in a directory name."""
    before = json.loads((small_scan[0].run_dir / "current" / "report.json").read_text())
    parent = tmp_path / "[agar] phantom, second day, analyzer at 90 degrees [/bold]"
    run = shutil.copytree(small_scan[0].run_dir, parent / "run", symlinks=True)
    exe = [sys.executable, "-m", "dotshell.cli.app"]
    r = subprocess.run([*exe, "reconstruct", str(run)], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.rstrip().splitlines()
    assert "Mean relative error" in r.stdout and lines[-1] == f"run: {run}  (status: completed)"
    assert f"cloud: {before['cloud']['points']} points → {run / 'cloud.ply'}" in lines
    for v in before["views"]:  # each view's line, as the scan printed it: figures unchanged
        q = v["quality"]
        assert (f"view {v['view'] + 1:3d}: ") in r.stderr
        assert (f"decoded {q['decoded_pct']:.1f} % of the image, {q['reversals']} neighbour "
                f"reversals ({q['reversals_pct']:.2f} % of decoded)") in r.stderr
    report = json.loads((run / "current" / "report.json").read_text())
    assert report["generation"] == before["generation"] + 1
    assert report["cloud"]["points"] == before["cloud"]["points"] > 0
    for key in ("mean_rel_error_pct", "std_rel_error_pct", "coverage_pct"):
        assert report["validation"][key] == before["validation"][key]
    assert [v["quality"] for v in report["views"]] == [v["quality"] for v in before["views"]]
    assert set(report["previews"]) == set(before["previews"]) >= {"cloud", "columns", "frame"}
    assert all((run / "current" / p).stat().st_size > 1000 for p in report["previews"].values())
    r = subprocess.run([*exe, "reconstruct", str(tmp_path / "nothing")], capture_output=True,
                       text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 2 and "error:" in r.stderr and "Traceback" not in r.stderr


def test_imports_ahead_start_with_the_step_that_makes_their_last_input():
    """While the cloud is merged, the validation's module is imported in the background (its
    last input is the cloud); no other step starts it."""
    from dotshell.pipeline.steps import import_ahead

    names = ["calibration", "views", "cloud", "validation", "previews"]
    assert import_ahead(names, "views") is None and import_ahead(names, "previews") is None
    assert import_ahead(["calibration", "views", "cloud", "mesh"], "cloud") is None
    thread = import_ahead(names, "cloud")
    assert thread is not None and thread.daemon
    thread.join(120)
    assert "dotshell.pipeline.validate" in sys.modules


def test_a_users_script_ends_with_pythons_exit_so_what_it_left_open_is_written(tmp_path):
    """`dotshell script` runs a user's code: it keeps Python's own exit (cli.NORMAL_EXIT), whose
    teardown closes a file a module the script imported wrote and never closed (the commands'
    fast exit would lose what is still in its buffer)."""
    (tmp_path / "helper.py").write_text(
        f"log = open({str(tmp_path / 'out.txt')!r}, 'w')\nlog.write('kept')\n")
    script = tmp_path / "use_helper.py"
    script.write_text(f"import sys\nsys.path.insert(0, {str(tmp_path)!r})\nimport helper\n")
    r = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "script", str(script)],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out.txt").read_text() == "kept"


def test_version_answers_without_heavy_imports():
    """``dotshell --version`` (the entry point :mod:`dotshell.cli.entry`) prints the version
    without importing rich, pluggy or numpy; any other command goes on to the full CLI."""
    from dotshell import __version__

    probe = ("import sys\nfrom dotshell.cli.entry import main\ncode = main(['--version'])\n"
             "heavy = sorted(m for m in ('rich', 'pluggy', 'numpy', 'dotshell.cli.app') "
             "if m in sys.modules)\nprint('heavy', heavy, code)\n")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == [f"dotshell {__version__}", "heavy [] 0"]
    r = subprocess.run([sys.executable, "-m", "dotshell.cli.entry", "no-such-command"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "invalid choice" in r.stderr
