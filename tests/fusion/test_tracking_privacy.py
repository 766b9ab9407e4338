"""The tracker's modules talk through public names: none reads or writes another object's
private attributes (``x._name`` with ``x`` not ``self``/``cls``), but the exceptions listed
here, each with its reason. A new reach fails this test: give the owner a public name."""

import ast
from pathlib import Path

TRACKING = Path(__file__).resolve().parents[2] / "fusion" / "tracking"

NAMEDTUPLE_API = {"_fields", "_replace", "_make", "_asdict"}
"""A named tuple's own public methods (underscored so as not to clash with field names)."""

EXCEPTIONS = {
    # the sigma-point filter reads its measurement groups' prepared arrays (the compiled
    # innovation's inputs): GroupPlan is the filter's own helper, split off for size
    ("ukf.py", "plan"),
}


def reaches():
    found = []
    for p in sorted(TRACKING.glob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            if not (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                    and not node.attr.startswith("__") and node.attr not in NAMEDTUPLE_API):
                continue
            v = node.value
            if isinstance(v, ast.Name) and v.id in ("self", "cls"):
                continue
            owner = v.id if isinstance(v, ast.Name) else ast.unparse(v)
            if (p.name, owner) not in EXCEPTIONS:
                found.append(f"{p.name}:{node.lineno} {ast.unparse(node)}")
    return found


def test_no_module_of_the_tracker_reaches_into_another_object():
    assert reaches() == []


def test_the_check_sees_a_reach(tmp_path):
    (tmp_path / "a.py").write_text("def f(tr):\n    return tr._ukf._x\n")
    globals()["TRACKING"], saved = tmp_path, TRACKING
    try:
        assert reaches() == ["a.py:2 tr._ukf._x", "a.py:2 tr._ukf"]
    finally:
        globals()["TRACKING"] = saved
