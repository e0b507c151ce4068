"""The project's import layout, read from its own source: arrows point one way, nothing imports in circles.

Every ``import`` and ``from ... import`` statement counts, those inside functions included (a lazy import
hides a circle from start-up, not from the reader); only ``if TYPE_CHECKING:`` blocks are skipped, since
they never run.  ``from p import m`` is an import of the submodule ``p.m`` when there is one, else of the
package ``p`` (its ``__init__`` and what it re-exports); ``import a.b.c`` is an import of ``a.b.c``, not of
the packages on its way.  Each rule is its own test and names the offending modules and lines.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The packages whose imports make the module graph.
PACKAGES = ("cloud", "shared", "edge", "simfleet", "benchmarks")

#: The estimator domains inside ``cloud/``: kernels and posteriors that are given values, never a transport.
CLOUD_DOMAINS = ("cloud.road", "cloud.bridge", "cloud.rail", "cloud.ingest", "cloud.reference")

#: The modules that open a bus: process entry points, the simulator's publishers and run orchestration,
#: the bus benchmarks, and the one helper that turns command-line options into a ``zenoh.Config``.
TRANSPORT_MODULES = frozenset({
    "shared.transport",
    "cloud.daemon.node",
    "edge.node",
    "simfleet.control",
    "simfleet.fleet",
    "simfleet.replay",
    "simfleet.run",
    "benchmarks.bus",
    "benchmarks.crash",
    "benchmarks.soak",
})

#: What counts as a transport: Zenoh itself, and the project's helper that wraps it.
TRANSPORTS = ("zenoh", "shared.transport")

#: The modules that draw with Rerun: every panel and the one blueprint live in the view.
RERUN_MODULES = frozenset({"cloud.view"})


@dataclass(frozen=True)
class Import:
    """One name an import statement binds: ``from module import name`` or ``import module`` (``name`` None)."""

    importer: str
    path: Path
    line: int
    module: str
    name: str | None

    def where(self) -> str:
        """``path:line`` relative to the checked root, for messages."""
        return f"{self.path}:{self.line}"


def module_files(root: Path, packages: Iterable[str]) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file under the given top-level packages."""
    out = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _statements(tree: ast.AST) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import statement in ``tree`` at any depth, except under ``if TYPE_CHECKING:``."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend(node.orelse)
        else:
            stack.extend(ast.iter_child_nodes(node))


def _absolute(importer: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module a (possibly relative) ``from`` statement names."""
    if not node.level:
        return node.module or ""
    base = importer.split(".")
    if not is_package:
        base = base[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def read_imports(root: Path, packages: Iterable[str]) -> list[Import]:
    """Every import of every module under ``packages`` (relative imports made absolute)."""
    out = []
    for importer, path in module_files(root, packages).items():
        is_package = path.name == "__init__.py"
        rel = path.relative_to(root)
        for node in _statements(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                out.extend(Import(importer, rel, node.lineno, alias.name, None) for alias in node.names)
            else:
                module = _absolute(importer, is_package, node)
                out.extend(Import(importer, rel, node.lineno, module, alias.name) for alias in node.names)
    return out


def target(imp: Import, modules: Iterable[str]) -> str | None:
    """The project module an import loads: ``from p import m`` is the submodule ``p.m`` when there is one,
    else ``p`` itself (a package's ``__init__`` and what it re-exports); ``import a.b.c`` is the deepest
    project module on that path.  None for modules outside the project."""
    modules = set(modules)
    if imp.name is not None and f"{imp.module}.{imp.name}" in modules:
        return f"{imp.module}.{imp.name}"
    parts = imp.module.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in modules:
            return ".".join(parts[:k])
    return None


def edges(imports: Iterable[Import], modules: Iterable[str]) -> list[tuple[Import, str]]:
    """``(import, project module it loads)`` for every import between two different project modules."""
    modules = set(modules)
    out = []
    for imp in imports:
        t = target(imp, modules)
        if t is not None and t != imp.importer:
            out.append((imp, t))
    return out


def cycles(imports: Iterable[Import], modules: Iterable[str]) -> list[list[str]]:
    """The strongly connected components of the module graph with more than one module (Tarjan), each
    sorted, each followed by the imports that close it."""
    graph: dict[str, set[str]] = {}
    for imp, t in edges(imports, modules):
        graph.setdefault(imp.importer, set()).add(t)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []

    def connect(v: str) -> None:
        # Recursion depth is bounded by the longest import chain, a few dozen modules.
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return sorted(out)


def cycle_report(imports: list[Import], modules: Iterable[str]) -> list[str]:
    """One line per import inside an import cycle: ``importer (path:line) -> module``."""
    modules = set(modules)
    lines = []
    for component in cycles(imports, modules):
        members = set(component)
        lines.append("cycle: " + " <-> ".join(component))
        closing = {f"  {imp.importer} ({imp.where()}) -> {t}"
                   for imp, t in edges(imports, modules) if imp.importer in members and t in members}
        lines += sorted(closing)
    return lines


def private_imports(imports: Iterable[Import], modules: Iterable[str]) -> list[str]:
    """``from m import _x`` (and ``import m._x``) where ``m`` is another project module."""
    modules = set(modules)
    out = []
    for imp in imports:
        if target(imp, modules) is None:
            continue
        names = imp.module.split(".") + ([imp.name] if imp.name else [])
        private = [n for n in names if n.startswith("_") and not n.startswith("__")]
        if private:
            out.append(f"{imp.importer} ({imp.where()}) imports {'.'.join(names)}")
    return sorted(set(out))


def _within(module: str, prefixes: Iterable[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def forbidden(imports: Iterable[Import], importers: Iterable[str], imported: Iterable[str],
              allowed: Iterable[str] = ()) -> list[str]:
    """Imports by modules under ``importers`` (except those under ``allowed``) of anything under
    ``imported`` (project or third-party), as ``importer (path:line) imports module``."""
    importers, imported, allowed = tuple(importers), tuple(imported), tuple(allowed)
    out = []
    for imp in imports:
        if not _within(imp.importer, importers) or _within(imp.importer, allowed):
            continue
        loaded = f"{imp.module}.{imp.name}" if imp.name else imp.module
        if _within(imp.module, imported) or _within(loaded, imported):
            out.append(f"{imp.importer} ({imp.where()}) imports {loaded}")
    return sorted(set(out))


def _fail_on(found: list[str], rule: str) -> None:
    assert not found, f"{rule}:\n" + "\n".join(found)


_MODULES = module_files(ROOT, PACKAGES)
_IMPORTS = read_imports(ROOT, PACKAGES)


def test_no_import_cycles():
    _fail_on(cycle_report(_IMPORTS, _MODULES), "modules that import each other (directly or round a loop)")


def test_no_private_name_is_imported_from_another_module():
    modules = module_files(ROOT, PACKAGES + ("tests",))
    _fail_on(private_imports(read_imports(ROOT, PACKAGES + ("tests",)), modules),
             "private names imported across modules (make them public, or test through the public API)")


def test_only_the_process_modules_open_a_transport():
    _fail_on(forbidden(_IMPORTS, PACKAGES, TRANSPORTS, allowed=TRANSPORT_MODULES),
             f"transport imports outside {sorted(TRANSPORT_MODULES)}")


def test_only_the_view_draws_with_rerun():
    _fail_on(forbidden(_IMPORTS, PACKAGES, ("rerun",), allowed=RERUN_MODULES),
             f"rerun imports outside {sorted(RERUN_MODULES)}")


def test_shared_and_the_estimators_know_no_transport_and_no_view():
    _fail_on(forbidden(_IMPORTS, ("shared",) + CLOUD_DOMAINS, ("zenoh", "rerun"), allowed=("shared.transport",)),
             "zenoh or rerun imported by shared/ or an estimator package")


def test_shared_imports_none_of_the_processes():
    _fail_on(forbidden(_IMPORTS, ("shared",), ("edge", "cloud", "simfleet", "benchmarks")),
             "shared/ importing a package built on it")


def test_the_edge_imports_neither_the_cloud_nor_the_simulator():
    _fail_on(forbidden(_IMPORTS, ("edge",), ("cloud", "simfleet")), "edge/ importing cloud/ or simfleet/")


def test_the_cloud_imports_neither_the_edge_nor_the_simulator():
    _fail_on(forbidden(_IMPORTS, ("cloud",), ("edge", "simfleet")), "cloud/ importing edge/ or simfleet/")


def test_the_cloud_domains_never_import_the_daemon():
    _fail_on(forbidden(_IMPORTS, CLOUD_DOMAINS, ("cloud.daemon",)), "an estimator package importing cloud.daemon")


def test_nothing_in_the_cloud_imports_the_reference_methods():
    _fail_on(forbidden(_IMPORTS, ("cloud", "shared", "edge"), ("cloud.reference",), allowed=("cloud.reference",)),
             "cloud.reference (for comparison only) imported by production code")


def test_the_checker_reports_a_hidden_cycle_a_private_import_and_a_stray_transport(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from pkg.a import f\n")
    (pkg / "a.py").write_text("from pkg.b import g\n\ndef f():\n    return g()\n\ndef _h():\n    return 1\n")
    (pkg / "b.py").write_text("def g():\n    from pkg import f  # in a function, through the package's re-export\n"
                              "    return f\n")
    (pkg / "c.py").write_text("from .a import _h\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "d.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.e import x\n"
                                      "else:\n    import zenoh\n")
    (pkg / "e.py").write_text("from pkg.sub import d\nx = 1\n")
    modules = module_files(tmp_path, ["pkg"])
    imports = read_imports(tmp_path, ["pkg"])

    assert cycles(imports, modules) == [["pkg", "pkg.a", "pkg.b"]]  # the TYPE_CHECKING import makes none
    report = cycle_report(imports, modules)
    assert "  pkg.b (pkg/b.py:2) -> pkg" in report and "  pkg.a (pkg/a.py:1) -> pkg.b" in report, report
    assert private_imports(imports, modules) == ["pkg.c (pkg/c.py:1) imports pkg.a._h"]
    assert forbidden(imports, ["pkg"], ["zenoh"], allowed=["pkg.e"]) == ["pkg.sub.d (pkg/sub/d.py:5) imports zenoh"]
    assert forbidden(imports, ["pkg"], ["zenoh"], allowed=["pkg.sub"]) == []
