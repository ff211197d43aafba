"""Every ``--help`` ends with examples of its own command: the argparse tree of ``tagtrail``
walked, every command and every ``stream`` subcommand included."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator

from tagtrail.cli import OPTIONAL, build_parser


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse keeps its sub-commands here, nowhere public
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def walk(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """Every parser under ``parser`` with its command path; an optional command's parser is
    built as the CLI builds it when that command runs (its arguments added then)."""
    yield path, parser
    for name, sub in _subparsers(parser).items():
        if not path:
            sub = _subparsers(build_parser(name))[name]
        yield from walk(sub, (*path, name))


def test_the_walk_reaches_every_command() -> None:
    paths = {p for p, _ in walk(build_parser())}
    assert {(name,) for name, _, _ in OPTIONAL} <= paths
    assert {("run",), ("status",), ("dag",), ("show",)} <= paths
    assert {("stream", s) for s in ("relocalize", "replay", "localize", "echo", "record")} <= paths


def test_every_help_ends_with_examples_of_its_command() -> None:
    missing = []
    for path, parser in walk(build_parser()):
        text = parser.format_help()
        head, sep, examples = text.rpartition("\nexamples:\n")
        command = " ".join(("tagtrail", *path))
        ok = bool(sep) and re.search(rf"^ +{re.escape(command)}( |$)", examples, re.M)
        if not ok:
            missing.append(command)
    assert missing == [], f"--help without examples of the command: {missing}"
