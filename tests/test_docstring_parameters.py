"""Every public callable's docstring names each of its parameters, and a ``Parameters`` section lists no
parameter the signature does not have (so that ``help(...)`` stays a reference as signatures change).

Public: the names of each module's ``__all__`` in :data:`MODULES`, and the public methods those classes
define. Enumerations (their constructor is the enum machinery's) and objects that are only instances are
left out.
"""
from __future__ import annotations

import doctest
import enum
import importlib
import inspect
import re

import pytest

MODULES = (
    "cmax", "cmax.io", "cmax.io.provenance", "cmax.io.calibration", "cmax.representations", "cmax.sim", "cmax.contrast", "cmax.fitting", "cmax.emvs",
    "cmax.metrics", "cmax.geometry", "cmax.warp", "cmax.iwe", "cmax.objectives", "cmax.viz", "cmax.show",
    "learned.model", "learned.losses", "learned.data", "learned.config", "learned.checkpoint", "learned.train",
    "learned.evaluate", "learned.predict",
)
SECTION = re.compile(r"^(?P<name>[A-Z][A-Za-z ]+)\n-{3,}\n", re.MULTILINE)


def _documented_callables():
    seen: set[int] = set()
    for module_name in MODULES:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            obj = getattr(module, name)
            if not (inspect.isfunction(obj) or inspect.isclass(obj)) or id(obj) in seen:
                continue
            if inspect.isclass(obj) and issubclass(obj, enum.Enum):
                continue
            seen.add(id(obj))
            yield f"{module_name}.{name}", obj
            if inspect.isclass(obj):
                for attribute, value in vars(obj).items():
                    function = value.__func__ if isinstance(value, (classmethod, staticmethod)) else value
                    if not attribute.startswith("_") and inspect.isfunction(function):
                        yield f"{module_name}.{name}.{attribute}", function


CALLABLES = list(_documented_callables())


def docstring(obj) -> str:
    """The text ``help(obj)`` shows for its parameters: a class's docstring and its own ``__init__``'s."""
    text = inspect.getdoc(obj) or ""
    if inspect.isclass(obj) and "__init__" in vars(obj) and vars(obj)["__init__"].__doc__:
        text += "\n" + inspect.getdoc(vars(obj)["__init__"])
    return text


def parameters(obj) -> list[str]:
    """The names of ``obj``'s parameters; none for an exception class without an ``__init__`` of its own."""
    try:
        signature = inspect.signature(obj)
    except ValueError:                   # e.g. class FormatError(ValueError): the builtin's constructor
        return []
    return [p.name for p in signature.parameters.values() if p.name not in ("self", "cls")]


def listed_parameters(text: str) -> list[str]:
    """The names a numpydoc ``Parameters`` section lists (``name : type`` lines at the section's indent)."""
    sections = list(SECTION.finditer(text))
    for i, section in enumerate(sections):
        if section.group("name") != "Parameters":
            continue
        end = sections[i + 1].start() if i + 1 < len(sections) else len(text)
        names = []
        for line in text[section.end():end].splitlines():
            entry = re.fullmatch(r"(?P<names>\**\w+(?:, \**\w+)*)(?: : .*)?", line)
            if entry:                    # ``name : type`` or ``a, b : type`` (prose lines of the section are not)
                names += [n.strip().lstrip("*") for n in entry.group("names").split(",")]
        return names
    return []


def test_the_public_api_is_found():
    names = {name for name, _ in CALLABLES}
    assert {"cmax.fit", "cmax.fit_sequence", "cmax.io.read", "cmax.representations.voxel_grid",
            "cmax.sim.simulate_scene", "cmax.contrast.EventWindows.from_events", "learned.data.augment"} <= names
    assert len(CALLABLES) > 150


@pytest.mark.parametrize("name, obj", CALLABLES, ids=[name for name, _ in CALLABLES])
def test_the_docstring_names_every_parameter(name, obj):
    text = docstring(obj)
    assert text, f"{name} has no docstring"
    missing = [p for p in parameters(obj) if not re.search(rf"(?<![\w.]){re.escape(p)}(?!\w)", text)]
    assert not missing, f"{name}{inspect.signature(obj)}: its docstring does not name {missing}"


@pytest.mark.parametrize("name, obj", CALLABLES, ids=[name for name, _ in CALLABLES])
def test_the_parameters_section_lists_only_parameters_that_exist(name, obj):
    stale = [p for p in listed_parameters(docstring(obj)) if p not in parameters(obj)]
    assert not stale, f"{name}{inspect.signature(obj)}: its docstring documents {stale}, which it does not take"


def test_the_checks_catch_a_missing_and_a_stale_parameter():
    def documented(a, b):
        """Sum.

        Parameters
        ----------
        a : int
        c : int
        """

    assert listed_parameters(docstring(documented)) == ["a", "c"]
    assert "b" not in docstring(documented)


ARRAY = re.compile(r"ndarray|Tensor")
SHAPE = re.compile(r"\((?:\.\.\., ?)?[\w+* -]+(?:, ?[\w+* -]*)*\)|shape")


@pytest.mark.parametrize("name, obj", CALLABLES, ids=[name for name, _ in CALLABLES])
def test_a_callable_taking_or_giving_arrays_states_a_shape(name, obj):
    """An array argument or result comes with its shape, e.g. ``(N,)``, ``(B, H, W)`` or ``shape (3, 3)``."""
    try:
        signature = inspect.signature(obj)
    except ValueError:
        return
    arrays = [p.name for p in signature.parameters.values() if ARRAY.search(str(p.annotation))]
    if arrays or ARRAY.search(str(signature.return_annotation)):
        assert SHAPE.search(docstring(obj)), f"{name}: arrays ({arrays or 'its result'}) but no shape in its docstring"


LIBRARIES = {"np": (re.compile(r"\bnp\."), re.compile(r"import numpy as np")),
             "torch": (re.compile(r"\btorch\."), re.compile(r"import (?:.*, )?torch\b"))}


@pytest.mark.parametrize("name, obj", CALLABLES, ids=[name for name, _ in CALLABLES])
def test_an_example_imports_numpy_and_torch_itself(name, obj):
    """An example copied from ``help(...)`` runs in a fresh session: the module's own ``np`` or ``torch``, which
    doctest lends it, is not there."""
    source = "".join(example.source for example in doctest.DocTestParser().get_examples(inspect.getdoc(obj) or ""))
    for library, (used, imported) in LIBRARIES.items():
        assert not used.search(source) or imported.search(source), f"{name}: its example uses {library} unimported"
