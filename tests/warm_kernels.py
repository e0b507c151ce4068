"""Compile the project's kernels into the numba cache once, before the test workers start.

Every kernel is compiled on first call and cached on disk (``shared.jit``). With a cold cache (a
fresh clone: CI) each xdist worker, and each daemon or pool process a test starts before a worker
has written the kernel it needs, compiles the same kernels again. So the controller compiles them
first, in as many processes as there are workers, from the signatures the suite compiles
(:data:`SIGNATURES`, one ``module function signature`` a line); the workers then load them.

This is an optimisation and nothing more: a signature that no longer matches its kernel is
compiled for nothing, or skipped if its kernel is gone, and a kernel missing from the list is
compiled by the worker that calls it, as without a warm-up. After changing a kernel's arguments,
refresh the list from a cache the suite has filled::

    NUMBA_CACHE_DIR=/tmp/nc python -m pytest -q
    NUMBA_CACHE_DIR=/tmp/nc python -m tests.warm_kernels record
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import re
import subprocess
import sys
import time
from pathlib import Path

from numba.core import types
from numba.core.registry import CPUDispatcher

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[1]
SIGNATURES = Path(__file__).with_name("kernel_signatures.txt")
PACKAGES = ("shared", "edge", "cloud", "simfleet")

def _named(path: str, members: tuple):
    """A named tuple's numba type from its class's dotted path and its members' types."""
    module, _, cls = path.rpartition(".")
    return types.BaseTuple.from_types(members, getattr(importlib.import_module(module), cls))


#: Names in a signature's text besides numba's types: ``bool`` (numba's boolean prints so),
#: ``literal`` for literal arguments, ``named`` for named tuples (which print as their class).
_NAMES = dict(vars(types), bool=types.boolean, literal=types.literal, named=_named)
_LITERAL = re.compile(r"Literal\[\w+\]\(([^()]*)\)")


def _text(t) -> str:
    if isinstance(t, types.BaseNamedTuple):
        cls = t.instance_class
        return f"named({cls.__module__ + '.' + cls.__qualname__!r}, ({''.join(_text(m) + ', ' for m in t.types)}))"
    return repr(t)


def parse_signature(text: str) -> tuple:
    """The argument types of a signature line's text."""
    return eval(_LITERAL.sub(r"literal(\1)", text), {"__builtins__": {}}, _NAMES)  # noqa: S307 (our own file)


def _kernels(module):
    """The module's own kernels: (name, dispatcher)."""
    return [(name, obj) for name, obj in vars(module).items()
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == module.__name__]


def record() -> int:
    """Write :data:`SIGNATURES` from the kernels' cache indexes (``NUMBA_CACHE_DIR``, filled by a run)."""
    lines, skipped = [], []
    for pkg in PACKAGES:
        for info in pkgutil.walk_packages([str(ROOT / pkg)], prefix=pkg + "."):
            if info.name.endswith("__main__"):
                continue
            for name, kernel in _kernels(importlib.import_module(info.name)):
                for sig in kernel._cache._cache_file._load_index():
                    text = f"({''.join(_text(t) + ', ' for t in sig[0])})"
                    try:
                        ok = parse_signature(text) == tuple(sig[0])
                    except Exception:  # a type whose text is not its constructor
                        ok = False
                    (lines if ok else skipped).append(f"{info.name} {name} {text}")
    SIGNATURES.write_text("".join(sorted(f"{line}\n" for line in set(lines))))
    for s in skipped:
        print(f"not listed (its types do not print as constructors): {s}", file=sys.stderr)
    print(f"{len(set(lines))} signatures → {SIGNATURES}")
    return 0


def warm(part: int, parts: int) -> int:
    """Compile every ``parts``-th signature of the list, starting at ``part``."""
    t0, done = time.perf_counter(), 0
    lines = SIGNATURES.read_text().splitlines()
    for line in lines[part::parts]:
        module, name, text = line.split(" ", 2)
        try:
            getattr(importlib.import_module(module), name).compile(parse_signature(text))
            done += 1
        except Exception as e:  # a stale line: that kernel is compiled where it is called
            log.warning("not warmed: %s (%s)", line, e)
    log.info("warmed %d kernels in %.1f s", done, time.perf_counter() - t0)
    return 0


def warm_in(parts: int, timeout_s: float = 900.0) -> None:
    """Compile the listed kernels in ``parts`` processes at once; return when they are done (or the
    generous ``timeout_s`` is up: the tests then compile what is missing themselves)."""
    procs = [subprocess.Popen([sys.executable, "-m", "tests.warm_kernels", "warm", str(i), str(parts)], cwd=ROOT,
                              stdin=subprocess.DEVNULL) for i in range(parts)]
    for p in procs:
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="warm_kernels: %(message)s")
    if argv[:1] == ["record"]:
        return record()
    if argv[:1] == ["warm"] and len(argv) == 3:
        return warm(int(argv[1]), int(argv[2]))
    print("usage: python -m tests.warm_kernels record | warm PART PARTS", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
