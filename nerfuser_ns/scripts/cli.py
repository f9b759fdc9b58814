"""``tyro.cli`` for our commands, with each field's docstring read as one paragraph in ``--help``.

tyro joins a docstring's single line breaks only before lines that start with a letter, and it does so before removing
the indentation of the lines under a class field (tyro 1.0), so a field documented over several lines printed each
line on its own in ``--help``. Here the docstring is cleaned (:func:`inspect.cleandoc`) and its lines joined, but
at blank lines (paragraphs), list items (lines starting ``- `` or ``* ``) and indented lines (examples)."""

from __future__ import annotations

import contextlib
import inspect
from collections.abc import Sequence
from typing import TypeVar
from unittest import mock

import tyro

try:  # a private module: where a later tyro moves it, help is printed as tyro prints it
    from tyro import _strings
except ImportError:
    _strings = None

T = TypeVar("T")

KEEP_LINE = ("- ", "* ", " ", "\t")
"""Lines starting so keep their own line (list items, indented examples)."""


def join_lines(text: str) -> str:
    """A docstring as paragraphs: its lines cleaned and joined, but at blank lines, list items and indented lines."""
    out: list[str] = []
    for line in inspect.cleandoc(text).split("\n"):
        line = line.rstrip()
        if out and out[-1] and line and not line.startswith(KEEP_LINE) and not out[-1].startswith((" ", "\t")):
            out[-1] += " " + line
        else:
            out.append(line)
    return "\n".join(out)


def parse(command: type[T], args: Sequence[str] | None = None) -> T:
    """``tyro.cli(command, args=args)``, field docstrings joined by :func:`join_lines`."""
    joined = (mock.patch.object(_strings, "remove_single_line_breaks", join_lines)
              if hasattr(_strings, "remove_single_line_breaks") else contextlib.nullcontext())  # fmt: skip
    with joined:
        return tyro.cli(command, args=args)
