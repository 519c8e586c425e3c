"""The ``--help`` of every command is a reference: each option that takes a value states its default, and each
option is named in the README or in ``docs/`` where a user would look for it (and no page names an option of
``cmax`` that no command has)."""
from __future__ import annotations

import argparse
import importlib
import re
from pathlib import Path

import pytest

from cmax.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
LEARNED_COMMANDS = ("learned.train", "learned.evaluate", "learned.predict", "learned.checkpoint")


class _Built(Exception):
    """Raised in place of parsing: the command's parser is built, nothing runs."""


def _subparsers(parser: argparse.ArgumentParser, name: str):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, child in action.choices.items():
                yield from _subparsers(child, f"{name} {sub}")


def _learned_parsers(module_name: str) -> list[tuple[str, argparse.ArgumentParser]]:
    """The parsers ``python -m MODULE`` builds, caught at its first ``parse_args`` (so nothing runs)."""
    built: list[argparse.ArgumentParser] = []

    def catch(self, *args, **kwargs):
        built.append(self)
        raise _Built

    module = importlib.import_module(module_name)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(argparse.ArgumentParser, "parse_args", catch)
        patch.setattr(argparse.ArgumentParser, "parse_known_args", catch)
        with pytest.raises(_Built):
            module.main(["--help"])
    return [found for parser in built for found in _subparsers(parser, f"python -m {module_name}")]


def all_parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    parsers = list(_subparsers(build_parser(), "cmax"))
    for module_name in LEARNED_COMMANDS:
        parsers += _learned_parsers(module_name)
    return parsers


PARSERS = all_parsers()
OPTIONS = [(name, parser, action) for name, parser in PARSERS for action in parser._actions
           if action.option_strings and not isinstance(action, (argparse._HelpAction, argparse._VersionAction))]


def test_every_command_is_found():
    names = {name for name, _ in PARSERS}
    assert {"cmax fit", "cmax simulate", "cmax manifest merge", "python -m learned.train",
            "python -m learned.predict"} <= names
    assert len(OPTIONS) > 100


@pytest.mark.parametrize("name, parser, action", [o for o in OPTIONS if o[2].nargs != 0 and not o[2].required],
                         ids=lambda value: value if isinstance(value, str) else "")
def test_an_option_with_a_value_states_its_default(name, parser, action):
    text = parser._get_formatter()._expand_help(action) if action.help else ""
    assert "default" in text.lower(), f"{name} {'/'.join(action.option_strings)}: no default in {text!r}"


def test_every_option_is_named_in_the_readme_or_docs():
    text = "\n".join(p.read_text(encoding="utf-8") for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))])
    unnamed = sorted({option for _, _, action in OPTIONS for option in action.option_strings
                      if option.startswith("--") and option not in ("--output", "--version", "--debug")
                      and not re.search(re.escape(option) + r"(?![\w-])", text)})
    assert not unnamed, f"options no page of docs/ or the README names: {unnamed}"


def test_the_docs_name_no_cmax_option_that_no_command_has():
    known = {option for _, _, action in OPTIONS for option in action.option_strings} | {"--help"}
    known |= {"--no-" + o[2:] for _, _, a in OPTIONS if isinstance(a, argparse.BooleanOptionalAction)
              for o in a.option_strings}
    unknown = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            # options on a line that runs a command of cmax or learned (benchmarks have options of their own)
            for command in re.finditer(r"(?:^|[`|]\s*|\s)(cmax [a-z]+|python -m learned\.[a-z]+)([^`|]*)", line):
                for option in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", command.group(2)):
                    if option not in known and option != "--bogus":   # bad_input.md's example of a bad option
                        unknown.append(f"{path.relative_to(ROOT)}:{number}: {option}")
    assert not unknown, unknown
