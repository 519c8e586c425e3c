"""Every code block of README.md and docs/*.md runs as written, so that none of them can rot.

A document's blocks run in order in one temporary folder (a later block may use the files an
earlier one wrote; every block makes its own data or uses what an earlier block made):

- ```python blocks: each in a fresh namespace, in this process;
- ```bash blocks: each as one ``bash -euo pipefail`` script, with this interpreter's ``python``
  and ``cmax`` first on the PATH and this checkout first on PYTHONPATH.

A block preceded by ``<!-- no-test: REASON -->`` is not run: only for installs, downloads and long
jobs (training, whole data sets), and such markers must stay rare (checked below). Blocks of any
other language (``text``, ``json``) are not code and are not run; a fence without a language is refused.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUN = ("python", "bash")
NOT_CODE = ("text", "json", "toml", "yaml")
NO_TEST = re.compile(r"^<!--\s*no-test:\s*(?P<reason>.+?)\s*-->$")
#: Why a block may be left out: the words one of them must contain.
NO_TEST_REASONS = ("install", "download", "long", "cluster", "GPU")
#: At most this share of the runnable blocks (and this many in all) may be left out.
NO_TEST_SHARE, NO_TEST_MAX = 0.25, 10


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # 1-based line of the opening fence
    language: str
    code: str
    skip: str | None  # the no-test reason, if any

    def __str__(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line} ({self.language})"


def code_blocks(path: Path) -> list[Block]:
    """The fenced blocks of a Markdown file, with the no-test marker of the line before each."""
    blocks, lines = [], path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        fence = re.match(r"^(`{3,})(\S*)\s*$", lines[i])
        if not fence:
            i += 1
            continue
        previous = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        marker = NO_TEST.match(previous)
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith(fence.group(1)))
        blocks.append(Block(path, i + 1, fence.group(2), "\n".join(lines[i + 1:end]) + "\n",
                            marker.group("reason") if marker else None))
        i = end + 1
    return blocks


ALL_BLOCKS = [block for path in DOCUMENTS for block in code_blocks(path)]


def _environment() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def _installed_environment() -> dict[str, str]:
    """The environment of a user who installed the package: this checkout is not on ``PYTHONPATH`` (a block that
    imports ``benchmarks`` or ``tests``, which are not installed, fails as it would for them)."""
    env = _environment()
    env["PYTHONPATH"] = os.pathsep.join(p for p in env["PYTHONPATH"].split(os.pathsep)
                                        if p and Path(p).resolve() != ROOT.resolve())
    return env


def run_block(block: Block, folder: Path) -> None:
    """Run one block in ``folder``; raise AssertionError naming the block when it fails. A python block runs as a
    user runs a copied example: a script of its own (``__name__ == "__main__"``, worker processes that import it),
    started from ``folder`` with the installed package, not this checkout, on the path."""
    if block.language == "python":
        script = folder / "block.py"
        script.write_text(block.code)
        done = subprocess.run([sys.executable, str(script)], cwd=folder, env=_installed_environment(),
                              capture_output=True, text=True, timeout=300)
        if done.returncode != 0:
            raise AssertionError(f"{block} failed (exit {done.returncode}): {done.stderr[-3000:]}")
        return
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", block.code], cwd=folder, env=_environment(),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{block} exited {done.returncode}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"


@pytest.mark.parametrize("path", DOCUMENTS, ids=[str(p.relative_to(ROOT)) for p in DOCUMENTS])
def test_code_blocks_run_as_written(path: Path, tmp_path: Path) -> None:
    for block in code_blocks(path):
        if block.language in RUN and block.skip is None:
            run_block(block, tmp_path)


def test_every_block_says_its_language() -> None:
    for block in ALL_BLOCKS:
        assert block.language in RUN + NOT_CODE, (
            f"{block}: a fence needs a language ({', '.join(RUN + NOT_CODE)}); "
            f"python and bash blocks run in CI, the others are shown only")


def test_blocks_left_out_are_few_and_say_why() -> None:
    runnable = [b for b in ALL_BLOCKS if b.language in RUN]
    skipped = [b for b in runnable if b.skip is not None]
    assert len(runnable) >= 10
    assert len(skipped) <= min(NO_TEST_MAX, NO_TEST_SHARE * len(runnable)), [str(b) for b in skipped]
    for block in skipped:
        assert any(word.lower() in block.skip.lower() for word in NO_TEST_REASONS), (
            f"{block}: no-test only for {', '.join(NO_TEST_REASONS)}; got {block.skip!r}")


def test_the_readme_test_command_is_what_ci_runs() -> None:
    readme, ci = (ROOT / "README.md").read_text(), (ROOT / ".ci" / "run").read_text()
    for command in ('pip install torch==2.13.0 -e ".[test]"', "python -m pytest -q"):
        assert command in readme and command in ci


def test_readme_is_short_and_its_links_resolve() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    for path in DOCUMENTS:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
            if not re.match(r"^[a-z]+://", target):
                assert (path.parent / target).exists(), f"{path.relative_to(ROOT)}: broken link {target}"


def test_the_harness_finds_blocks_and_markers(tmp_path: Path) -> None:
    """The parser and the runner can fail: a marked block is seen as skipped, a failing block fails."""
    sample = tmp_path / "sample.md"
    sample.write_text("text\n\n<!-- no-test: install -->\n```bash\nexit 1\n```\n\n```python\nx = 1\n```\n"
                      "```bash\nexit 3\n```\n")
    blocks = code_blocks(sample)
    assert [(b.language, b.skip, b.line) for b in blocks] == [("bash", "install", 4), ("python", None, 8),
                                                              ("bash", None, 11)]
    with pytest.raises(AssertionError, match="exited 3"):
        run_block(Block(ROOT / "README.md", 1, "bash", "exit 3\n", None), tmp_path)
    with pytest.raises(AssertionError, match="NameError"):
        run_block(Block(ROOT / "README.md", 1, "python", "np.zeros(3)\n", None), tmp_path)
