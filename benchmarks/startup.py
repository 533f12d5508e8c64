"""Start-up of light commands (issue 31): ``dotshell --help``, ``dotshell status``,
``dotshell plugins`` and ``dotshell check sim-metal-cylinder`` (a profile: it imports the
backends it names) as fresh processes, this checkout against a reference commit (default
``main``) in the same run, interleaved.

For each command and code base: wall time of the whole process (interpreter start included;
median and spread of ``--repeat`` runs), CPU time of the process (user + system, less sensitive
to a busy host than wall), the modules it imported, and whether cv2, pyserial or any first-party
driver module was among them. The reference is exported with ``git archive`` into a temporary
directory and put first on ``PYTHONPATH`` (entry points come from the installed metadata, the
same for both). The host's load average is printed beside the figures. Nothing here asserts a
speed.

    python benchmarks/startup.py [--ref main] [--repeat 9]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = (["--help"], ["status"], ["plugins"],
            ["check", "sim-metal-cylinder"])  # a profile: only the backends it names
#: first-party modules that are drivers or pull in their libraries
DRIVERS = ("dotshell_cameras.", "dotshell_serial.", "dotshell_projectors.", "dotshell_sim.",
           "dotshell_codings.", "dotshell_meshing.", "dotshell_dotio.", "dotshell_normalizers.")

#: run one command in-process (as the console script does, minus its fast exit) and report the
#: modules it left loaded
CHILD = """
import json, sys
from dotshell.cli.entry import main
try:
    main({argv!r})
except SystemExit:
    pass
sys.stderr.write("\\nMODULES " + json.dumps(sorted(sys.modules)) + "\\n")
"""


def export_ref(ref: str, into: Path) -> Path:
    """``dotshell/``, ``plugins/`` and the shipped files of commit ``ref`` under ``into``."""
    tar = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "dotshell", "plugins",
                          "profiles", "layouts", "docs"],
                         capture_output=True, check=True).stdout
    with tarfile.open(fileobj=BytesIO(tar)) as t:
        t.extractall(into, filter="data")
    return into


def run_once(code_root: Path, argv: list[str], env: dict[str, str]) -> dict[str, object]:
    """One fresh process: wall and CPU seconds, and its modules."""
    env = {**env, "PYTHONPATH": f"{code_root}{os.pathsep}{code_root / 'plugins'}"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", CHILD.format(argv=argv)], capture_output=True,
                       text=True, env=env, timeout=300)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    modules = json.loads(r.stderr.rsplit("MODULES ", 1)[1])
    return {"wall": wall, "cpu": cpu, "modules": modules}


def summary(runs: list[dict[str, object]]) -> dict[str, object]:
    walls = sorted(r["wall"] for r in runs)  # type: ignore[misc]
    cpus = sorted(r["cpu"] for r in runs)  # type: ignore[misc]
    modules: list[str] = runs[-1]["modules"]  # type: ignore[assignment]
    return {"wall_median_s": statistics.median(walls), "wall_min_s": walls[0],
            "wall_max_s": walls[-1], "cpu_median_s": statistics.median(cpus),
            "modules": len(modules), "cv2": "cv2" in modules, "serial": "serial" in modules,
            "drivers": sum(m.startswith(DRIVERS) for m in modules)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", default="main", help="the reference commit (default: main)")
    ap.add_argument("--repeat", type=int, default=9, help="runs per command and code base")
    args = ap.parse_args()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update(OMP_NUM_THREADS="1", COLUMNS="120")
    with tempfile.TemporaryDirectory() as tmp:
        env["XDG_RUNTIME_DIR"] = tmp  # `status` finds no server: the same work for both
        bases = {args.ref: export_ref(args.ref, Path(tmp) / "ref"), "this": ROOT}
        load_before = os.getloadavg()[0]
        runs: dict[tuple[str, str], list[dict[str, object]]] = {}
        for _ in range(args.repeat):  # interleaved: the host's load falls on both alike
            for argv in COMMANDS:
                for base, root in bases.items():
                    runs.setdefault((" ".join(argv)[:10], base), []).append(
                        run_once(root, argv, env))
        load_after = os.getloadavg()[0]
    print(f"start-up, {args.repeat} fresh processes each; {os.cpu_count()} CPUs, load average "
          f"{load_before:.1f} before, {load_after:.1f} after")
    print(f"{'command':<10} {'code':<6} {'wall median':>11} {'(min-max)':>13} {'CPU':>7} "
          f"{'modules':>8} {'cv2':>4} {'serial':>6} {'drivers':>7}")
    results = {}
    for (cmd, base), rs in runs.items():
        s = summary(rs)
        results[f"{cmd} [{base}]"] = s
        print(f"{cmd:<10} {base[:6]:<6} {s['wall_median_s']:>9.3f} s "
              f"({s['wall_min_s']:.2f}-{s['wall_max_s']:.2f}) {s['cpu_median_s']:>5.2f} s "
              f"{s['modules']:>8} {'yes' if s['cv2'] else 'no':>4} "
              f"{'yes' if s['serial'] else 'no':>6} {s['drivers']:>7}")
    for argv in COMMANDS:
        cmd = " ".join(argv)[:10]
        ref, this = results[f"{cmd} [{args.ref}]"], results[f"{cmd} [this]"]
        print(f"{cmd}: wall {ref['wall_median_s']:.3f} -> {this['wall_median_s']:.3f} s "
              f"(x{ref['wall_median_s'] / this['wall_median_s']:.2f}), CPU "
              f"{ref['cpu_median_s']:.2f} -> {this['cpu_median_s']:.2f} s, modules "
              f"{ref['modules']} -> {this['modules']}")
    out = ROOT / "bench-results"
    out.mkdir(exist_ok=True)
    (out / "startup.json").write_text(json.dumps(
        {"ref": args.ref, "repeat": args.repeat, "load": [load_before, load_after],
         "results": results}, indent=1))


if __name__ == "__main__":
    main()
