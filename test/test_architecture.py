"""The codebase's shape, checked: no import cycles, modules and functions of readable size, one place per name.

These read the source with :mod:`ast`; nothing is imported or run.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

from msg_adapters import names

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("t42_transfer", "msg_adapters")
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
LONG_ON_PURPOSE = "Longer than 80 lines because"
"""A function's docstring that starts a sentence with this may exceed the limit: it says why."""


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for file in sorted((ROOT / package).rglob("*.py")):
            parts = file.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = file
    return found


MODULES = _modules()


def _imported(module: str, file: Path, tree: ast.Module) -> Iterator[str]:
    """Project modules ``module`` imports, at any depth in the file (lazy imports count too)."""
    package = module if file.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            targets = [base, *(f"{base}.{alias.name}" for alias in node.names)]
        else:
            continue
        for target in targets:
            parts = target.split(".")
            for depth in range(1, len(parts) + 1):  # importing a.b.c runs a and a.b too,
                name = ".".join(parts[:depth])  # unless the importer is inside them (already running)
                if name in MODULES and name != module and not module.startswith(name + "."):
                    yield name


def _graph() -> dict[str, set[str]]:
    return {m: set(_imported(m, f, ast.parse(f.read_text()))) for m, f in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_among_the_projects_modules() -> None:
    assert _cycles(_graph()) == []


def test_msg_adapters_is_the_layer_below_and_imports_nothing_of_t42_transfer() -> None:
    graph = _graph()
    upward = {m: sorted(d for d in deps if d.startswith("t42_transfer"))
              for m, deps in graph.items() if m.startswith("msg_adapters")}
    assert {m: d for m, d in upward.items() if d} == {}


def test_modules_and_functions_stay_readable_in_size() -> None:
    too_long = []
    for module, file in MODULES.items():
        text = file.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            too_long.append(f"{module}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES and LONG_ON_PURPOSE not in (ast.get_docstring(node) or ""):
                    too_long.append(f"{module}.{node.name}: {length} lines")
    assert sorted(too_long) == []


# ------------------------------------------------------------------ one place per name
INTERFACE_WORDS = {value for key, value in vars(names).items() if key.isupper() and isinstance(value, str)}
"""Every topic, service and status word of the interface module."""
SCANNED = ("t42_transfer", "msg_adapters", "bench", "scripts", "launch")


def _literals(tree: ast.Module) -> Iterator[tuple[int, str]]:
    """String constants of a module that are not docstrings, dict keys or subscripts."""
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                docstrings.add(id(body[0].value))
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            docstrings.add(id(node.value))  # attribute docstrings
        if isinstance(node, ast.Dict):  # keys of a record ({"dropped": 3}) are field names, not names
            docstrings.update(id(key) for key in node.keys if key is not None)
        if isinstance(node, ast.Subscript):
            docstrings.add(id(node.slice))
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            yield node.lineno, node.value


def test_interface_words_cover_the_names_the_nodes_use() -> None:
    assert {"hand/status", "t42/transfer", "trajectory_done", "dropped", "~/split"} <= INTERFACE_WORDS


def test_every_topic_service_and_status_word_is_written_once() -> None:
    again = []
    for folder in SCANNED:
        for file in sorted((ROOT / folder).rglob("*.py")):
            if file == ROOT / "msg_adapters" / "names.py":
                continue
            for line, text in _literals(ast.parse(file.read_text())):
                if text in INTERFACE_WORDS or text.lstrip("/") in INTERFACE_WORDS:
                    again.append(f"{file.relative_to(ROOT)}:{line}: {text!r}")
    assert again == []


@pytest.mark.parametrize("text", ['x = "hand/status"\n', 'f(["dropped"])\n', 'g(f"{a}/clock")\n'])
def test_the_literal_scan_sees_a_name_written_again(text: str) -> None:
    assert [value for _, value in _literals(ast.parse(text)) if value in INTERFACE_WORDS]


def _defines(tree: ast.Module) -> set[str]:
    """Names a module binds at its top level (definitions, assignments, imports)."""
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
            exported = any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets)
            if exported and isinstance(node.value, (ast.List, ast.Tuple)):  # names __getattr__ may serve
                names.update(e.value for e in node.value.elts if isinstance(e, ast.Constant))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.If, ast.Try)):
            names.update(_defines(ast.Module(body=node.body + getattr(node, "orelse", []), type_ignores=[])))
    return names


def _unresolved(files: list[Path]) -> list[str]:
    """``from <project module> import name`` lines whose name the module does not define."""
    defined = {m: _defines(ast.parse(f.read_text())) for m, f in MODULES.items()}
    missing = []
    for file in files:
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.ImportFrom) and not node.level and node.module in MODULES:
                missing += [f"{file.name}:{node.lineno}: {node.module}.{a.name}" for a in node.names
                            if a.name != "*" and a.name not in defined[node.module]
                            and f"{node.module}.{a.name}" not in MODULES]
    return missing


def test_the_resolver_sees_a_name_that_is_gone(tmp_path: Path) -> None:
    script = tmp_path / "script.py"
    script.write_text("from t42_transfer.evaluation.experiment import target_split, _gone\n")
    assert [line.split(": ")[1] for line in _unresolved([script])] == ["t42_transfer.evaluation.experiment._gone"]


def test_scripts_benchmarks_and_tests_import_only_names_the_package_has() -> None:
    """Benchmarks and scripts run in the slow suite or by hand: a renamed function must fail here first."""
    files = [f for d in ("bench", "scripts", "docs", "test", *PACKAGES) for f in sorted((ROOT / d).rglob("*.py"))]
    assert _unresolved(files) == []
