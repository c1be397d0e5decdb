"""Helpers for tests of the command line: its exit status and its one-line errors."""

from __future__ import annotations

import re

from rainbench import cli


def cli_status(argv) -> int:
    """``rainbench.cli.main(argv)``'s exit status (arguments as strings), argparse's SystemExit
    included."""
    try:
        return cli.main([str(arg) for arg in argv])
    except SystemExit as exit:
        return exit.code


def one_line_error(capsys, code, pattern) -> str:
    """Assert exit status 2 and exactly one line on stderr, ``rainbench: error: `` followed by
    the regular expression ``pattern``; returns the line."""
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert re.fullmatch(r"rainbench: error: " + pattern, err[0]), err[0]
    return err[0]
