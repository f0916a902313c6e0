"""The command line run in the test's own process: exit code and output, for one-line
error checks (argparse's own refusals, SystemExit, included)."""

from __future__ import annotations

import contextlib
import io
import warnings

from bridge.app.cli import main


def run_cli(argv: list[str], warnings_as_errors: bool = False) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``attitude-bridge ARGV``. ``warnings_as_errors``:
    a warning leaking out (numpy's RuntimeWarning) raises instead, failing the test."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
            warnings.catch_warnings():
        if warnings_as_errors:
            warnings.simplefilter("error")
        try:
            code = main(argv)
        except SystemExit as exc:
            code = int(exc.code)
    return code, out.getvalue(), err.getvalue()


def one_line_error(code: int, err: str, *expected: str) -> None:
    """Exit 2, one line, no traceback, naming each of ``expected``."""
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "internal error" not in err, err
    for text in expected:
        assert text in err, err
