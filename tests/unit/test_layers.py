"""The architecture's rules (README, "Architecture"; ``../shared/STYLE.md`` §7.2), read from the
code with ``ast`` over every file of the five packages:

- ``covnet/core/**`` imports only the standard library, numpy, scipy and ``covnet.core``;
- ``covnet/**`` never imports the process packages (``manager``, ``sensors``, ``world``,
  ``recorder``); a kind's package never imports another kind's package;
- no import cycle among the modules, function-local imports counted;
- a function-local import is there for start-up time, and its function says so;
- nothing outside the kind registry, the kinds' own packages and their role modules decides
  by the kind's name;
- importing the core, the config and the in-process simulator does not import zenoh.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("covnet", "manager", "sensors", "world", "recorder")
PROCESS_PACKAGES = ("manager", "sensors", "world", "recorder")
KINDS = {"covariance_control": "covariance", "mobile": "mobile", "passive": "passive"}
"""Each kind's package (``covnet/<kind>/``) and its role modules' name (``manager/<name>.py``)."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def _resolve(module: str, importer: str, is_package: bool, node: ast.ImportFrom) -> list[str]:
    """The first-party modules an import statement loads (``from pkg import mod`` -> pkg.mod
    when that is a module)."""
    if node.level:
        base = importer.split(".")
        base = base if is_package else base[:-1]
        base = base[: len(base) - (node.level - 1)]
        module = ".".join([*base, *([module] if module else [])])
    out = [module]
    for alias in node.names:
        sub = f"{module}.{alias.name}"
        if sub in MODULES:
            out.append(sub)
    return out


def _imports(name: str) -> Iterator[tuple[ast.AST, str, bool]]:
    """``(node, imported module, function-local)`` for every import of module ``name``."""
    path = MODULES[name]
    tree = ast.parse(path.read_text(), filename=str(path))
    local: set[int] = set()
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            local |= {id(n) for n in ast.walk(fn) if isinstance(n, ast.Import | ast.ImportFrom)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node, alias.name, id(node) in local
        elif isinstance(node, ast.ImportFrom):
            for mod in _resolve(node.module or "", name, path.name == "__init__.py", node):
                yield node, mod, id(node) in local


def _first_party(mod: str) -> str | None:
    """The module of ours that ``mod`` is (or is in), if any."""
    while mod and mod not in MODULES:
        mod = mod.rpartition(".")[0]
    return mod or None


def test_core_imports_only_the_standard_library_numpy_scipy_and_core():
    core = [m for m in MODULES if m.startswith("covnet.core")]
    assert len(core) > 20
    allowed = {"numpy", "scipy", *sys.stdlib_module_names}
    for name in core:
        for _, mod, _ in _imports(name):
            top = mod.split(".")[0]
            if top == "covnet":
                assert mod.startswith("covnet.core"), f"{name} imports {mod} (outside the core)"
            else:
                assert top in allowed, f"{name} imports {mod}"


def test_covnet_never_imports_the_process_packages():
    for name in (m for m in MODULES if m.startswith("covnet")):
        for _, mod, _ in _imports(name):
            assert mod.split(".")[0] not in PROCESS_PACKAGES, f"{name} imports {mod}"


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_kind_never_imports_another_kind(kind):
    """A kind's package and its role modules use the shared layers, never another kind's code
    (what two kinds share belongs below them)."""
    role = KINDS[kind]
    own = [m for m in MODULES if m.startswith(f"covnet.{kind}")]
    own += [
        f"{pkg}.{role}" for pkg in ("manager", "sensors", "world") if f"{pkg}.{role}" in MODULES
    ]
    assert len(own) > 5
    others = [k for k in KINDS if k != kind]
    other_roles = {f"{pkg}.{KINDS[k]}" for k in others for pkg in ("manager", "sensors", "world")}
    for name in own:
        for _, mod, _ in _imports(name):
            assert not any(mod.startswith(f"covnet.{k}") for k in others), f"{name} imports {mod}"
            assert mod not in other_roles, f"{name} imports {mod}"


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for name in MODULES:
        for _, mod, _ in _imports(name):
            target = _first_party(mod)
            if target is not None and target != name:
                graph[name].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_function_local_imports_included():
    assert _cycles(_graph()) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_function_local_imports_say_they_are_for_start_up_time():
    """A function-local import must buy start-up time; the function says so (a comment or its
    docstring between its ``def`` and the import mentions start-up)."""
    missing = []
    for path in MODULES.values():
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Import | ast.ImportFrom):
                    span = "\n".join(lines[fn.lineno - 1 : node.lineno]).lower()
                    if "start-up" not in span:
                        missing.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not missing, "function-local imports without a start-up reason:\n" + "\n".join(missing)


def test_nothing_outside_the_kinds_decides_by_the_kind():
    """Comparing with a kind's name (``== "mobile"``, ``in ("mobile", "passive")``) or asking
    ``isinstance`` of a kind's config is the registry's job (covnet.kinds), or the kind's own."""
    names = set(KINDS)
    own_prefixes = [f"covnet.{k}" for k in KINDS] + [
        f"{pkg}.{r}" for r in KINDS.values() for pkg in ("manager", "sensors", "world")
    ]
    offenders = []
    for name, path in MODULES.items():
        if name == "covnet.kinds" or any(name.startswith(p) for p in own_prefixes):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Compare):
                consts = [
                    c.value
                    for c in ast.walk(node)
                    if isinstance(c, ast.Constant) and isinstance(c.value, str)
                ]
                if names & set(consts):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
            if isinstance(node, ast.Name) and node.id in ("MobileConfig", "PassiveConfig"):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, offenders


def test_importing_covnet_and_core_does_not_import_zenoh():
    code = (
        "import sys, covnet, covnet.core.allocation, covnet.core.metrics, covnet.core.kalman, "
        "covnet.covariance_control.simulate, covnet.config, covnet.kinds; "
        "assert 'zenoh' not in sys.modules, 'zenoh imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_node_processes_build_only_what_they_use(paper_path):
    """A sensor's and the world's model never build the allocation search tables (issue 13):
    only a decision does."""
    code = f"""
import threading
from covnet import kinds
from covnet.core.allocation import _fast as _allocation_fast
from covnet.covariance_control.model import build_model, truth_trajectory
from sensors.covariance import NoiseTable
built = []
init = _allocation_fast.SearchTables.__init__
def spy(self, *a, **k):
    built.append(1)
    init(self, *a, **k)
_allocation_fast.SearchTables.__init__ = spy
_, sc = kinds.load({str(paper_path)!r})
model = build_model(sc)
truth_trajectory(model)
NoiseTable(model, 0)
assert built == [], "a node built the search tables"
model.plan
assert built, "the spy saw nothing"
"""
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
