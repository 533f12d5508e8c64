"""Where a view's CPU goes, by compiled function: ``perf`` samples of ``reconstruct_view`` on the
bench view, with numba's compiled code named.

perf cannot name numba's code (it is generated in memory, without symbols). This script
compiles the kernels afresh in a temporary numba cache (a process keeps a function's object
code only when it compiled it), writes ``/tmp/perf-PID.map`` from each compiled library's
symbol table (every function with its address and size), then records ``perf`` on itself
while it reconstructs the view ``--views`` times, with the top 64 bytes of the stack at each
sample (``--call-graph dwarf,64``): a sample inside numba's reference counting
(``NRT_incref``/``NRT_decref``, small functions that push nothing) has its caller's return
address there, which names the caller.

``--annotate NAME`` (a compiled function, e.g. ``_refine_row``) also lays the samples on that
function's instructions: its machine code is read from the process's memory and disassembled
by ``objdump``, and the hottest stretches are printed with their share of its samples.

Run (Linux with ``perf``; ~1 minute of compiling first, then the views):
``.venv/bin/python benchmarks/profile_view.py [--quick] [--threads N] [--views N]
[--annotate NAME]``.
docs/performance.md, "Part 6", shows what it found.
"""

from __future__ import annotations

import argparse
import bisect
import collections
import ctypes
import os
import re
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="dotshell-profile-numba-")

from bench_profile import load_bench_profile  # noqa: E402
from run import render_view  # noqa: E402

from dotshell.runtime import parallel  # noqa: E402
from dotshell.pipeline.reconstruct import reconstruct_view  # noqa: E402
from dotshell.plugins import get_plugin_manager  # noqa: E402
from dotshell.runtime.process import configure_process  # noqa: E402

_SHT_SYMTAB, _STT_FUNC = 2, 2


def elf_functions(obj: bytes) -> list[tuple[str, int]]:
    """(name, size in bytes) of every function an ELF64 object defines."""
    shoff, = struct.unpack_from("<Q", obj, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", obj, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", obj, shoff + i * shentsize)
                for i in range(shnum)]
    out = []
    for sec in sections:
        if sec[1] != _SHT_SYMTAB:
            continue
        offset, size, link, entsize = sec[4], sec[5], sec[6], sec[9]
        strings = sections[link][4]
        for k in range(size // entsize):
            name, info, _, shndx, _, length = struct.unpack_from("<IBBHQQ", obj,
                                                                 offset + k * entsize)
            if info & 0xF == _STT_FUNC and shndx != 0 and length:
                end = obj.index(b"\0", strings + name)
                out.append((obj[strings + name:end].decode(), length))
    return out


def readable(mangled: str) -> str:
    """``module.function`` of a numba symbol (Itanium-style ``_ZN<len><part>...``)."""
    if not mangled.startswith("_ZN"):
        return mangled
    i, parts = 3, []
    while i < len(mangled) and mangled[i].isdigit():
        j = i
        while mangled[j].isdigit():
            j += 1
        n = int(mangled[i:j])
        parts.append(mangled[j:j + n])
        i = j + n
    return ".".join(parts) or mangled


def compiled_functions() -> dict[int, tuple[int, str]]:
    """address → (size, name) of every function numba compiled in this process."""
    from numba.core.registry import CPUDispatcher

    found: dict[int, tuple[int, str]] = {}
    for module in list(sys.modules.values()):
        for value in list(getattr(module, "__dict__", {}).values()):
            if not isinstance(value, CPUDispatcher):
                continue
            for cres in value.overloads.values():
                library = cres.library
                try:
                    obj = library._get_compiled_object()  # numba-internal
                except Exception:  # loaded from a cache: no object code kept
                    continue
                for name, size in elf_functions(obj):
                    address = library.get_pointer_to_function(name)
                    if address:
                        found[address] = (size, readable(name))
    return found


def write_perf_map(functions: dict[int, tuple[int, str]]) -> Path:
    path = Path(f"/tmp/perf-{os.getpid()}.map")
    path.write_text("".join(f"{a:x} {size:x} {name}\n"
                            for a, (size, name) in sorted(functions.items())))
    return path


def counting_callers(data: Path, functions: dict[int, tuple[int, str]]) -> collections.Counter:
    """(reference-counting function, caller) → samples, from the stack tops ``perf`` kept."""
    starts = sorted(functions)

    def name_at(address: int) -> str:
        i = bisect.bisect_right(starts, address) - 1
        if i >= 0 and address < starts[i] + functions[starts[i]][0]:
            return functions[starts[i]][1]
        return "?"

    dump = subprocess.run(["perf", "script", "-i", str(data), "-D"], capture_output=True,
                          text=True, check=True).stdout.splitlines()
    raw, stack_at, callers = bytearray(), None, collections.Counter()
    for line in dump:
        if "raw event: size" in line:
            raw, stack_at = bytearray(), None
            continue
        hexline = re.match(r"\.\s+[0-9a-f]{4}:\s+((?:[0-9a-f]{2} )+)", line)
        if hexline:
            raw += bytes.fromhex(hexline.group(1).replace(" ", ""))
            continue
        ustack = re.search(r"ustack: size \d+, offset (0x[0-9a-f]+)", line)
        if ustack:
            stack_at = int(ustack.group(1), 16)
            continue
        sample = re.search(r"\s[0-9a-f]+ (NRT_(?:incref|decref))\+", line)
        if sample and stack_at is not None and len(raw) >= stack_at + 16:
            ret = int.from_bytes(raw[stack_at + 8:stack_at + 16], "little")
            callers[(sample.group(1), name_at(ret))] += 1
    return callers


def disassembly(address: int, size: int) -> list[tuple[int, str]]:
    """(address, instruction) of the ``size`` bytes of machine code at ``address`` in this
    process (``objdump`` of a copy)."""
    with tempfile.NamedTemporaryFile(suffix=".bin") as f:
        f.write(ctypes.string_at(address, size))
        f.flush()
        out = subprocess.run(["objdump", "-D", "-b", "binary", "-m", "i386:x86-64",
                              "--no-show-raw-insn", f"--adjust-vma={address:#x}", f.name],
                             capture_output=True, text=True, check=True).stdout
    code = []
    for line in out.splitlines():
        m = re.match(r"\s+([0-9a-f]+):\s+(.*)", line)
        if m:
            code.append((int(m.group(1), 16), m.group(2).strip()))
    return code


def sampled_addresses(data: Path) -> collections.Counter:
    """address → samples ``perf`` took there (the sampled instruction, not its callers)."""
    ips = subprocess.run(["perf", "script", "-i", str(data), "-F", "ip", "-G"],
                         capture_output=True, text=True, check=True).stdout.split()
    return collections.Counter(int(ip, 16) for ip in ips if re.fullmatch(r"[0-9a-f]+", ip))


def annotate(sampled: collections.Counter, functions: dict[int, tuple[int, str]], name: str,
             context: int = 6, stretches: int = 8) -> None:
    """Print the hottest stretches of compiled function ``name`` (the one whose name ends with
    it that has the most samples) with the samples at each instruction (``sampled``:
    :func:`sampled_addresses`)."""
    found = [(a, size) for a, (size, n) in functions.items() if n.endswith(name)]
    if not found:
        print(f"== no compiled function named *{name}")
        return
    # a function called from another library runs as that library's copy: the most sampled
    start, size = max(found, key=lambda f: sum(n for a, n in sampled.items()
                                               if f[0] <= a < f[0] + f[1]))
    hits = collections.Counter({a: n for a, n in sampled.items() if start <= a < start + size})
    code = disassembly(start, size)
    total = sum(hits.values()) or 1
    print(f"== {name}: {total} samples over {len(code)} instructions; hottest stretches "
          "(% of the function's samples, per instruction)")
    index = {a: i for i, (a, _) in enumerate(code)}
    shown: set[int] = set()
    for address, _ in hits.most_common():
        if len(shown) >= stretches * (2 * context + 1) or address not in index:
            continue
        i = index[address]
        if i in shown:
            continue
        lo, hi = max(i - context, 0), min(i + context + 1, len(code))
        print("  ...")
        for k in range(lo, hi):
            shown.add(k)
            a, text = code[k]
            n = hits.get(a, 0)
            print(f"  {100 * n / total:5.1f}  {a - start:6x}  {text}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the 320x256 bench view")
    ap.add_argument("--threads", type=int, default=1, help="threads of the passes (default 1)")
    ap.add_argument("--views", type=int, default=25, help="reconstructions recorded")
    ap.add_argument("--annotate", metavar="NAME", action="append", default=[],
                    help="lay the samples on this compiled function's instructions")
    args = ap.parse_args()
    configure_process()
    pm = get_plugin_manager()
    profile = load_bench_profile(pm, args.quick)
    view = render_view(profile, pm)
    processing = profile.data["processing"]

    def once() -> None:
        reconstruct_view(0, view.angle_deg, view.frames, view.coding, view.calib, processing)

    with parallel.threads(args.threads):
        once()  # compiles every kernel in this process
        functions = compiled_functions()
        write_perf_map(functions)
        data = Path(tempfile.mkdtemp(prefix="dotshell-profile-")) / "perf.data"
        perf = subprocess.Popen(["perf", "record", "--call-graph", "dwarf,64", "-o", str(data),
                                 "-p", str(os.getpid())], stderr=subprocess.DEVNULL)
        time.sleep(1.0)  # perf attached
        for _ in range(args.views):
            once()
        perf.send_signal(signal.SIGINT)
        perf.wait()
    report = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "--sort",
                             "sym", "--stdio"], capture_output=True, text=True).stdout
    rows = [r for r in report.splitlines() if r.strip() and not r.startswith("#")]
    print(f"== share of the samples by function ({args.views} views, {args.threads} thread(s))")
    print("\n".join(r for r in rows if re.match(r"\s+[\d.]+%", r))[:4000])
    print("== callers of numba's reference counting (samples)")
    for (fn, caller), n in counting_callers(data, functions).most_common(10):
        print(f"  {n:6d}  {fn:12s} from {caller}")
    sampled = sampled_addresses(data) if args.annotate else collections.Counter()
    for name in args.annotate:
        annotate(sampled, functions, name)


if __name__ == "__main__":
    main()
