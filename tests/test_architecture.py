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
NAMESPACE = "armfusion"
FORBIDDEN = {"sensors": ("models", "fusion", "tools"), "models": ("fusion", "tools"), "fusion": ("tools",)}


def module_files(root: Path, packages=(*LAYERS, "tools")) -> dict[str, Path]:
    """Every module under ``packages`` by its dotted name as imported (a package by its
    ``__init__``): the layers' folders install below ``armfusion`` (``fusion/cli/main.py`` is
    ``armfusion.fusion.cli.main``); ``tools/`` is not installed and keeps its own name."""
    out = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join([NAMESPACE, *parts] if package in LAYERS else parts)] = path
    return out


def layer(module: str) -> str:
    """The layer (or ``tools``) a dotted module name belongs to."""
    parts = module.split(".")
    return parts[1] if parts[0] == NAMESPACE and len(parts) > 1 else parts[0]


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
                  if layer(t) in FORBIDDEN.get(layer(m), ()))


@pytest.fixture(scope="module")
def graph():
    return import_graph(ROOT)


def test_the_graph_sees_the_imports_it_must(graph):
    assert "armfusion.models.arm" in graph["armfusion.fusion.configfile"]  # module level
    assert "armfusion.fusion.cli.simulate" in graph["armfusion.fusion.cli.demo"]  # from a module import a name
    assert "armfusion.fusion.service.payloads" in graph["armfusion.fusion.cli.nodes"]  # inside a function
    assert "armfusion.fusion.cli.fleet" not in graph["armfusion.fusion.cli.nodes"]
    assert len(graph) > 80


def test_sensors_import_neither_models_nor_fusion_and_models_not_fusion_and_none_imports_tools(graph):
    assert layer_violations(graph) == []


def test_no_import_cycle_among_the_modules_of_the_three_packages(graph):
    ours = {m: {d for d in deps if layer(d) in LAYERS}
            for m, deps in graph.items() if layer(m) in LAYERS}
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
        "sensors/bus.py": "def f():\n    from armfusion.models import arm\n",
        "models/arm.py": "import numpy\n",
        "fusion/service/a.py": "from . import b\n",
        "fusion/service/b.py": "from armfusion.fusion.service.c import x\n",
        "fusion/service/c.py": "if False:\n    from .a import y\nx = 1\n",
        "fusion/d.py": "import tools.bench\n",
        "tools/bench.py": "import armfusion.fusion.d\n",
    })
    graph = import_graph(tmp_path)
    assert layer_violations(graph) == ["armfusion.fusion.d imports tools.bench",
                                       "armfusion.sensors.bus imports armfusion.models.arm"]
    assert cycles(graph) == [["armfusion.fusion.d", "tools.bench"],
                             ["armfusion.fusion.service.a", "armfusion.fusion.service.b", "armfusion.fusion.service.c"]]


# --- rooms: the sub-packages, and tools/ ---------------------------------------------------------


def room(module: str, root: Path = ROOT) -> str:
    """The room a module lives in: its sub-package of a layer (``armfusion.fusion.cli``,
    ``armfusion.models.effects``), else the module itself (``armfusion.fusion.configfile``, ``tools.benchdoc``)."""
    parts = module.split(".")
    folder = parts[1:] if parts[0] == NAMESPACE else parts  # the folders at the repository's top
    if len(folder) >= 2 and (root / folder[0] / folder[1]).is_dir():
        return ".".join(parts[: len(parts) - len(folder) + 2])
    return module


def room_graph(graph: dict[str, set[str]], root: Path = ROOT) -> dict[str, set[str]]:
    """Room -> the other rooms its modules import."""
    out: dict[str, set[str]] = {}
    for m, deps in graph.items():
        r = room(m, root)
        out.setdefault(r, set()).update(room(d, root) for d in deps)
        out[r].discard(r)
    return out


def test_no_import_cycle_among_the_rooms_so_the_command_line_imports_the_service_one_way(graph):
    assert cycles(room_graph(graph)) == []
    rooms = room_graph(graph)
    assert "armfusion.fusion.service" in rooms["armfusion.fusion.cli"]
    assert "armfusion.fusion.cli" not in rooms["armfusion.fusion.service"]


def test_no_import_cycle_among_the_tools(graph):
    tools = {m: {d for d in deps if d.startswith("tools.")} for m, deps in graph.items()
             if m.startswith("tools.")}
    assert cycles(tools) == []


def test_the_room_check_catches_a_cycle_between_sub_packages(tmp_path):
    _write(tmp_path, {
        "fusion/__init__.py": "", "fusion/cli/__init__.py": "", "fusion/service/__init__.py": "",
        "sensors/__init__.py": "", "models/__init__.py": "", "tools/__init__.py": "",
        "fusion/cli/main.py": "from armfusion.fusion.service import node\n",
        "fusion/service/node.py": "x = 1\n",
        "fusion/service/commands.py": "def f():\n    from armfusion.fusion.cli.main import y\n",
    })
    graph = import_graph(tmp_path)
    assert cycles(graph) == []  # no module-level cycle...
    assert cycles(room_graph(graph, tmp_path)) == [["armfusion.fusion.cli", "armfusion.fusion.service"]]  # ...but a room one


# --- the size rule (docs/architecture.md, "Sizes") -----------------------------------------------

MAX_MODULE_LINES = 500
MAX_CLASS_LINES = 300
MAX_FUNCTION_BODY_LINES = 60

OVERSIZED: dict[str, str] = {
    # name -> why it is still over the rule; remove a line when its entry is split
}
"""What is still over the size rule, each with its reason: empty, every module, class and
function of the layers keeps it. A new violation fails the test."""


def _body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A function's body in lines, its signature, decorators and docstring left out."""
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    return body[-1].end_lineno - body[0].lineno + 1 if body else 0


def oversized(root: Path) -> dict[str, int]:
    """Every module, class and function of the layers over the size rule, by name
    (``module``, ``module:Class``, ``module:Class.method``, ``module:outer.inner``) -> its lines."""
    found: dict[str, int] = {}
    for module, path in module_files(root, LAYERS).items():
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            found[module] = len(text.splitlines())

        def visit(node: ast.AST, prefix: str, module: str = module) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.ClassDef):
                    lines = child.end_lineno - child.lineno + 1
                    if lines > MAX_CLASS_LINES:
                        found[f"{module}:{prefix}{child.name}"] = lines
                    visit(child, f"{prefix}{child.name}.")
                elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                    if _body_lines(child) > MAX_FUNCTION_BODY_LINES:
                        found[f"{module}:{prefix}{child.name}"] = _body_lines(child)
                    visit(child, f"{prefix}{child.name}.")
                else:
                    visit(child, prefix)

        visit(ast.parse(text, str(path)), "")
    return found


def test_no_module_class_or_function_over_the_size_rule_but_the_listed_exceptions():
    found = oversized(ROOT)
    assert sorted(set(found) - set(OVERSIZED)) == [], "new violations of the size rule"
    assert sorted(set(OVERSIZED) - set(found)) == [], "now within the rule: remove from OVERSIZED"
    assert all(reason.strip() for reason in OVERSIZED.values())


def test_the_size_rule_is_the_one_docs_architecture_states():
    text = (ROOT / "docs" / "architecture.md").read_text()
    assert (f"no module over {MAX_MODULE_LINES} lines, no class over {MAX_CLASS_LINES} lines, "
            f"no function body over {MAX_FUNCTION_BODY_LINES} lines") in " ".join(text.split())


def test_the_size_check_measures_a_body_without_its_docstring_and_names_nested_functions(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_BODY_LINES))
    _write(tmp_path, {
        "sensors/__init__.py": "", "models/__init__.py": "", "fusion/__init__.py": "",
        "fusion/a.py": f'def ok(\n    a,\n    b,\n):\n    """Doc."""\n{body}',
        "fusion/b.py": f"def register(app):\n    def command():\n{body.replace('    ', '        ')}"
                       "        return 1\n",
    })
    assert oversized(tmp_path) == {"armfusion.fusion.b:register": MAX_FUNCTION_BODY_LINES + 2,
                                   "armfusion.fusion.b:register.command": MAX_FUNCTION_BODY_LINES + 1}


# --- parameters: at most eight, outside compiled kernels ---------------------------------------

MAX_PARAMETERS = 8

_COMMAND_OPTIONS = ("a typer command: its signature is its table of command-line options, each with its "
                    "help, which typer reads to build the command")
_TO_RECORD = "positional values that travel together; to become a typed record"

MANY_PARAMETERS: dict[str, tuple[int, str]] = {
    # name -> (its parameter count today, why); remove a line when its entry takes at most the limit
    "armfusion.fusion.cli.calibrate_joints:calibrate_joints": (13, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.calibrate_sensors:calibrate_sensors": (12, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.demo:demo_command": (11, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.diagnose:diagnose_command": (13, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.drivers:drivers_command": (22, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.fleet:fleet_command": (11, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.fleet:monitor_command": (10, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.nodes:record_command": (10, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.nodes:replay_command": (11, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.nodes:serve_command": (17, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.plan_maneuver:plan_command": (9, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.simulate:register.simulate_command": (12, _COMMAND_OPTIONS),
    "armfusion.fusion.cli.track:track": (13, _COMMAND_OPTIONS),
}
"""Functions of the layers over the parameter limit, with their count and why. A shrinking list
like ``OVERSIZED``: a new one fails, and so does one that has come down to the limit."""


def _is_kernel(node: ast.FunctionDef) -> bool:
    """Whether a function is compiled by numba (``@njit``/``@jit``, called or bare)."""
    def name(d: ast.expr) -> str:
        d = d.func if isinstance(d, ast.Call) else d
        return d.id if isinstance(d, ast.Name) else d.attr if isinstance(d, ast.Attribute) else ""
    return any(name(d) in ("njit", "jit") for d in node.decorator_list)


def many_parameters(root: Path) -> dict[str, int]:
    """Every function of the layers, compiled kernels aside, taking more than the limit
    (``self``/``cls`` not counted, ``*args``/``**kwargs`` one each) -> its count."""
    found: dict[str, int] = {}
    for module, path in module_files(root, LAYERS).items():
        def visit(node: ast.AST, prefix: str, module: str = module) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.ClassDef):
                    visit(child, f"{prefix}{child.name}.")
                elif isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                    a = child.args
                    n = (sum(x.arg not in ("self", "cls") for x in a.posonlyargs + a.args + a.kwonlyargs)
                         + (a.vararg is not None) + (a.kwarg is not None))
                    if n > MAX_PARAMETERS and not _is_kernel(child):
                        found[f"{module}:{prefix}{child.name}"] = n
                    visit(child, f"{prefix}{child.name}.")
                else:
                    visit(child, prefix)

        visit(ast.parse(path.read_text(), str(path)), "")
    return found


def test_no_function_over_the_parameter_limit_but_the_listed_ones():
    found = many_parameters(ROOT)
    listed = {name: n for name, (n, _) in MANY_PARAMETERS.items()}
    assert {k: n for k, n in found.items() if n > listed.get(k, 0)} == {}, "new functions over the limit"
    assert sorted(set(listed) - set(found)) == [], "now within the limit: remove from MANY_PARAMETERS"


def test_the_parameter_count_skips_self_and_kernels_and_counts_star_args(tmp_path):
    _write(tmp_path, {
        "sensors/__init__.py": "", "models/__init__.py": "", "fusion/__init__.py": "",
        "fusion/a.py": ("from numba import njit\n"
                        "class A:\n    def m(self, a, b, c, d, e, f, g, h):\n        pass\n"
                        "def f(a, b, c, d, e, f2, g, h, *rest):\n    pass\n"
                        "@njit(cache=True)\ndef k(a, b, c, d, e, f, g, h, i):\n    pass\n"),
    })
    assert many_parameters(tmp_path) == {"armfusion.fusion.a:f": 9}


# --- reaches into another object's private attributes --------------------------------------------

PRIVATE_REACHES: dict[str, tuple[int, str]] = {
    # module -> (how many ``x._name`` with x not self/cls, why)
    "armfusion.fusion.cli.main": (1, "typer vendors click as typer._click: its UsageError has no public name"),
    "armfusion.fusion.tracking.frames": (1, "a named tuple's own _fields (underscored not to clash with fields)"),
    "armfusion.fusion.tracking.measurement": (1, "a named tuple's own _replace"),
}
"""Where code still reads or writes another object's private attribute, with the count and
the reason."""


def private_reaches(root: Path) -> dict[str, int]:
    """Module -> how many ``x._name`` it writes where ``x`` is not ``self`` or ``cls`` (dunders
    not counted)."""
    out: dict[str, int] = {}
    for module, path in module_files(root, LAYERS).items():
        n = sum(1 for node in ast.walk(ast.parse(path.read_text(), str(path)))
                if isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")))
        if n:
            out[module] = n
    return out


def test_private_reaches_only_where_listed_and_no_more_than_listed():
    found = private_reaches(ROOT)
    listed = {m: n for m, (n, _) in PRIVATE_REACHES.items()}
    assert {m: n for m, n in found.items() if n > listed.get(m, 0)} == {}, "new reaches into private names"
    assert {m: n for m, n in listed.items() if found.get(m, 0) < n} == {}, "fewer now: lower the count"


def test_the_reach_count_skips_self_and_cls_and_counts_others(tmp_path):
    _write(tmp_path, {"sensors/__init__.py": "", "models/__init__.py": "", "fusion/__init__.py": "",
                      "fusion/a.py": "class A:\n    def f(self, o):\n        self._x = cls._y = o._z\n"
                                     "        return o.__dict__, o._w\n"})
    assert private_reaches(tmp_path) == {"armfusion.fusion.a": 2}


# --- one import namespace --------------------------------------------------------------------------


def old_style_imports(root: Path) -> list[str]:
    """Every import, in any Python file of the repository, of a layer by its folder's name as if
    it were a top-level package (``import fusion``, ``from models.arm import ...``): the layers
    install below ``armfusion`` only, so such an import fails where armfusion is installed, or
    finds another distribution's package of that name, or loads a module twice."""
    found = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        if rel.parts[0].startswith(".") or "site-packages" in rel.parts or rel.parts[0] == "build":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and not node.level and node.module
                     else [])
            found += [f"{rel.as_posix()}:{node.lineno} {n}" for n in names if n.split(".")[0] in LAYERS]
    return found


def test_every_import_of_the_layers_goes_through_the_one_namespace():
    assert old_style_imports(ROOT) == []


def test_the_namespace_check_sees_an_old_style_import(tmp_path):
    _write(tmp_path, {"tools/a.py": "import numpy\nfrom armfusion.models import arm\n",
                      "tests/b.py": "def f():\n    from models.arm import ArmModel\n    import fusion.cli\n"})
    assert old_style_imports(tmp_path) == ["tests/b.py:2 models.arm", "tests/b.py:3 fusion.cli"]
