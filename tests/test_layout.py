"""The package's shape, read from the source: the library never imports the benchmark kit, and no import cycles."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "nerfuser_ns"
METHOD_CONFIGS = Path(__file__).resolve().parents[1] / "method_configs"


def _module_name(path: Path) -> str:
    if path.is_relative_to(METHOD_CONFIGS):
        rel = ("nerfuser_ns", "method_configs", *path.relative_to(METHOD_CONFIGS).with_suffix("").parts)
    else:
        rel = ("nerfuser_ns", *path.relative_to(PACKAGE).with_suffix("").parts)
    return ".".join(rel[:-1] if rel[-1] == "__init__" else rel)


def _is_type_checking(node: ast.If) -> bool:
    return isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


def project_imports(path: Path) -> set[str]:
    """Every nerfuser_ns module ``path`` imports at run time (module level or inside functions; not under
    ``if TYPE_CHECKING``), as dotted names."""
    tree = ast.parse(path.read_text())
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node)
            for child in node.body for n in ast.walk(child)}  # fmt: skip
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("nerfuser_ns")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("nerfuser_ns"):
            # "from nerfuser_ns import runs" imports the module nerfuser_ns.runs
            out |= {f"{node.module}.{a.name}" for a in node.names} | {node.module}
    return out


def _modules() -> dict[str, Path]:
    """Installed module name -> source file (method_configs/ installs as nerfuser_ns.method_configs)."""
    return {_module_name(p): p for p in [*PACKAGE.rglob("*.py"), *METHOD_CONFIGS.rglob("*.py")]}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: {i for i in project_imports(p) if i in modules and i != m} for m, p in modules.items()}


def test_the_library_never_imports_the_benchmark_kit():
    offenders = {m: sorted(i for i in deps if i.startswith("nerfuser_ns.bench"))
                 for m, deps in _graph().items() if not m.startswith("nerfuser_ns.bench")}  # fmt: skip
    assert {m: d for m, d in offenders.items() if d} == {}


def test_no_import_cycles():
    graph = _graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d] if d in stack else [m, d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


KIT_IMPORTS = ["import nerfuser_ns.bench.scenes\n", "def f():\n    from nerfuser_ns.bench import scenes\n"]


@pytest.mark.parametrize("source", KIT_IMPORTS)
def test_the_import_reader_sees_kit_imports(tmp_path, source):
    """The rule above can fail: an import of the kit, at module level or inside a function, is found."""
    p = tmp_path / "m.py"
    p.write_text(source)
    assert any(i.startswith("nerfuser_ns.bench") for i in project_imports(p))


def test_type_checking_imports_do_not_count(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from nerfuser_ns import model\n")
    assert project_imports(p) == set()


def test_every_subpackage_is_installed():
    """A package folder missing from pyproject's list works in an editable install and vanishes from a wheel."""
    pyproject = (PACKAGE.parent / "pyproject.toml").read_text()
    listed = set(re.findall(r'"(nerfuser_ns[\w.]*)"', pyproject.split("packages = [", 1)[1].split("]", 1)[0]))
    code = {p.parent for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts}
    folders = {_module_name(p / "__init__.py") for p in code} | {"nerfuser_ns.method_configs"}
    assert folders - listed == set()
