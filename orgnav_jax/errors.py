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

import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

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


# ------------------------------------------------------------------ typed readers
# Every file the program reads back goes through one reader (docs/reliability.md, "Typed
# readers"); these helpers give their errors one form:
#     <file>: field <name>: expected <what>, got <value>

INT32_MAX = 2 ** 31 - 1
FLOAT_MAX = 1.7976931348623157e308


def shown(value, limit: int = 60) -> str:
    """repr(value), shortened to `limit` characters (a message stays one short line)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def field_error(source, field, expected: str, value) -> ValueError:
    """ValueError('<source>: field <field>: expected <expected>, got <value>')."""
    return ValueError(f"{source}: field {field!r}: expected {expected}, got {shown(value)}")


def is_int(value) -> bool:
    """A JSON integer: int, not bool."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value) -> bool:
    """A JSON number that is a finite float: int or float, not bool, not inf/nan and not
    an integer too large for a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    try:
        return abs(float(value)) <= FLOAT_MAX
    except OverflowError:
        return False


def read_object(value, source, what: str = "a JSON object") -> dict:
    """`value` if it is a dict (a JSON object), else ValueError naming `source`."""
    if not isinstance(value, dict):
        raise ValueError(f"{source}: expected {what}, got {_kind(value)}")
    return value


def _kind(value) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean",
            type(None): "null", int: "an integer", float: "a number"}.get(
        type(value), type(value).__name__)


_MISSING = object()


def read_field(doc: dict, field: str, source, *, default=_MISSING):
    """doc[field], or `default` when given and the field is absent; ValueError naming
    the file and the field when a required field is missing."""
    if field in doc:
        return doc[field]
    if default is not _MISSING:
        return default
    raise ValueError(f"{source}: field {field!r} is missing")


def read_int(doc: dict, field: str, source, *, lo: int | None = 0, hi: int | None = INT32_MAX,
             default=_MISSING) -> int:
    """An integer field within [lo, hi] (default: a non-negative int32)."""
    if field not in doc and default is not _MISSING:
        return default
    value = read_field(doc, field, source)
    if not is_int(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
        span = (f"{lo:,} <= {field} <= {hi:,}" if lo is not None and hi is not None else
                f"{field} >= {lo:,}" if lo is not None else f"{field} <= {hi:,}")
        raise field_error(source, field, f"an integer {span}" if lo is not None or
                          hi is not None else "an integer", value)
    return value


def read_number(doc: dict, field: str, source, *, default=_MISSING) -> float:
    """A finite number field -> float."""
    if field not in doc and default is not _MISSING:
        return default
    value = read_field(doc, field, source)
    if not is_number(value) or value != value:
        raise field_error(source, field, "a finite number", value)
    return float(value)


def read_str(doc: dict, field: str, source, *, choices=None, default=_MISSING) -> str:
    """A string field (one of `choices` when given)."""
    if field not in doc and default is not _MISSING:
        return default
    value = read_field(doc, field, source)
    if not isinstance(value, str) or (choices is not None and value not in choices):
        raise field_error(source, field, f"one of {list(choices)}" if choices is not None
                          else "a string", value)
    return value


def read_json(path, what: str = "JSON"):
    """The parsed JSON of a file; a ValueError naming the file when it is not JSON (cut
    short by a kill, say) and an OSError naming it when it cannot be read."""
    try:
        text = Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not {what} (not UTF-8 text)") from None
    try:
        return json.loads(text)
    except ValueError as err:
        raise ValueError(f"{path}: not {what} ({getattr(err, 'msg', err)} at line "
                         f"{getattr(err, 'lineno', '?')}; a file cut short?)") from None
