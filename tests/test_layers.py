"""Package boundaries: every import between the project's packages follows the layers, and no modules import each
other in a cycle.

Layers (a package may import its own modules and those of the packages listed for it)::

    common                        the vocabulary: samples, angles, config machinery, log format, report files
    gsoe, fusion   -> common      the optical estimator and the EKF (pure)
    pipeline       -> common, gsoe, fusion
    sim, nav       -> common, gsoe, fusion, pipeline     (never each other)
    cli            -> all of them: the command line is the only place that may import both sim and nav

An import is every ``import``/``from ... import`` statement of a module, at its top or inside a function (a lazy
import runs too), and ``importlib.import_module``/``__import__`` with a literal name; imports under
``if TYPE_CHECKING:`` are left out (they never run).  A process started by name (``python -m sim.mavlink_vehicle``)
or a module named in a config string is not an import.
"""

from __future__ import annotations

import ast
import textwrap
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: package -> the other packages it may import
LAYERS: dict[str, frozenset[str]] = {
    "common": frozenset(),
    "gsoe": frozenset({"common"}),
    "fusion": frozenset({"common"}),
    "pipeline": frozenset({"common", "gsoe", "fusion"}),
    "sim": frozenset({"common", "gsoe", "fusion", "pipeline"}),
    "nav": frozenset({"common", "gsoe", "fusion", "pipeline"}),
    "cli": frozenset({"common", "gsoe", "fusion", "pipeline", "sim", "nav"}),
}
#: top-level folders of the tree that are not packages of the module
NOT_LAYERED = frozenset({"tests"})


@dataclass(frozen=True)
class Edge:
    """``src`` imports ``dst`` (dotted module names) at ``path:line``."""

    src: str
    dst: str
    path: str
    line: int

    def __str__(self) -> str:
        return f"{self.src} -> {self.dst} ({self.path}:{self.line})"


def _package(module: str) -> str:
    return module.split(".", 1)[0]


def discover_modules(root: Path, packages: Iterable[str]) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` file under the ``packages`` folders of ``root``."""
    out: dict[str, Path] = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob("*.py")):
            if "__pycache__" in f.parts:
                continue
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = f
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _runtime_nodes(node: ast.AST) -> Iterator[ast.AST]:
    """Every node below ``node`` except the bodies of ``if TYPE_CHECKING:`` (their ``else`` runs)."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and _is_type_checking(child.test):
            for other in child.orelse:
                yield other
                yield from _runtime_nodes(other)
            continue
        yield child
        yield from _runtime_nodes(child)


def _imported_names(node: ast.AST, module: str, is_package: bool) -> Iterator[tuple[str, list[str]]]:
    """(module imported, names taken from it) for one import node; relative imports made absolute."""
    if isinstance(node, ast.Import):
        for alias in node.names:
            yield alias.name, []
    elif isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:
            anchor = module.split(".") if is_package else module.split(".")[:-1]
            anchor = anchor[:len(anchor) - (node.level - 1)]
            base = ".".join([*anchor, base] if base else anchor)
        yield base, [a.name for a in node.names if a.name != "*"]
    elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
            and isinstance(node.args[0].value, str):
        f = node.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        if name in ("import_module", "__import__"):
            yield node.args[0].value, []


def import_graph(root: Path, packages: Iterable[str]) -> tuple[list[Edge], list[Edge]]:
    """(edges between the project's modules, imports of a project package that name no module of it)."""
    packages = set(packages)
    modules = discover_modules(root, packages)
    edges: list[Edge] = []
    unresolved: list[Edge] = []
    for mod, path in modules.items():
        rel = path.relative_to(root).as_posix()
        tree = ast.parse(path.read_text(), filename=rel)
        for node in _runtime_nodes(tree):
            for target, names in _imported_names(node, mod, path.name == "__init__.py"):
                if _package(target) not in packages:
                    continue
                line = getattr(node, "lineno", 0)
                if target not in modules:
                    unresolved.append(Edge(mod, target, rel, line))
                    continue
                subs = [f"{target}.{n}" for n in names if f"{target}.{n}" in modules]
                for dst in subs or [target]:
                    if dst != mod:
                        edges.append(Edge(mod, dst, rel, line))
    return edges, unresolved


def layer_violations(edges: Iterable[Edge], layers: Mapping[str, frozenset[str]]) -> list[Edge]:
    """The edges from one package to another that its layer does not allow (an unknown package allows nothing)."""
    out = []
    for e in edges:
        src, dst = _package(e.src), _package(e.dst)
        if src != dst and dst not in layers.get(src, frozenset()):
            out.append(e)
    return out


def import_cycles(edges: Iterable[Edge]) -> list[list[Edge]]:
    """The edges inside each strongly connected component of more than one module (Tarjan): every import cycle."""
    edges = list(edges)
    succ: dict[str, list[str]] = {}
    for e in edges:
        succ.setdefault(e.src, []).append(e.dst)
        succ.setdefault(e.dst, [])
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in succ[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                components.append(comp)

    for v in sorted(succ):
        if v not in index:
            visit(v)
    return [sorted((e for e in edges if e.src in comp and e.dst in comp), key=str) for comp in components]


def _listing(edges: Iterable[Edge]) -> str:
    return "\n  " + "\n  ".join(sorted({str(e) for e in edges}))


# --------------------------------------------------------------------------------------------------------------
# The project


def _project_graph() -> tuple[list[Edge], list[Edge]]:
    return import_graph(ROOT, LAYERS)


def test_every_package_of_the_tree_has_a_layer() -> None:
    found = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()} - NOT_LAYERED
    assert found == set(LAYERS), f"packages without a layer: {sorted(found - set(LAYERS))}; " \
                                 f"layers without a package: {sorted(set(LAYERS) - found)}"


def test_the_layer_table_is_a_hierarchy_with_the_command_line_on_top() -> None:
    for pkg, allowed in LAYERS.items():
        assert pkg not in allowed and allowed <= set(LAYERS)
        for dep in allowed:
            assert LAYERS[dep] <= allowed, f"{pkg} may import {dep} but not what {dep} imports"
    assert [p for p, allowed in LAYERS.items() if {"sim", "nav"} <= allowed] == ["cli"]


def test_the_import_graph_covers_the_packages() -> None:
    """The checker sees the tree (so that the checks below cannot pass on an empty graph)."""
    edges, _ = _project_graph()
    pairs = {(_package(e.src), _package(e.dst)) for e in edges}
    for pair in (("gsoe", "common"), ("fusion", "common"), ("pipeline", "gsoe"), ("sim", "pipeline"),
                 ("nav", "fusion"), ("cli", "sim"), ("cli", "nav")):
        assert pair in pairs, pair


def test_packages_import_only_their_lower_layers() -> None:
    edges, _ = _project_graph()
    bad = layer_violations(edges, LAYERS)
    assert not bad, "imports against the layers (see tests/test_layers.py):" + _listing(bad)


def test_no_import_cycles_between_modules() -> None:
    edges, _ = _project_graph()
    cycles = import_cycles(edges)
    assert not cycles, "import cycles:" + "".join(_listing(c) for c in cycles)


def test_every_project_import_names_an_existing_module() -> None:
    """A lazy import of a moved module fails only when its function runs: catch it here."""
    _, unresolved = _project_graph()
    assert not unresolved, "imports of project modules that do not exist:" + _listing(unresolved)


# --------------------------------------------------------------------------------------------------------------
# The checker itself, on a tiny tree with known violations and a known cycle


SYNTHETIC: dict[str, str] = {
    "common/__init__.py": "",
    "common/a.py": "import json\nfrom sim import x\n",                        # violation: common -> sim
    "sim/__init__.py": "",
    "sim/x.py": "import common.a\n\ndef f():\n    from sim.y import g\n    return g\n",   # lazy: x -> y
    "sim/y.py": textwrap.dedent("""\
        from typing import TYPE_CHECKING

        from sim import x

        if TYPE_CHECKING:
            from nav import z
        else:
            from common import a

        def g():
            return x
        """),                                                                 # y -> x: cycle with x
    "nav/__init__.py": "",
    "nav/z.py": "import sim.x\nfrom . import w\nfrom sim.gone import q\n",    # violation nav -> sim; unresolved
    "nav/w.py": "from .z import thing\n",                                     # relative: a cycle z <-> w
    "cli/__init__.py": "",
    "cli/main.py": "import importlib\nfrom nav import z\nfrom sim import x\nimportlib.import_module('nav.w')\n",
}


def _synthetic(tmp_path: Path) -> tuple[list[Edge], list[Edge]]:
    for rel, text in SYNTHETIC.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    return import_graph(tmp_path, LAYERS)


def test_checker_sees_lazy_relative_and_importlib_imports_but_not_type_checking_ones(tmp_path: Path) -> None:
    edges, unresolved = _synthetic(tmp_path)
    pairs = {(e.src, e.dst) for e in edges}
    assert pairs == {("common.a", "sim.x"), ("sim.x", "common.a"), ("sim.x", "sim.y"), ("sim.y", "sim.x"),
                     ("sim.y", "common.a"), ("nav.z", "sim.x"), ("nav.z", "nav.w"), ("nav.w", "nav.z"),
                     ("cli.main", "nav.z"), ("cli.main", "sim.x"), ("cli.main", "nav.w")}
    assert [(e.src, e.dst, e.line) for e in unresolved] == [("nav.z", "sim.gone", 3)]


def test_checker_reports_the_violating_edges(tmp_path: Path) -> None:
    edges, _ = _synthetic(tmp_path)
    bad = layer_violations(edges, LAYERS)
    assert sorted(str(e) for e in bad) == ["common.a -> sim.x (common/a.py:2)", "nav.z -> sim.x (nav/z.py:1)"]
    # the command line may import both sides
    assert not [e for e in bad if e.src.startswith("cli.")]


def test_checker_reports_every_cycle_with_its_edges(tmp_path: Path) -> None:
    edges, _ = _synthetic(tmp_path)
    cycles = sorted(([str(e) for e in c] for c in import_cycles(edges)), key=lambda c: c[0])
    assert cycles == [
        ["common.a -> sim.x (common/a.py:2)", "sim.x -> common.a (sim/x.py:1)", "sim.x -> sim.y (sim/x.py:4)",
         "sim.y -> common.a (sim/y.py:8)", "sim.y -> sim.x (sim/y.py:3)"],
        ["nav.w -> nav.z (nav/w.py:1)", "nav.z -> nav.w (nav/z.py:2)"],
    ]
