"""The code stays lint-clean and type-clean: ruff (the rule set in pyproject.toml's
``[tool.ruff]``) on dotshell/ and plugins/, mypy (``[tool.mypy]``: the dotshell package) on
dotshell/. Both run from the test venv (the ``test`` extra installs them); a finding fails the
test with the tool's own report.

mypy keeps its incremental cache in the checkout's ``.mypy_cache`` (git-ignored): a first run
checks every module (~20-30 s of CPU, one to two minutes on a busy 2-core host), later runs
only what changed.
"""

from __future__ import annotations

import subprocess
import sys

from conftest import ROOT


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=540, check=False)


def test_ruff_finds_nothing_in_dotshell_and_plugins() -> None:
    done = _run("ruff", "check", "--no-cache", "--output-format", "concise", "dotshell",
                "plugins")
    assert done.returncode == 0, (f"ruff check dotshell plugins (exit {done.returncode}):\n"
                                  f"{done.stdout}{done.stderr}")


def test_mypy_finds_nothing_in_dotshell() -> None:
    done = _run("mypy", "--cache-dir", str(ROOT / ".mypy_cache"))
    assert done.returncode == 0, (f"mypy (exit {done.returncode}), [tool.mypy] in "
                                  f"pyproject.toml:\n{done.stdout}{done.stderr}")
    assert "Success: no issues found" in done.stdout, done.stdout
