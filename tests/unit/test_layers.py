"""The import direction of STYLE §7.2: the numerical core never imports I/O or zenoh."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[2] / "covnet" / "core"
FORBIDDEN = {"zenoh", "msgpack", "yaml", "pydantic", "matplotlib", "rich", "sensors", "manager"}


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


def test_core_imports_only_numpy_scipy_and_core():
    files = sorted(CORE.rglob("*.py"))
    assert files
    for f in files:
        for name in _imports(f):
            top = name.split(".")[0]
            assert top not in FORBIDDEN, f"{f.name} imports {name}"
            if top == "covnet":
                assert name.startswith("covnet.core"), f"{f.name} imports {name} (outside the core)"


def test_importing_covnet_and_core_does_not_import_zenoh():
    code = (
        "import sys, covnet, covnet.core.allocation, covnet.core.metrics, covnet.core.kalman, "
        "covnet.covariance_control.simulate, covnet.config; "
        "assert 'zenoh' not in sys.modules, 'zenoh imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
