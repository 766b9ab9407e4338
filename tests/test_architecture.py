"""The layers hold: sensors -> models -> fusion, tools/ on top, config/ files only, and no
import cycle among the modules of the three packages.

Read statically with :mod:`ast` from the source files, so nothing is imported and every
import counts wherever it is written: at module level, inside a function (a lazy import
is still a dependency: the module fails without it, only later), and under
``if TYPE_CHECKING:`` (a type from a higher layer is still a dependency of the design).
``from pkg import name`` counts as a dependency on ``pkg.name`` when that is a module of
ours, else on ``pkg``; relative imports are resolved. A module's own package
``__init__`` is not counted as a dependency of it (Python runs it first anyway).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("sensors", "models", "fusion")
FORBIDDEN = {"sensors": ("models", "fusion", "tools"), "models": ("fusion", "tools"), "fusion": ("tools",)}


def module_files(root: Path, packages=(*LAYERS, "tools")) -> dict[str, Path]:
    """Every module under ``packages`` by its dotted name (a package by its ``__init__``)."""
    out = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def imported_names(name: str, path: Path, modules: set[str]) -> set[str]:
    """The dotted names ``path`` imports, anywhere in the file, relative ones resolved:
    ``import a.b`` gives ``a.b``; ``from a import b`` gives ``a.b`` if that is one of
    ``modules``, else ``a``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join([*parts[: len(parts) - (node.level - 1)], *([base] if base else [])])
            names.update(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                         for alias in node.names)
    return names


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the modules of ours it imports (a name below a module counts as that
    module); its own packages left out."""
    modules = module_files(root)
    graph = {}
    for name, path in modules.items():
        own_packages = {name.rsplit(".", k)[0] for k in range(1, name.count(".") + 1)}
        deps = set()
        for target in imported_names(name, path, set(modules)):
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name and target not in own_packages:
                deps.add(target)
        graph[name] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    return sorted(f"{m} imports {t}" for m, deps in graph.items() for t in deps
                  if t.split(".")[0] in FORBIDDEN.get(m.split(".")[0], ()))


@pytest.fixture(scope="module")
def graph():
    return import_graph(ROOT)


def test_the_graph_sees_the_imports_it_must(graph):
    assert "models.arm" in graph["fusion.configfile"]  # module level
    assert "fusion.cli.simulate" in graph["fusion.cli.demo"]  # from a module import a name
    assert "fusion.service.payloads" in graph["fusion.cli.nodes"]  # inside a function
    assert "fusion.cli.fleet" not in graph["fusion.cli.nodes"]
    assert len(graph) > 80


def test_sensors_import_neither_models_nor_fusion_and_models_not_fusion_and_none_imports_tools(graph):
    assert layer_violations(graph) == []


def test_no_import_cycle_among_the_modules_of_the_three_packages(graph):
    ours = {m: {d for d in deps if d.split(".")[0] in LAYERS}
            for m, deps in graph.items() if m.split(".")[0] in LAYERS}
    assert cycles(ours) == []


def test_config_holds_files_only():
    assert sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "config").rglob("*.py")) == []


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_the_checks_catch_a_lazy_upward_import_and_a_cycle_through_a_relative_import(tmp_path):
    _write(tmp_path, {
        "sensors/__init__.py": "", "models/__init__.py": "", "tools/__init__.py": "",
        "fusion/__init__.py": "", "fusion/service/__init__.py": "",
        "sensors/bus.py": "def f():\n    from models import arm\n",
        "models/arm.py": "import numpy\n",
        "fusion/service/a.py": "from . import b\n",
        "fusion/service/b.py": "from fusion.service.c import x\n",
        "fusion/service/c.py": "if False:\n    from .a import y\nx = 1\n",
        "fusion/d.py": "import tools.bench\n",
        "tools/bench.py": "import fusion.d\n",
    })
    graph = import_graph(tmp_path)
    assert layer_violations(graph) == ["fusion.d imports tools.bench", "sensors.bus imports models.arm"]
    assert cycles(graph) == [["fusion.d", "tools.bench"],
                             ["fusion.service.a", "fusion.service.b", "fusion.service.c"]]
