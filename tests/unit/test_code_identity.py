"""Which code wrote a result (:mod:`covnet.code_identity`): the digest of covnet's source, the
same wherever the same source lies, another for any change."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

from covnet.code_identity import PACKAGES, code_identity, other_code
from tests.conftest import REPO


def _identity_of(root) -> str:
    out = subprocess.run(
        [sys.executable, "-c", "from covnet.code_identity import code_identity as c; print(c())"],
        cwd=root, env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"},
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    return out.stdout.strip()


def test_the_identity_is_of_the_source_not_of_where_it_lies(tmp_path):
    same, changed = tmp_path / "a b", tmp_path / "c"  # another path, with a space
    for root in (same, changed):
        for pkg in PACKAGES:
            shutil.copytree(REPO / pkg, root / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    with (changed / "covnet" / "core" / "metrics.py").open("a") as f:
        f.write("\n# one comment more\n")
    mine = code_identity()
    assert len(mine) == 16 and int(mine, 16) >= 0 and code_identity() == mine
    assert _identity_of(same) == mine
    assert _identity_of(changed) != mine


def test_other_code_names_whose_code_it_is():
    assert other_code(code_identity()) is None
    assert other_code("0123456789abcdef") == (
        f"another covnet's (0123456789abcdef; this one is {code_identity()})"
    )
    for none in (None, "", 7):
        assert other_code(none).startswith("an older covnet's (it names no code")


def test_a_run_and_its_batch_name_their_code(tmp_path):
    from covnet.cli.app import main

    assert main(["mc", str(REPO / "configs/mobile.yaml"), "--trials", "2", "--workers", "1",
                 "--out", str(tmp_path / "mc"), "--no-figures"]) == 0  # fmt: skip
    assert json.loads((tmp_path / "mc" / "batch.json").read_text())["code"] == code_identity()
    assert json.loads((tmp_path / "mc" / "run.json").read_text())["code"] == code_identity()


def test_an_editors_lock_file_or_an_unreadable_file_never_fails_it(tmp_path):
    """An Emacs lock file (``.#config.py``, a dangling link) in the clone made every run exit 1
    after its results, ``run.json`` without a status: the identity read every ``*.py`` and
    raised on it (hunt 15).  Hidden files are left out; an unreadable one counts by its error."""
    root = tmp_path / "c"
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, root / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    clean = _identity_of(root)
    (root / "covnet" / ".#config.py").symlink_to("root@host.1234:1701234567")
    assert _identity_of(root) == clean == code_identity()
    (root / "covnet" / "broken.py").symlink_to("nowhere.py")
    assert _identity_of(root) not in ("", clean)
