"""Word vectors of the 22 target categories: WE / SAVN's target input (issue 41).

SAVN's release (allenai/savn `models/basemodel.py:21-26, 60-61`) feeds the target's GloVe
vector (300-d) through Linear 300 -> 64 and a ReLU and tiles those 64 values over the 7x7
map (models/encoders.py: WordVectorEncoder). Its vectors come precomputed, one per
category name, from an h5 file (`datasets/glove.py`, `thor_glove`); here they are read
from a GloVe text file the user gives (`--word-vectors FILE`):

    word v1 v2 ... vD          one word per line, D numbers, D the same on every line

A first line of two integers "N D" followed by lines of D numbers is word2vec's text
header and is skipped; one followed by lines of another count is refused as a header
that does not fit. A category's vector is the file's vector of its name as written
("CoffeeMachine") or in lower case ("coffeemachine"); failing both, the mean of the
vectors of its camel-case words in lower case ("coffee", "machine"), as the usual GloVe
vocabularies hold lower-case single words. A malformed line (a word without numbers, a
number that is not one, another D than the first line's) is a one-line ValueError naming
the file and the line; so is a word the categories need that the file gives twice with
different vectors (which one was meant cannot be told; twice the same vector is
accepted); a word the file lacks is one naming the file, the word and the category.

A run trained with a file keeps the sha256 of its (22, D) table in its config
(`word_vectors_sha256`, `WordTable.sha256`): evaluation and resume refuse a file whose
vectors are not those (training/runs.py: keep_word_vectors, check_word_vectors).

Without a file the stand-in is used (STAND_IN): a fixed random unit vector per category
(300-d, numpy's default_rng(STAND_IN_SEED)). It holds no semantics: two categories are as
alike as any two others, so the network's input is the one-hot target up to a fixed
rotation, through SAVN's layout. Why this and not a vocabulary shipped with the package:
no word-vector file is distributed with this project (GloVe is 800 MB and none can be
fetched here), and random vectors keep the layout and widths of SAVN's input without
claiming a semantic prior it would not have. Rows trained with the stand-in are labelled
"random word vectors" (`label`).

    table = category_table(path_or_None)     # WordTable: (22, D), hashable (a module field)
    table.array()                            # np.ndarray (22, D) float32
    table.sha256                             # what a run keeps of the vectors it read
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
import re
from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES

STAND_IN_DIM = 300           # GloVe's width in SAVN's release (args.glove_dim)
STAND_IN_SEED = 41
STAND_IN = "random unit vectors (seed 41)"


@dataclasses.dataclass(frozen=True)
class WordTable:
    """A (rows, dim) float32 table as bytes: hashable, so a flax module can hold it."""
    data: bytes
    rows: int
    dim: int
    source: str              # the file it was read from, or STAND_IN

    def array(self) -> np.ndarray:
        return np.frombuffer(self.data, np.float32).reshape(self.rows, self.dim)

    @property
    def sha256(self) -> str:
        """sha256 of the table (its shape and float32 values): equal for equal vectors,
        whatever the file's formatting or name."""
        return hashlib.sha256(f"{self.rows}x{self.dim}:".encode() + self.data).hexdigest()

    @staticmethod
    def of(array: np.ndarray, source: str) -> "WordTable":
        a = np.ascontiguousarray(array, np.float32)
        return WordTable(a.tobytes(), a.shape[0], a.shape[1], source)


def camel_words(name: str) -> list[str]:
    """"CoffeeMachine" -> ["coffee", "machine"]; "TVStand" -> ["tv", "stand"]."""
    return [w.lower() for w in re.findall(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+", name)]


def stand_in(categories=CATEGORIES, dim: int = STAND_IN_DIM,
             seed: int = STAND_IN_SEED) -> np.ndarray:
    """(C, dim) fixed random unit vectors, one per category."""
    x = np.random.default_rng(seed).standard_normal((len(categories), dim))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def read_vectors(path: str | Path, words) -> tuple[dict[str, np.ndarray], int]:
    """The vectors of `words` (a set) in a GloVe text file -> ({word: vector}, D). Every
    line's shape is checked (a word and D numbers); the numbers of the words asked for
    are parsed and must be finite. One-line ValueError naming the file and line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"word vectors {path}: no such file")
    found, where, dim, header = {}, {}, None, None
    with open(path, "rb") as f:
        for n, raw in enumerate(f, 1):
            try:
                line = raw.decode("utf-8")
            except UnicodeDecodeError:
                raise ValueError(f"word vectors {path}, line {n}: not UTF-8 text") from None
            parts = line.split()
            if not parts:
                raise ValueError(f"word vectors {path}, line {n}: empty line, expected "
                                 "'word v1 ... vD'")
            if n == 1 and len(parts) == 2 and all(p.isdigit() for p in parts):
                header = (int(parts[0]), int(parts[1]))  # word2vec's "N D", if line 2 fits
                continue
            if dim is None:
                dim, first = len(parts) - 1, n
                if dim < 1:
                    raise ValueError(f"word vectors {path}, line {n}: a word without "
                                     "numbers, expected 'word v1 ... vD'")
                if header is not None and dim != header[1] and dim != 1:
                    raise ValueError(
                        f"word vectors {path}, line 1: '{header[0]} {header[1]}' looks like "
                        f"a word2vec header ('N D'), but line {n} has {dim} numbers, not "
                        f"{header[1]}: expected 'word v1 ... vD' lines")
                # a header whose D does not fit line 2's single number: line 1 was a word
                # and one number (no category's word is a number: nothing to keep of it)
            if len(parts) - 1 != dim:
                raise ValueError(f"word vectors {path}, line {n}: {len(parts) - 1} numbers, "
                                 f"expected {dim} (line {first}'s, the first vector's)")
            if parts[0] in words:
                try:
                    v = np.array([float(x) for x in parts[1:]], np.float64)
                except ValueError:
                    raise ValueError(f"word vectors {path}, line {n}: {parts[0]!r} has a "
                                     "value that is not a number") from None
                if not np.isfinite(v).all() or np.abs(v).max() > 3.4e38:
                    raise ValueError(f"word vectors {path}, line {n}: {parts[0]!r} has a "
                                     "value that is not a finite float32")
                if parts[0] in found:
                    if not np.array_equal(found[parts[0]], v):
                        raise ValueError(
                            f"word vectors {path}, line {n}: {parts[0]!r} is given again "
                            f"(first on line {where[parts[0]]}) with another vector: "
                            "expected one vector per word")
                    continue
                found[parts[0]], where[parts[0]] = v, n
    if dim is None and header is not None:
        raise ValueError(f"word vectors {path}: only a header line '{header[0]} "
                         f"{header[1]}', expected lines 'word v1 ... vD'")
    if dim is None:
        raise ValueError(f"word vectors {path}: empty file, expected lines "
                         "'word v1 ... vD'")
    return found, dim


def category_vectors(path: str | Path, categories=CATEGORIES) -> np.ndarray:
    """(C, D) the categories' vectors from a GloVe text file (module docstring)."""
    wanted = {w for c in categories for w in (c, c.lower(), *camel_words(c))}
    found, dim = read_vectors(path, wanted)
    rows = []
    for c in categories:
        if c in found or c.lower() in found:
            rows.append(found.get(c, found.get(c.lower())))
            continue
        missing = [w for w in camel_words(c) if w not in found]
        if missing:
            raise ValueError(f"word vectors {path}: no vector for {missing[0]!r} (category "
                             f"{c}: its name, its name in lower case, or each of its words "
                             f"{camel_words(c)})")
        rows.append(np.mean([found[w] for w in camel_words(c)], axis=0))
    return np.stack(rows).astype(np.float32)


def category_table(path: str | Path | None) -> WordTable:
    """The WordTable of a config's word_vectors: the file's, or the stand-in (None).
    Read once per process, path and file version (size and modification time: models
    are built several times per run, and a file changed meanwhile is read again)."""
    if path is None:
        return _table(None, None)
    try:
        st = os.stat(path)
        version = (st.st_size, st.st_mtime_ns)
    except OSError:
        version = None                       # read_vectors names what is wrong
    return _table(str(path), version)


@functools.lru_cache(maxsize=8)
def _table(path: str | None, version) -> WordTable:
    if path is None:
        return WordTable.of(stand_in(), STAND_IN)
    return WordTable.of(category_vectors(path), path)


def label(word_vectors: str | None) -> str:
    """How a row's target vectors are described: the file's name or the stand-in."""
    return f"word vectors {Path(word_vectors).name}" if word_vectors else \
        f"random word vectors (stand-in: {STAND_IN})"


__all__ = ["STAND_IN", "WordTable", "camel_words", "category_table", "category_vectors",
           "label", "read_vectors", "stand_in"]
