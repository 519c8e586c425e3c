"""The README and docs/ as a reference: every ``#anchor`` of a link names a heading of its page, and every
dotted name of the API they mention (``cmax.io.read``, ``learned.predict.run_prediction``) exists, so that a
renamed function or heading cannot leave a page pointing at nothing. (That linked files exist is checked by
``test_docs_code_blocks.py``.)"""
from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)


def prose(path: Path) -> str:
    """The page without its code blocks (blank lines in their place, so line numbers stay)."""
    return FENCE.sub(lambda block: "\n" * block.group(0).count("\n"), path.read_text(encoding="utf-8"))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but ``-`` and ``_`` dropped, spaces to ``-``."""
    text = re.sub(r"[`*]", "", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found, seen = set(), {}
    for heading in re.findall(r"^#+\s+(.*)$", prose(path), re.MULTILINE):
        name = slug(heading)
        seen[name] = seen.get(name, -1) + 1
        found.add(name if seen[name] == 0 else f"{name}-{seen[name]}")
    return found


def resolves(name: str) -> bool:
    """Whether ``a.b.c`` is a module or an attribute reached from the longest importable module prefix."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attribute in parts[i:]:
            if not hasattr(obj, attribute):
                return False
            obj = getattr(obj, attribute)
        return True
    return False


def test_slug_follows_github():
    assert slug("Motion members (`motion_members=`)") == "motion-members-motion_members"
    assert slug("## The choice: `SHARED_OBJECTIVE = AverageTimestamp(smoothness=0.003)`".lstrip("# ")) == \
        "the-choice-shared_objective--averagetimestampsmoothness0003"


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_anchor_names_a_heading(path):
    broken = []
    for number, line in enumerate(prose(path).splitlines(), 1):
        for target in re.findall(r"\]\(([^)\s]*#[^)\s]+)\)", line):
            if re.match(r"^[a-z]+://", target):
                continue
            page, _, anchor = target.partition("#")
            destination = (path.parent / page) if page else path
            if destination.suffix == ".md" and anchor not in anchors(destination):
                broken.append(f"{path.relative_to(ROOT)}:{number}: {target}")
    assert not broken, broken


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_api_name_exists(path):
    missing = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        for name in re.findall(r"(?<![\w/.])((?:cmax|learned)(?:\.[A-Za-z_]\w*)+)", line):
            if not name.endswith((".py", ".md", ".h5", ".toml", ".json")) and not resolves(name):
                missing.append(f"{path.relative_to(ROOT)}:{number}: {name}")
    assert not missing, missing
