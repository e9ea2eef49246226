"""``covnet.interop.stonesoup`` without Stone Soup (simulated in a child process by blocking
the ``stonesoup`` import): an :class:`ImportError` that says how to install the extra; covnet
itself and ``covnet.interop`` import without it."""

from __future__ import annotations

import subprocess
import sys

BLOCK = "import sys; sys.modules['stonesoup'] = None\n"


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", BLOCK + code], capture_output=True, text=True, timeout=120
    )


def test_importing_the_interop_without_stonesoup_names_the_extra():
    r = _run(
        "try:\n    import covnet.interop.stonesoup\nexcept ImportError as e:\n    print('MSG', e)\n"
    )
    assert r.returncode == 0, r.stderr
    assert "MSG covnet.interop.stonesoup needs Stone Soup" in r.stdout
    assert "pip install 'covnet[stonesoup]'" in r.stdout


def test_covnet_and_the_interop_package_do_not_import_stonesoup():
    r = _run("import covnet, covnet.interop, covnet.core.metrics\nprint('OK')\n")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "OK"
