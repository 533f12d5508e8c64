"""The house holds its shape (issue 31, docs/architecture.md): dotshell's rooms import downward
only (the import-linter contract in pyproject.toml), no two of its modules import each other,
even through a chain or from inside a function, and no module sits at the top level of
``dotshell/`` but the flat plugin contract. The last test builds a tiny package that breaks each
rule and shows the same checks report it, with the chain that breaks it."""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
import tomllib
from collections import deque
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The flat plugin contract: the only modules directly in dotshell/ (beside __init__, __main__).
PLUGIN_CONTRACT = ("hookspecs", "devices", "coding", "normalizer", "settings", "errors",
                   "events", "plugins", "backends", "manifest", "testing")


# ---- the checks -------------------------------------------------------------------------------

def lint_imports(config: Path, cwd: Path) -> subprocess.CompletedProcess:
    """import-linter on the contracts of ``config``, packages found from ``cwd`` first (the
    checkout's own code, not an installed copy); no cache written."""
    return subprocess.run(
        [sys.executable, "-c", "from importlinter.cli import lint_imports_command as c; c()",
         "--no-cache", "--no-logo", str(config)],
        cwd=cwd, capture_output=True, text=True, timeout=300)


def import_graph(package: str) -> grimp.ImportGraph:
    """Every import between ``package``'s modules, those inside functions included."""
    return grimp.build_graph(package, cache_dir=None)


def import_cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, without
    recursion), each sorted; modules that import themselves are not cycles here."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            module, targets = work[-1]
            target = next(targets, None)
            if target is not None:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(sorted(graph.find_modules_directly_imported_by(
                        target)))))
                elif target in on_stack:
                    low[module] = min(low[module], index[target])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[module])
            if low[module] == index[module]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == module:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return sorted(found)


def cycle_chain(graph: grimp.ImportGraph, component: list[str]) -> str:
    """One shortest cycle through the first module of ``component``, as people read it:
    ``a -> b (l.12) -> a (l.40)`` (the line of each import in its importer)."""
    start, members = component[0], set(component)
    came_from: dict[str, str] = {}
    queue = deque([start])
    while queue:
        module = queue.popleft()
        for target in sorted(graph.find_modules_directly_imported_by(module) & members):
            if target == start:
                path = [module]
                while path[-1] != start:
                    path.append(came_from[path[-1]])
                return _render([start, *reversed(path[:-1]), start], graph)
            if target not in came_from:
                came_from[target] = module
                queue.append(target)
    raise AssertionError(f"{component} is not a cycle")


def _render(chain: list[str], graph: grimp.ImportGraph) -> str:
    parts = [chain[0]]
    for importer, imported in zip(chain, chain[1:]):
        lines = sorted(d["line_number"] for d in graph.get_import_details(
            importer=importer, imported=imported))
        parts.append(f"{imported} ({', '.join(f'l.{n}' for n in lines)})")
    return " -> ".join(parts)


def cycles_report(package: str | grimp.ImportGraph) -> str:
    """Each import cycle of ``package`` (a name, or its graph): its modules and one chain; ''
    when there is none."""
    graph = import_graph(package) if isinstance(package, str) else package
    return "\n".join(f"cycle of {len(c)} modules ({', '.join(c)}):\n  {cycle_chain(graph, c)}"
                     for c in import_cycles(graph))


def script_graph(directory: Path) -> grimp.ImportGraph:
    """The imports between the scripts of ``directory`` (not a package: the benchmarks import
    each other by their bare names), inside functions too."""
    graph = grimp.ImportGraph()
    names = {p.stem for p in directory.glob("*.py")}
    for name in names:
        graph.add_module(name)
    for path in sorted(directory.glob("*.py")):
        lines = path.read_text().splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            targets = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                       [node.module] if isinstance(node, ast.ImportFrom) and node.module
                       and not node.level else [])
            for target in {t.split(".")[0] for t in targets} & names - {path.stem}:
                graph.add_import(importer=path.stem, imported=target, line_number=node.lineno,
                                 line_contents=lines[node.lineno - 1].strip())
    return graph


def stray_modules(package_dir: Path, allowed: tuple[str, ...]) -> list[str]:
    """The modules directly in ``package_dir`` that are neither ``allowed`` nor ``__init__``
    or ``__main__`` (packages are rooms; the layers contract names each)."""
    keep = {*allowed, "__init__", "__main__"}
    return sorted(p.name for p in package_dir.glob("*.py") if p.stem not in keep)


# ---- dotshell -----------------------------------------------------------------------------------

def test_rooms_import_downward_only():
    """The layers contract of pyproject.toml holds: no import runs up (the report names each
    chain that does, with its lines)."""
    result = lint_imports(ROOT / "pyproject.toml", ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Contracts: 1 kept, 0 broken." in result.stdout


def test_no_import_cycles():
    report = cycles_report("dotshell")
    assert report == "", "import cycles in dotshell/:\n" + report


def test_no_import_cycles_among_the_benchmarks():
    report = cycles_report(script_graph(ROOT / "benchmarks"))
    assert report == "", "import cycles in benchmarks/:\n" + report


def test_only_the_plugin_contract_sits_at_the_top():
    assert stray_modules(ROOT / "dotshell", PLUGIN_CONTRACT) == []
    contract = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    bottom = contract["contracts"][0]["layers"][-1]
    assert tuple(name.strip() for name in bottom.split(":")) == PLUGIN_CONTRACT


# ---- the checks catch what they are for ---------------------------------------------------------

TOY = {
    "__init__.py": "",
    "high/__init__.py": "",
    "high/view.py": "",
    "high/menu.py": "from toy.low import a  # down: allowed\n",
    "low/__init__.py": "",
    "low/store.py": ("def show():\n"
                     "    from toy.high import view  # up the layers, inside a function\n"
                     "    return view\n"),
    "low/a.py": "from toy.low import b\n",
    "low/b.py": "import os\n\n\ndef back():\n    from toy.low import a  # a cycle a -> b -> a\n",
    "base.py": "",
    "stray.py": "",  # a module at the top level, outside the contract
}


@pytest.fixture
def toy(tmp_path, monkeypatch):
    """A package ``toy`` (layers high > low > base) that breaks each rule once, and its
    contract in the shape of dotshell's."""
    for name, source in TOY.items():
        path = tmp_path / "toy" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(source)
    (tmp_path / "contracts.toml").write_text(textwrap.dedent("""\
        [tool.importlinter]
        root_package = "toy"

        [[tool.importlinter.contracts]]
        id = "layers"
        name = "toy layers"
        type = "layers"
        containers = ["toy"]
        layers = ["high", "low", "base"]
        exhaustive = true
        """))
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_checks_report_what_breaks_them(toy):
    linted = lint_imports(toy / "contracts.toml", toy)
    assert linted.returncode == 1
    assert "toy.low is not allowed to import toy.high" in linted.stdout
    assert "- toy.low.store -> toy.high.view (l.2)" in linted.stdout  # the chain and its line
    assert "not listed as layers:\n\n- toy.stray" in linted.stdout  # the contract is exhaustive
    assert cycles_report("toy") == ("cycle of 2 modules (toy.low.a, toy.low.b):\n"
                                    "  toy.low.a -> toy.low.b (l.1) -> toy.low.a (l.5)")
    assert stray_modules(toy / "toy", ("base",)) == ["stray.py"]
    scripts = toy / "scripts"  # by bare names, as the benchmarks import each other
    scripts.mkdir()
    (scripts / "bench.py").write_text("import json\nimport helper\n")
    (scripts / "helper.py").write_text("def figures():\n    from bench import RESULTS\n")
    assert cycles_report(script_graph(scripts)) == ("cycle of 2 modules (bench, helper):\n"
                                                    "  bench -> helper (l.2) -> bench (l.2)")
