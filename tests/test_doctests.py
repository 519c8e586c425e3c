"""Every docstring example of ``cmax`` and ``learned`` runs and prints what it shows (the doctests of CI).

The modules are found by their source (a line starting with ``>>>``), so a new example is run without
being listed here, and a module without examples is never imported (the slow and optional ones:
peers, tensorboard). Each module's examples run in a fresh temporary folder. An example may be skipped
(``# doctest: +SKIP``) only where it needs a file that cannot be made in a line or two; such modules
are listed in :data:`SKIPS` with the reason, and the list is checked both ways.
"""
from __future__ import annotations

import doctest
import importlib
import inspect
import re
import types
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cmax", "learned")
EXAMPLE = re.compile(r"^\s*>>> ", re.MULTILINE)
SKIP = re.compile(r"^\s*>>> .*#\s*doctest:.*\+SKIP", re.MULTILINE)
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE

#: Modules with skipped examples, and why (each skip needs a recording that no line of code can make).
SKIPS = {
    "cmax.emvs": "a recording and its groundtruth.txt trajectory (cmax.emvs.core runs one on synthetic events)",
    "cmax.io.aedat4": "an .aedat4 recording (cmax writes no AEDAT4)",
}


def module_name(path: Path) -> str:
    """``cmax/io/h5.py`` -> ``cmax.io.h5``; ``cmax/cli/__init__.py`` -> ``cmax.cli``."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def example_modules() -> dict[str, Path]:
    """``{module name: source path}`` of every module of :data:`PACKAGES` with a docstring example."""
    files = sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)
    return {module_name(p): p for p in files if EXAMPLE.search(p.read_text(encoding="utf-8"))}


MODULES = example_modules()


def written_examples(source: str) -> Counter[str]:
    """The first line of every example (``>>>``) in ``source``, stripped, with its count."""
    return Counter(line.strip()[4:].strip() for line in source.splitlines() if line.lstrip().startswith(">>> "))


def doctests(module: types.ModuleType) -> list[doctest.DocTest]:
    """The doctests of ``module``: :class:`doctest.DocTestFinder`'s, and those of the module's decorated
    functions and compiled kernels, which it leaves out (their wrapper is not "from" the module)."""
    finder = doctest.DocTestFinder(exclude_empty=True)
    tests = finder.find(module, module.__name__)
    found = {test.name for test in tests}
    for attribute, value in vars(module).items():
        name = f"{module.__name__}.{attribute}"
        wrapped = inspect.unwrap(value) if callable(value) and hasattr(value, "__wrapped__") else None
        if name not in found and getattr(wrapped, "__module__", None) == module.__name__:
            tests += finder.find(value, name, module=module, globs=vars(module))
    return tests


def run_examples(module: types.ModuleType) -> tuple[doctest.TestResults, str, Counter[str]]:
    """Run the examples of ``module``: (failed / attempted, the failure report, the first lines of the
    examples collected, as :func:`written_examples` counts them)."""
    report: list[str] = []
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    collected: Counter[str] = Counter()
    for test in doctests(module):
        runner.run(test, out=report.append)
        collected.update(example.source.splitlines()[0].strip() for example in test.examples)
    return doctest.TestResults(runner.failures, runner.tries), "".join(report), collected


@pytest.mark.parametrize("name", sorted(MODULES))
def test_docstring_examples_run_as_shown(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # an example that writes a file writes it here
    monkeypatch.delenv("CMAX_TORCH_THREADS", raising=False)  # the examples show the policy, not an override
    results, report, collected = run_examples(importlib.import_module(name))
    assert results.failed == 0, f"{name}: {results.failed} of {results.attempted} examples failed\n{report}"
    missed = written_examples(MODULES[name].read_text(encoding="utf-8")) - collected
    assert not missed, f"{name}: examples never run (in a docstring doctest cannot reach?): {sorted(missed)}"


def test_skipped_examples_are_few_and_say_why() -> None:
    skipping = {name for name, path in MODULES.items() if SKIP.search(path.read_text(encoding="utf-8"))}
    assert skipping == set(SKIPS), ("modules skipping examples must be listed in SKIPS with their reason: "
                                    f"unlisted {sorted(skipping - set(SKIPS))}, listed in vain "
                                    f"{sorted(set(SKIPS) - skipping)}")


def test_examples_are_found_across_the_packages() -> None:
    assert {"cmax.events", "cmax.cli.recording", "cmax.fitting.api", "learned.model"} <= set(MODULES)
    assert len(MODULES) >= 30


def test_the_runner_reports_a_wrong_output_and_a_missed_example(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The harness can fail: a wrong printed value fails, and an example doctest cannot reach is seen."""
    module = types.ModuleType("sample", ">>> 1 + 1\n3\n")
    results, report, _ = run_examples(module)
    assert (results.failed, results.attempted) == (1, 1) and "Expected:\n    3\nGot:\n    2" in report

    source = ('"""\n>>> 2\n2\n"""\nimport contextlib\n\n\n@contextlib.contextmanager\ndef scope():\n'
              '    """\n    >>> with scope() as n:\n    ...     n\n    3\n    """\n    yield 3\n\n\n'
              'def outer():\n    def inner():\n        """\n\n        >>> 1\n        1\n        """\n')
    path = tmp_path / "nested_sample.py"
    path.write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    results, _, collected = run_examples(importlib.import_module("nested_sample"))
    # the decorated function's example runs; the nested one is reported as never run
    assert (results.failed, results.attempted) == (0, 2)
    assert written_examples(source) - collected == Counter({"1": 1})
