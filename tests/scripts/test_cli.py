"""Our commands' ``--help`` (nerfuser_ns.scripts.cli): each field's docstring printed as one paragraph."""

from __future__ import annotations

import docstring_parser
import pytest

from nerfuser_ns.scripts.check_capture import CheckCaptureCommand
from nerfuser_ns.scripts.cli import join_lines, parse
from nerfuser_ns.scripts.register import RegisterCommand
from nerfuser_ns.scripts.view import ViewCommand


def test_join_lines_keeps_paragraphs_lists_and_indented_examples():
    text = """Register runs
    over two lines.

    Example::

        ns-a b
        ns-c d

    - one item
    - (another) item
    """
    joined = "Register runs over two lines.\n\nExample::\n\n    ns-a b\n    ns-c d\n\n- one item\n- (another) item"
    assert join_lines(text) == joined
    assert join_lines("one line") == "one line"


@pytest.mark.parametrize("command", [CheckCaptureCommand, RegisterCommand, ViewCommand])
def test_help_prints_each_fields_docstring_unbroken(command, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")  # rich wraps at the terminal's width: none here
    with pytest.raises(SystemExit) as exit_:
        parse(command, ["--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    # the first two lines of each field's docstring meet on one help line
    for name, doc in _field_docs(command).items():
        first, second = (line.strip() for line in doc.strip().splitlines()[:2])
        assert f"{first.split()[-1]} {second.split()[0]}" in out, (name, first, second)


def _field_docs(command: type) -> dict[str, str]:
    """The fields of ``command`` documented over two lines or more, with their docstrings (as tyro reads them)."""
    docs = {p.arg_name: p.description for p in docstring_parser.parse_from_object(command).params if p.description}
    return {k: v for k, v in docs.items() if len(v.strip().splitlines()) > 1 and not v.splitlines()[1].strip() == ""}
