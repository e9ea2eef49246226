"""The documentation stands on its own in a clone of the repository (issue 26, usability 7).

- every relative link of ``README.md`` and ``docs/**/*.md`` (Markdown ``[text](target)`` and
  HTML ``src=``/``href=``) names a file of the repository, and a ``#fragment`` into a Markdown
  file names one of its headings (GitHub's anchors);
- a Markdown file named in a code span (``docs/netem.md``) exists too, and no reference leaves
  the repository (``../shared/spec/...`` is not in a clone);
- every ``covnet.…`` (or ``manager.…``, ``sensors.…``) name in a code span of ``docs/maths``
  is an importable module or an attribute of one, so the pages cannot name a function that
  was renamed or removed.
"""

from __future__ import annotations

import importlib
import re
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
MATHS = sorted((ROOT / "docs" / "maths").glob("*.md"))

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HTML = re.compile(r"""\b(?:src|href)\s*=\s*["']([^"']+)["']""")
_CODE = re.compile(r"`([^`]+)`")  # a code span may wrap a line
_MD_PATH = re.compile(r"^(?:\.{1,2}/)*[\w.-]+(?:/[\w.-]+)*\.md(?:#[\w-]*)?$")
_NAME = re.compile(r"^(?:covnet|manager|sensors|world|recorder)(?:\.\w+)+$")


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _text(path: Path) -> str:
    """The file without its fenced code blocks (examples there are not links)."""
    return _FENCE.sub("", path.read_text(encoding="utf-8"))


def _external(target: str) -> bool:
    return re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) is not None or target.startswith("//")


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`|\*\*|__", "", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen: Counter[str] = Counter()
    out = set()
    for line in _text(path).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            s = _slug(m.group(1))
            out.add(s if seen[s] == 0 else f"{s}-{seen[s]}")
            seen[s] += 1
    return out


def _references(path: Path) -> list[str]:
    text = _text(path)
    refs = _LINK.findall(text) + _HTML.findall(text)
    spans = (" ".join(c.split()) for c in _CODE.findall(text))
    refs += [c for c in spans if _MD_PATH.match(c)]
    return refs


def _problem(source: Path, target: str) -> str | None:
    """What is wrong with ``target`` referenced from ``source`` (None: nothing)."""
    if _external(target):
        return None
    file, _, fragment = target.partition("#")
    if not file:
        dest = source
    else:
        dest = (source.parent / file).resolve()
        if not dest.is_relative_to(ROOT):
            return f"{target!r} points outside the repository (a clone does not have it)"
        if not dest.exists():
            # a code span may name a path from the repository root (`docs/netem.md`)
            from_root = (ROOT / file).resolve()
            if source.name == "README.md" or not from_root.exists():
                return f"{target!r}: no such file {_rel(dest)}"
            dest = from_root
    if fragment and dest.suffix == ".md" and fragment not in _anchors(dest):
        return f"{target!r}: {_rel(dest)} has no heading with the anchor #{fragment}"
    return None


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_every_relative_link_resolves(doc: Path) -> None:
    problems = [p for t in _references(doc) if (p := _problem(doc, t))]
    assert not problems, f"{_rel(doc)}:\n  " + "\n  ".join(problems)


def test_the_readme_links_the_maths_pages() -> None:
    refs = _references(ROOT / "README.md")
    for page in ("covariance_control", "many_targets", "mobile_selection", "passive_association"):
        assert f"docs/maths/{page}.md" in refs, page
    index = _references(ROOT / "docs" / "maths" / "README.md")
    for page in MATHS:
        if page.name != "README.md":
            assert page.name in index, f"docs/maths/README.md does not link {page.name}"


def _resolve(name: str) -> object:
    """The module or attribute ``name`` names; AssertionError saying why not."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError as exc:
            if exc.name is not None and not ".".join(parts[:i]).startswith(exc.name):
                raise  # the module exists but one of its own imports is missing
            continue
        for j, attr in enumerate(parts[i:], start=i):
            if not hasattr(obj, attr):
                raise AssertionError(f"{'.'.join(parts[:j])} has no attribute {attr!r}")
            obj = getattr(obj, attr)
        return obj
    raise AssertionError(f"no module {parts[0]!r}")


def _names(page: Path) -> list[str]:
    return sorted({c.strip() for c in _CODE.findall(_text(page)) if _NAME.match(c.strip())})


@pytest.mark.parametrize("page", MATHS, ids=_rel)
def test_every_code_name_on_the_maths_pages_exists(page: Path) -> None:
    problems = []
    for name in _names(page):
        try:
            _resolve(name)
        except AssertionError as exc:
            problems.append(f"`{name}`: {exc}")
    assert not problems, f"{_rel(page)}:\n  " + "\n  ".join(problems)


def test_the_maths_pages_exist_and_name_code() -> None:
    assert {p.stem for p in MATHS} >= {
        "README",
        "covariance_control",
        "fusion",
        "slow_links",
        "many_targets",
        "mobile_selection",
        "passive_association",
        "runtime",
    }
    for page in MATHS:
        if page.name != "README.md":
            assert len(_names(page)) >= 5, f"{_rel(page)} names hardly any code"


def test_the_checks_catch_what_they_should() -> None:
    """The helpers themselves: a missing file, a path out of the repository, a bad anchor and
    a missing attribute are reported."""
    page = ROOT / "docs" / "maths" / "fusion.md"
    assert _problem(page, "nowhere.md") is not None
    assert "outside" in (_problem(ROOT / "README.md", "../shared/spec/covariance_control.md") or "")
    assert _problem(page, "runtime.md#no-such-heading") is not None
    assert _problem(page, "runtime.md") is None
    assert _problem(page, "https://example.org/x.md") is None
    assert _slug("5. `peer`: no fusion centre") == "5-peer-no-fusion-centre"
    with pytest.raises(AssertionError, match="no attribute"):
        _resolve("covnet.core.kalman.no_such_function")
    kalman = importlib.import_module("covnet.core.kalman")
    assert _resolve("covnet.core.kalman.update") is kalman.update
