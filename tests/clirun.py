"""Run the real ``pbrsr`` entry point in-process, as tests of the CLI's exit codes do."""

from __future__ import annotations

import sys

from pbrsr_core import cli


def run_cli(args: list[str], capfd) -> tuple[int, str]:
    """``pbrsr_core.cli.main`` with ``args``: (exit code, stderr)."""
    code, _, err = run_cli_output(args, capfd)
    return code, err


def run_cli_output(args: list[str], capfd) -> tuple[int, str, str]:
    """``pbrsr_core.cli.main`` with ``args``: (exit code, stdout, stderr)."""
    old = sys.argv
    sys.argv = ["pbrsr", *args]
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = old
    out, err = capfd.readouterr()
    return code, out, err
