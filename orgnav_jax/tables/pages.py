"""Generated pages: every file a table, sweep or check makes is written here (atomically,
safe_write.write_text_atomic) or compared here (`--check`).

    pages = {out / "table.md": text, out / "results.json": json_text}
    regenerate(pages, check=args.check)        # write them, or exit status 1 on a difference

A page ending in .json is compared by its parsed value (a JSON written by another json
version or indentation still agrees); any other page byte for byte.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

from orgnav_jax.errors import read_json
from orgnav_jax.safe_write import write_text_atomic


def write_pages(pages: Mapping[Path, str]) -> None:
    """Write every page, each atomically (a kill leaves the old file or the new one)."""
    for path, text in pages.items():
        write_text_atomic(path, text)


def differences(pages: Mapping[Path, str], optional: Iterable[Path] = ()) -> list[str]:
    """One line per page whose file differs from its text or is missing (pages in
    `optional` are compared only where they exist); empty when all agree."""
    optional = set(optional)
    bad = []
    for path, text in pages.items():
        if not path.exists():
            if path not in optional:
                bad.append(f"{path}: missing")
        elif path.suffix == ".json":
            if read_json(path) != json.loads(text):
                bad.append(f"{path}: differs from what the runs' files give")
        elif path.read_text() != text:
            bad.append(f"{path}: differs from what the runs' files give")
    return bad


def regenerate(pages: Mapping[Path, str], check: bool, optional: Iterable[Path] = ()) -> int:
    """--check: compare the pages (differences), print `check failed: ...` per difference
    to stderr and return 1, or a line saying they agree and 0. Otherwise write them
    (write_pages) and return 0."""
    if not check:
        write_pages(pages)
        return 0
    optional = set(optional)
    bad = differences(pages, optional)
    for line in bad:
        print(f"check failed: {line}", file=sys.stderr)
    if not bad:
        shown = [p for p in pages if p.exists() or p not in optional]
        folders = {p.parent for p in shown}
        names = (f"{shown[0].parent}: " + ", ".join(p.name for p in shown)
                 if len(folders) == 1 else ", ".join(map(str, shown)))
        print(f"{names} {'agrees' if len(shown) == 1 else 'agree'} with the runs' files")
    return 1 if bad else 0
