"""The README and docs/ read as reference: the README's python blocks run as written (in a
fresh directory), its size and top section stay small, every command of its commands table
answers `--help`, its headline tables show the committed tables' numbers, every relative
link in the README and docs/ resolves, and no words about
the project's own work periods or borrowed machines appear in the README, docs/ (outside
docs/history/, which keeps dated accounts) or the code's comments and docstrings."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
HISTORY = DOCS / "history"

README_MAX_BYTES = 15_000           # "at most 15 KB"
README_TOP_MAX_LINES = 24           # lines before the commands table: under 25
FIRST_LINES = ["```bash",
               "pip install -e . && python -m orgnav_jax.train",
               'pip install -e ".[dev]" && python -m pytest -q',
               "```"]

# Words of the project's work periods and of borrowed machines. Pytest's own sense is
# allowed: `scope="session"`, "session-scoped", "pytest session". The patterns spell the
# words in pieces, so that this file passes its own check.
FORBIDDEN = re.compile(r"\b(se(?:ssions?)|lo(?:ans?|aned)|le(?:nt|ases?|ased|asing))\b", re.I)
PYTEST_SENSE = re.compile(r"""scope\s*=\s*["']se(?:ssion)["']|se(?:ssion)[- ]scoped?|"""
                          r"""pytest(?:'s)?\s+se(?:ssions?)""", re.I)
CODE_DIRS = ("orgnav_jax", "benchmarks", "tests")


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "the README has no python block"
    monkeypatch.chdir(tmp_path)
    for block in blocks:
        namespace: dict = {}
        exec(compile(block, str(README), "exec"), namespace)   # noqa: S102
    assert (tmp_path / "runs" / "demo" / "config.json").exists()


def test_readme_size_first_commands_and_top_section():
    text = README.read_text()
    size = len(text.encode())
    assert size <= README_MAX_BYTES, f"README.md is {size:,} bytes, at most {README_MAX_BYTES:,}"
    lines = text.splitlines()
    assert lines[:4] == FIRST_LINES, "the README must open with the two commands"
    top = lines.index("## Commands")
    assert top <= README_TOP_MAX_LINES, (
        f"{top} lines before the commands table, at most {README_TOP_MAX_LINES}")
    assert "## Headline results" in lines


def readme_section(title: str) -> str:
    """The README's text under `## title`, up to the next `## ` heading."""
    return README.read_text().split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def commands_table() -> list[str]:
    """The commands (first column, one code span each) of the README's commands table."""
    section = readme_section("Commands")
    rows = [line for line in section.splitlines() if line.startswith("| `")]
    return [re.match(r"\| `(.+?)` \|", row)[1].replace("\\|", "|") for row in rows]


def program_of(command: str) -> list[list[str]]:
    """The program part of a table command (up to its first option, placeholder or
    optional part), one per alternative of a `a|b|c` subcommand: argv lists."""
    words = command.split()
    assert words[0] == "python", command
    argv: list[str] = []
    for word in words[1:]:
        if argv and (word.startswith("-") or word.startswith("[") or "..." in word
                     or re.search(r"[A-Z]", word) or "/" in word and argv[0] == "-m"):
            break
        if "|" in word:
            parts = word.split("|")
            assert all(re.fullmatch(r"[a-z][a-z-]*", p) for p in parts), command
            return [argv + [p] for p in parts]
        argv.append(word)
    return [argv]


def test_every_readme_command_answers_help():
    """Each distinct program of the commands table runs `--help` with exit code 0, in a
    subprocess of its own (four at a time)."""
    commands = commands_table()
    assert len(commands) >= 10, commands
    programs = sorted({tuple(p) for c in commands for p in program_of(c)})
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    failed = []
    for i in range(0, len(programs), 4):
        procs = [(p, subprocess.Popen([sys.executable, *p, "--help"], cwd=ROOT, env=env,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True)) for p in programs[i:i + 4]]
        for program, proc in procs:
            out, _ = proc.communicate(timeout=300)
            if proc.returncode != 0 or "usage" not in out.lower():
                failed.append(f"python {' '.join(program)} --help: exit {proc.returncode}: "
                              f"{out[-300:]}")
    assert not failed, "\n".join(failed)


def markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def anchors_of(path: Path) -> set[str]:
    """GitHub's heading anchors of a markdown file, and its explicit <a id=...>."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    out = set(re.findall(r'<a id="([^"]+)"', text))
    for heading in re.findall(r"^#{1,6} +(.+?) *$", text, re.M):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        out.add(slug)
    return out


def test_relative_links_resolve():
    """Every relative link of the README and docs/ (docs/history/ included) names a file
    or folder that exists and, for a markdown file, a heading anchor it has."""
    bad = []
    for path in markdown_files():
        text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
        text = re.sub(r"`[^`\n]*`", "", text)                 # code spans are not links
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z][a-z0-9+.-]*:", target):      # https:, mailto: ...
                continue
            file_part, _, anchor = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path
            where = f"{path.relative_to(ROOT)}: ({target})"
            if not dest.exists():
                bad.append(f"{where}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in anchors_of(dest):
                bad.append(f"{where}: no heading with anchor #{anchor}")
    assert not bad, "\n".join(bad)


def forbidden_in(text: str) -> list[str]:
    return [m.group(0) for m in FORBIDDEN.finditer(PYTEST_SENSE.sub("", text))]


def test_no_work_period_or_loan_words_outside_history():
    """README.md, docs/ outside docs/history/, and every line (code, names, messages,
    comments, docstrings) of orgnav_jax/, benchmarks/, experiments/ (its scripts) and
    tests/ (this file too) say what and why, with dates, machines or
    commits: none of FORBIDDEN's words (pytest's session aside)."""
    bad = []
    for path in markdown_files():
        if HISTORY in path.parents:
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            bad += [f"{path.relative_to(ROOT)}:{n}: {w!r}" for w in forbidden_in(line)]
    sources = [p for d in CODE_DIRS for p in sorted((ROOT / d).rglob("*.py"))]
    sources += sorted((ROOT / "experiments").rglob("*.py"))
    sources += sorted((ROOT / "experiments").rglob("*.sh"))
    for path in sources:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            bad += [f"{path.relative_to(ROOT)}:{n}: {w!r}" for w in forbidden_in(line)]
    assert not bad, "\n".join(bad)


# The README's headline tables: which committed table a column pair (success, SPL) is
# read from, keyed by the header's first cell and the success column's header; and which
# row of table.md a README row shows.
HEADLINE_COLUMNS = {("row", "small: success"): "table_5m",
                    ("row", "calibrated: success"): "table_calibrated",
                    ("row, at its convergence", "success"): "table_converged_ext"}
HEADLINE_ROWS = {"Random": "random", "WE": "we", "D-SP": "dsp", "SAVN": "savn",
                 "D-SAVN": "dsavn", "Baseline": "baseline",
                 "Baseline + TPN": "baseline+tpn@1e-4", "Baseline + IL": "il",
                 "Baseline + ORG": "org", "ORG + IL (w/o TPN)": "org_il",
                 "ORG + TPN (w/o IL)": "org+tpn@1e-4", "IL + TPN (w/o ORG)": "il+tpn@1e-4",
                 "ORG + IL + TPN (full model)": "org_il+tpn@1e-4",
                 "full model, TPN on every step": "org_il+tpn_all@1e-4",
                 "full model, TPN random target": "org_il+tpn_random@1e-4",
                 "VTNet (pre-trained on the expert's actions)": "vtnet †"}


def markdown_tables(text: str) -> list[list[list[str]]]:
    """Each table of `text` as rows of stripped cells (the |---| line dropped)."""
    tables, current = [], []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            if not set(line) <= set("|- "):
                current.append([c.strip().strip("*").strip()
                                for c in line.strip().strip("|").split("|")])
        elif current:
            tables.append(current)
            current = []
    return tables


def test_readme_headline_numbers_are_the_committed_tables():
    """Every success ± std and SPL the README's headline tables show is the row's entry in
    its committed table.md (which `claims.py --check` recomputes from the runs): a number
    copied wrong, or left behind when a table changed, fails here."""
    section = readme_section("Headline results")
    results = ROOT / "experiments" / "results"
    checked = 0
    for header, *body in markdown_tables(section):
        for col, name in enumerate(header):
            table = HEADLINE_COLUMNS.get((header[0], name))
            if table is None:
                continue
            entries = {cells[0]: cells for cells in markdown_tables(
                (results / table / "table.md").read_text())[0][1:]}
            for cells in body:
                assert cells[0] in HEADLINE_ROWS, f"README row {cells[0]!r} has no table row"
                if cells[col] == "-":
                    continue
                key = HEADLINE_ROWS[cells[0]]
                assert key in entries, f"{table}/table.md has no row {key!r}"
                success, spl = entries[key][2], entries[key][3]
                assert (cells[col], cells[col + 1]) == (success, spl.split(" ±")[0]), (
                    f"README {cells[0]!r} ({name}): {cells[col]}, {cells[col + 1]}; "
                    f"{table}/table.md: {success}, {spl}")
                checked += 1
    assert checked >= 30, f"only {checked} README numbers found: did the tables move?"
