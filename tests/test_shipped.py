"""Shipped profiles and layouts by bare name (a user's file wins), `dotshell profiles [copy]`,
the log flags and library warnings, shell completion, and the user directories
(platformdirs). The installed wheel itself: tests/test_wheel.py."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from conftest import ROOT
from dotshell.cli.app import _parser, main
from dotshell.cli.completion import completion_script
from dotshell.cli.log_setup import chosen_level
from dotshell.run.capture_layouts import resolve_layout_path
from dotshell.profile.loader import load_profile
from dotshell.shipped import resolve, shipped_dir, shipped_names


def test_bare_names_resolve_to_the_shipped_files_and_a_user_file_wins(tmp_path, monkeypatch, pm):
    monkeypatch.chdir(tmp_path)
    assert resolve("profiles", "sim-metal-cylinder").samefile(
        ROOT / "profiles" / "sim-metal-cylinder.toml")
    assert resolve("profiles", "sim-metal-cylinder.toml") == resolve("profiles", "sim-metal-cylinder")
    assert load_profile("sim-metal-cylinder", pm).name == "sim-metal-cylinder"
    assert resolve_layout_path("slstudio-graycode").samefile(ROOT / "layouts" / "slstudio-graycode.toml")
    mine = tmp_path / "sim-metal-cylinder"  # a user's file of that path wins
    raw = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text())
    mine.write_text((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text().replace(
        f'name = "{raw["profile"]["name"]}"', 'name = "mine"'))
    assert load_profile("sim-metal-cylinder", pm).name == "mine"
    assert resolve("profiles", "sub/sim-metal-cylinder") == Path("sub/sim-metal-cylinder")
    assert set(shipped_names("profiles")) == {p.stem for p in (ROOT / "profiles").glob("*.toml")}
    assert set(shipped_names("layouts")) == {p.stem for p in (ROOT / "layouts").glob("*.toml")}


def test_unknown_names_list_the_shipped_ones_and_how_to_copy(tmp_path, capsys):
    assert main(["check", "no-such-profile"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "sim-metal-cylinder, sim-metal-cylinder-diagonal" in err
    assert "dotshell profiles copy NAME my-rig.toml" in err
    assert main(["decode", "--captures", str(tmp_path), "--layout", "no-such-layout"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "shipped layouts: opencv-graycode, slstudio-graycode" in err


def test_profiles_lists_and_copies_a_profile_with_the_files_it_names(tmp_path, capsys, pm):
    assert main(["profiles"]) == 0
    text = capsys.readouterr().out
    for name in shipped_names("profiles") + shipped_names("layouts"):
        assert name in text
    dest = tmp_path / "rig" / "lc.toml"
    assert main(["profiles", "copy", "sim-metal-cylinder-lightcrafter", str(dest)]) == 0
    assert (dest.parent / "lc4500" / "lc4500_00.png").read_bytes() == \
        (shipped_dir("profiles") / "lc4500" / "lc4500_00.png").read_bytes()
    assert load_profile(dest, pm).name == "sim-metal-cylinder-lightcrafter"
    capsys.readouterr()
    assert main(["profiles", "copy", "sim-metal-cylinder-lightcrafter", str(dest)]) == 2
    assert "--force" in capsys.readouterr().err  # nothing overwritten without it
    assert main(["profiles", "copy", "opencv-graycode", str(tmp_path)]) == 0  # a layout
    assert resolve_layout_path(tmp_path / "opencv-graycode.toml")
    assert main(["profiles", "copy", "nope", str(dest)]) == 2
    assert "sim-metal-cylinder" in capsys.readouterr().err


def test_docs_prints_the_installed_documentation(capsys):
    assert main(["docs"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert str(shipped_dir("docs").resolve() / "index.md") in out.replace(" ", "") or \
        "index.md" in out


def test_help_sends_a_pip_user_to_dotshell_docs_not_to_the_checkout():
    text = _parser().format_help()
    assert "dotshell docs" in text and "README.md" not in text


def test_log_flags_choose_the_level():
    assert chosen_level() == 20 + 10  # WARNING
    assert chosen_level(verbose=1) == 20 and chosen_level(verbose=2) == 10
    assert chosen_level(quiet=True) == 40
    assert chosen_level(verbose=2, log_level="ERROR") == 40
    args = _parser().parse_args(["-vv", "--log-level", "info", "profiles"])
    assert args.verbose == 2 and args.log_level == "INFO"
    args = _parser().parse_args(["-q", "check", "p.toml", "-v"])  # after the command as well
    assert args.verbose == 1 and args.quiet and args.log_level is None
    args = _parser().parse_args(["check", "p.toml"])
    assert args.verbose == 0 and not args.quiet


def test_library_warnings_reach_the_terminal_only_with_verbose(tmp_path):
    """A library that warns on import (as pyacvd's use of PyVista's deprecated API does): the
    warning is not printed by `dotshell script`, and is with -v."""
    (tmp_path / "noisylib.py").write_text(
        "import warnings\nwarnings.warn('noisylib: this API is deprecated', FutureWarning)\n")
    (tmp_path / "use.py").write_text("import noisylib\nprint('done')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    runs = {flag: subprocess.run([sys.executable, "-m", "dotshell", *flag, "script", "use.py"],
                                 cwd=tmp_path, env=env, capture_output=True, text=True,
                                 timeout=300) for flag in ((), ("-v",))}
    for r in runs.values():
        assert r.returncode == 0 and "done" in r.stdout, r.stderr
    assert "deprecated" not in runs[()].stderr
    assert "noisylib: this API is deprecated" in runs[("-v",)].stderr


def test_open3d_import_error_speaks_to_a_pip_user(monkeypatch):
    import builtins

    from dotshell.runtime import compat
    from dotshell.errors import DotshellError

    real = builtins.__import__

    def no_open3d(name, *a, **k):
        if name == "open3d":
            raise ImportError("libusb-1.0.so.0: cannot open shared object file")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_open3d)
    with pytest.raises(DotshellError) as exc:
        compat.import_open3d()
    assert "make demo" not in str(exc.value).split("in a checkout")[0]
    assert "pip install open3d libusb-package" in str(exc.value)


def _bash_complete(script: Path, words: list[str]) -> list[str]:
    line = " ".join(words)
    cmd = (f"source {script}; COMP_WORDS=({' '.join(repr(w) for w in words)}); "
           f"COMP_CWORD={len(words) - 1}; COMP_LINE={line!r}; COMP_POINT={len(line)}; "
           "_shtab_dotshell; printf '%s\\n' \"${COMPREPLY[@]}\"")
    r = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


def test_bash_completion_completes_commands_options_and_choices(tmp_path, capsys):
    assert main(["completion", "bash"]) == 0
    script = tmp_path / "dotshell.bash"
    script.write_text(capsys.readouterr().out)
    assert _bash_complete(script, ["dotshell", "pro"]) == ["profiles"]
    assert "completion" in _bash_complete(script, ["dotshell", "c"])
    assert _bash_complete(script, ["dotshell", "completion", "f"]) == ["fish"]
    assert "--detach" in _bash_complete(script, ["dotshell", "scan", "--"])
    assert _bash_complete(script, ["dotshell", "scan", "sim-metal-cylinder-v"]) == [
        "sim-metal-cylinder-vertical"]  # a PROFILE: the shipped names (and TOML files)


@pytest.mark.skipif(shutil.which("fish") is None, reason="fish is not installed")
def test_fish_completion_completes_commands_options_and_choices(tmp_path):
    script = tmp_path / "dotshell.fish"
    script.write_text(completion_script(_parser(), "fish"))

    def complete(line: str) -> list[str]:
        r = subprocess.run(["fish", "--no-config", "-c", f"source {script}; complete -C '{line}'"],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        return [row.split("\t")[0] for row in r.stdout.splitlines()]

    assert "profiles" in complete("dotshell pro") and "scan" not in complete("dotshell pro")
    assert complete("dotshell completion ") == ["bash", "fish", "zsh"] or \
        sorted(complete("dotshell completion ")) == ["bash", "fish", "zsh"]
    assert "--detach" in complete("dotshell scan --")
    assert "copy" in complete("dotshell profiles ")
    assert "INFO" in complete("dotshell --log-level ")
    assert "sim-metal-cylinder-vertical" in complete("dotshell tui sim-metal-cylinder-v")


@pytest.mark.skipif(shutil.which("zsh") is None, reason="zsh is not installed")
def test_zsh_completion_script_parses(tmp_path):
    script = tmp_path / "_dotshell"
    script.write_text(completion_script(_parser(), "zsh"))
    r = subprocess.run(["zsh", "-n", str(script)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "'profiles:" in script.read_text() or "profiles" in script.read_text()


def test_user_directories_are_platformdirs_at_todays_places(monkeypatch, tmp_path):
    from dotshell.runtime import paths

    monkeypatch.delenv("XDG_STATE_HOME", raising=False)
    monkeypatch.delenv("XDG_CONFIG_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert paths.state_dir() == tmp_path / ".local" / "state" / "dotshell"
    assert paths.config_path() == tmp_path / ".config" / "dotshell" / "config.toml"
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "s"))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "c"))
    assert paths.state_dir() == tmp_path / "s" / "dotshell"
    assert paths.config_path() == tmp_path / "c" / "dotshell" / "config.toml"
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "r"))
    (tmp_path / "r").mkdir(mode=0o700)
    assert paths.runtime_dir() == tmp_path / "r" / "dotshell"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert paths.runtime_dir().name == f"dotshell-{os.getuid()}"  # where servers are today


def test_argparse_namespace_without_log_flags_keeps_warning_level():
    from dotshell.cli.log_setup import configure_logging

    assert configure_logging(argparse.Namespace()) == 30


def test_cli_reference_lists_every_command_and_option():
    """The docs site's cli.md is generated from the parser: every command (and sub-command) has
    its heading, every option its row."""
    from dotshell.cli.reference import markdown

    parser = _parser()
    text = markdown(parser)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, child in sub.choices.items():
        assert f"## dotshell {name}\n" in text, name
        for action in child._actions:
            if action.help == argparse.SUPPRESS:
                continue
            for flag in action.option_strings:
                assert f"`{flag}`" in text or flag in ("-h", "--help"), (name, flag)
    assert "### dotshell profiles copy" in text and "### dotshell batch reconstruct" in text
    marker = "<!-- the command reference is generated here from the parser -->"
    assert marker in (ROOT / "docs" / "cli.md").read_text()  # where mkdocs_hooks.py puts it


def test_log_records_reach_stderr_by_level_and_device_lines_only_when_verbose(capsys):
    """Library records at WARNING by default; device log lines (which the front ends already
    show as events) only with -v; -q keeps errors only."""
    import logging

    from dotshell.cli.log_setup import configure_logging

    lib, dev = logging.getLogger("somelib"), logging.getLogger("dotshell.devices")
    try:
        configure_logging(argparse.Namespace(verbose=0, quiet=False, log_level=None))
        lib.info("lib info")
        lib.warning("lib warning")
        dev.warning("stage (grbl): alarm")
        err = capsys.readouterr().err
        assert "lib warning" in err and "lib info" not in err and "alarm" not in err
        configure_logging(argparse.Namespace(verbose=1, quiet=False, log_level=None))
        lib.info("lib info")
        dev.warning("stage (grbl): alarm")
        err = capsys.readouterr().err
        assert "INFO somelib: lib info" in err and "alarm" in err
        configure_logging(argparse.Namespace(verbose=0, quiet=True, log_level=None))
        lib.warning("lib warning")
        assert "lib warning" not in capsys.readouterr().err
    finally:
        configure_logging(argparse.Namespace())


def test_a_library_logger_set_below_the_chosen_level_stays_quiet(capsys):
    """Dask sets its ``distributed`` logger to INFO and, finding dotshell's handler on the root
    logger, propagates to it: every `dotshell batch` printed ~25 INFO lines, and under load the
    INFO record of a comm closed at the cluster's shutdown with its traceback (issue 33's batch
    flake). The chosen level holds for such a logger too; -v shows its INFO lines."""
    import logging

    from dotshell.cli.log_setup import configure_logging

    lib = logging.getLogger("selfleveled")
    lib.setLevel(logging.INFO)
    try:
        configure_logging(argparse.Namespace(verbose=0, quiet=False, log_level=None))
        try:
            raise ConnectionError("comm closed")
        except ConnectionError:
            lib.info("Batched Comm Closed", exc_info=True)
        lib.warning("lib warning")
        err = capsys.readouterr().err
        assert "WARNING selfleveled: lib warning" in err, err
        assert "Batched Comm Closed" not in err and "Traceback" not in err, err
        configure_logging(argparse.Namespace(verbose=1, quiet=False, log_level=None))
        lib.info("Batched Comm Closed")
        assert "INFO selfleveled: Batched Comm Closed" in capsys.readouterr().err
    finally:
        lib.setLevel(logging.NOTSET)
        configure_logging(argparse.Namespace())
