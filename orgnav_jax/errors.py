"""The error convention of every command line: user errors in one line, exit code 2.

    if __name__ == "__main__":
        sys.exit(run_cli(main))

A CLI's `main(argv)` raises; `run_cli` prints a user error as `error: <message>` on
stderr and returns 2. User errors are `UserError`, `ValueError` (bad values, bad files)
and `OSError` (missing, unreadable or protected paths). Anything else is a bug and keeps
its traceback. `--debug` (anywhere in argv) or ORGNAV_DEBUG=1 shows the traceback of user
errors too.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence

EXIT_USER_ERROR = 2


class UserError(Exception):
    """Bad input from the user (an option, a file, a directory); the message says what,
    where, and what was expected."""


USER_ERRORS = (UserError, ValueError, OSError)


def one_line(err: BaseException) -> str:
    """The error's message on one line."""
    text = " ".join(str(err).split())
    if isinstance(err, OSError) and err.filename and str(err.filename) not in text:
        text = f"{err.filename}: {text}"
    return text or type(err).__name__


def run_cli(main: Callable[[list[str]], object], argv: Sequence[str] | None = None) -> int:
    """Run main(argv) -> exit code: 0 (or main's int), 2 with `error: ...` on stderr for a
    user error, 130 on Ctrl-C."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("ORGNAV_DEBUG", "") not in ("", "0")
    argv = [a for a in argv if a != "--debug"]
    try:
        out = main(argv)
    except USER_ERRORS as err:
        if debug:
            raise
        print(f"error: {one_line(err)}", file=sys.stderr, flush=True)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return out if isinstance(out, int) and not isinstance(out, bool) else 0


def choose(options: dict, value, what: str):
    """options[value], or a ValueError naming `what` and the valid choices: the one way
    this package dispatches on a string mode."""
    try:
        return options[value]
    except (KeyError, TypeError):
        raise ValueError(f"unknown {what} {value!r}: expected one of "
                         f"{sorted(map(str, options))}") from None
