"""Writing outputs without losing anything the program did not write.

    check_output_dir(path, is_scene_set, "a SceneSet")   # before writing into `path`
    check_output_file(path, is_results_json, "an evaluation results JSON")
    write_text_atomic(path, text)                          # readers never see half a file

Every `--out` / `--run-dir` writer calls one of the checks first: an existing directory
(file) that is not empty and not of the writer's own kind is refused with an error that
names it; nothing is deleted or overwritten. A symbolic link at an output path is refused
(dangling or not: the link is the user's), and so is an output that is one of the same
command's inputs. Pictures carry a PNG text chunk naming this package (write_png), by
which a later run knows it may replace them.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path


def check_output_dir(path: str | os.PathLike, is_own: Callable[[Path], bool], kind: str,
                     option: str = "--out") -> None:
    """Raise FileExistsError unless `path` is absent, an empty directory, or `kind`
    (is_own(path) is True)."""
    path = Path(path)
    if not path.exists():
        return
    if not path.is_dir():
        raise FileExistsError(f"{option} {path} is a file, expected a directory for {kind}; "
                              "nothing was written")
    if any(path.iterdir()) and not is_own(path):
        raise FileExistsError(f"{option} {path} is a non-empty directory that is not {kind}; "
                              "it is left untouched: choose another path")


def check_output_file(path: str | os.PathLike, is_own: Callable[[Path], bool], kind: str,
                      option: str = "--out", inputs=()) -> None:
    """Raise FileExistsError if `path` exists and is not `kind` (is_own(path) is False), is
    a symbolic link, or is one of the command's `inputs` (paths)."""
    path = Path(path)
    if path.is_symlink():
        raise FileExistsError(f"{option} {path} is a symbolic link; it is left untouched: "
                              "give the path of a file to write")
    for given in inputs:
        if given is not None and _same_path(path, Path(given)):
            raise FileExistsError(f"{option} {path} is also an input of this command; "
                                  "choose another path")
    if path.is_dir():
        raise FileExistsError(f"{option} {path} is a directory, expected a file path for "
                              f"{kind}")
    if path.exists() and not is_own(path):
        raise FileExistsError(f"{option} {path} exists and is not {kind}; it is left "
                              "untouched: choose another path")


def _same_path(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve()
    except OSError:
        return False


PNG_SOFTWARE = "orgnav_jax"          # the PNG text chunk that marks our pictures


def is_own_png(path: str | os.PathLike) -> bool:
    """Whether `path` is a PNG this package wrote (its Software text chunk)."""
    try:
        with open(path, "rb") as f:
            head = f.read(8192)
    except OSError:
        return False
    return head.startswith(b"\x89PNG\r\n\x1a\n") and \
        b"Software\x00" + PNG_SOFTWARE.encode() in head


def write_png(fig, path: str | os.PathLike, dpi: int = 120, option: str = "--out") -> Path:
    """Save a matplotlib figure as a PNG marked as ours, atomically, never over a file
    we did not write (check_output_file) -> path. The name must end in .png."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{option} {path}: expected a .png path (pictures are PNG files)")
    check_output_file(path, is_own_png, "a PNG written by orgnav_jax", option)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.png")
    try:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", metadata={"Software": PNG_SOFTWARE})
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to a temporary file beside `path`, then rename it over `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def json_text(doc, indent: int = 1) -> str:
    """json.dumps(doc, indent=indent), with lists of numbers on one line each (per-episode
    arrays stay one line per field instead of one line per value)."""
    def encode(x, level):
        pad, inner = " " * (indent * level), " " * (indent * (level + 1))
        if isinstance(x, dict) and x:
            items = [f"{inner}{json.dumps(str(k))}: {encode(v, level + 1)}"
                     for k, v in x.items()]
            return "{\n" + ",\n".join(items) + "\n" + pad + "}"
        if isinstance(x, list) and x and any(isinstance(v, (dict, list)) for v in x):
            return "[\n" + ",\n".join(inner + encode(v, level + 1) for v in x) + \
                "\n" + pad + "]"
        return json.dumps(x, separators=(",", ":") if isinstance(x, list) else None)
    return encode(doc, 0)
