"""The packages import only downward, in the data-flow order of the README's layout:
no module imports a layer above its own (function-level imports included), so there is
no import cycle between packages. No module is exempt: the command lines sit on top."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "orgnav_jax"
SPLIT = {"scenes"}   # packages whose sub-packages and modules are parts of their own

# lowest first; a module may import its own layer and those below
LAYERS = (
    ("constants", "errors", "safe_write", "tree", "compile_cache"),
    ("scenes.sceneset",),   # the SceneSet data model: what every source produces
    ("scenes.synthetic",),  # the procedural generator
    ("scenes.offline",),    # the authors' format (their episode files: EpisodeSets)
    ("scenes", "scenes.summary"),   # the front door (scenes/__init__.py), a set's summary
    ("episodes", "env", "reference_env"),
    ("models",),
    ("gymnax_env",),     # env + the models' feature decoding, as a gymnax Environment
    ("evaluation",),
    ("training",),
    ("tpn",),
    ("tables",),         # run layout, statistics, convergence rule: what tables are made of
    ("api", "plots"),
    ("train", "evaluate", "scenes.cli", "scenes.__main__"),   # the command lines
)
LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}


def is_module(module: str) -> bool:
    """Whether 'orgnav_jax.a.b' is a module or package of this package."""
    path = PACKAGE.parent.joinpath(*module.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def part(module: str) -> str | None:
    """'orgnav_jax.models.encoders' -> 'models'; in a SPLIT package its children are
    parts: 'orgnav_jax.scenes.offline.reader' -> 'scenes.offline', 'orgnav_jax.scenes'
    (the package itself) -> 'scenes'; other packages -> None."""
    parts = module.split(".")
    if parts[0] != "orgnav_jax" or len(parts) < 2:
        return None
    if parts[1] in SPLIT and len(parts) > 2:
        return f"{parts[1]}.{parts[2]}"
    return parts[1]


def imported_parts(path: Path) -> set[str]:
    """The orgnav_jax parts a file imports, anywhere in it."""
    parts = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            # `from P import m` imports module P.m when there is one, else names of P
            names = [f"{node.module}.{a.name}" if is_module(f"{node.module}.{a.name}")
                     else node.module for a in node.names]
        else:
            continue
        parts |= {p for p in map(part, names) if p}
    return parts


def module_name(rel: str) -> str:
    """'scenes/offline/reader.py' -> 'orgnav_jax.scenes.offline.reader';
    'scenes/__init__.py' -> 'orgnav_jax.scenes'."""
    return ".".join(["orgnav_jax", *rel.removesuffix(".py").split("/")]).removesuffix(
        ".__init__")


def modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel != "__init__.py":
            yield rel


def test_every_module_has_a_layer():
    parts = {part(module_name(rel)) for rel in modules()}
    assert parts == set(LAYER)


@pytest.mark.parametrize("rel", list(modules()))
def test_imports_go_only_downward(rel):
    own = part(module_name(rel))
    above = {p for p in imported_parts(PACKAGE / rel) if LAYER[p] > LAYER[own]}
    assert not above, f"orgnav_jax/{rel} ({own}) imports a higher layer: {sorted(above)}"


def test_the_check_sees_function_level_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from orgnav_jax.tpn.config import X\n    import orgnav_jax.api\n"
                 "from orgnav_jax import episodes\n")
    assert imported_parts(f) == {"tpn", "api", "episodes"}


def test_the_check_sees_the_parts_of_scenes(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from orgnav_jax.scenes import offline, build\n"
                 "from orgnav_jax.scenes.synthetic.builder import build\n"
                 "import orgnav_jax.scenes.cli\n")
    assert imported_parts(f) == {"scenes.offline", "scenes", "scenes.synthetic", "scenes.cli"}
    assert part(module_name("scenes/sceneset/__init__.py")) == "scenes.sceneset"
    assert part(module_name("scenes/__init__.py")) == "scenes"


# ---- experiments/: thin command lines over the package (docs/results.md, "The tables
# library"): they import the package up to api and plots (never a command line, never
# each other), leave sys.path alone, and import at the top, or say why not

EXPERIMENTS = PACKAGE.parent / "experiments"
SCRIPT_LAYER = LAYER["api"]          # experiments/ sits beside api, below the command lines


def scripts():
    for path in sorted(EXPERIMENTS.rglob("*.py")):
        rel = path.relative_to(EXPERIMENTS)
        if rel.parts[0] != "results":
            yield rel.as_posix()


SCRIPT_NAMES = {Path(rel).stem for rel in scripts()}


def imported_names(path: Path) -> set[str]:
    """The top-level names of every module a file imports, anywhere in it."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            names |= {"." if node.level else node.module.split(".")[0]}
    return names


def late_imports(path: Path) -> list[ast.stmt]:
    """The imports that are not statements of the module's top level (inside a function,
    a class or an `if` block)."""
    tree = ast.parse(path.read_text())
    top = {id(node) for node in tree.body}
    return [node for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))
            and id(node) not in top]


def says_why(lines: list[str], node: ast.stmt) -> bool:
    """Whether an import carries a comment on its own lines or the line above."""
    span = lines[node.lineno - 1:node.end_lineno]
    return any("#" in line for line in span) or \
        lines[node.lineno - 2].strip().startswith("#")


@pytest.mark.parametrize("rel", list(scripts()))
def test_scripts_import_only_the_package_and_never_each_other(rel):
    path = EXPERIMENTS / rel
    others = imported_names(path) & (SCRIPT_NAMES | {"."})
    assert not others, f"experiments/{rel} imports another script: {sorted(others)}"
    above = {p for p in imported_parts(path) if LAYER[p] > SCRIPT_LAYER}
    assert not above, f"experiments/{rel} imports a command line: {sorted(above)}"


def sys_path_lines(path: Path) -> list[int]:
    """The lines where a file uses sys.path."""
    return [node.lineno for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.Attribute) and node.attr == "path"
            and isinstance(node.value, ast.Name) and node.value.id == "sys"]


@pytest.mark.parametrize("rel", list(scripts()))
def test_scripts_leave_sys_path_alone(rel):
    touched = sys_path_lines(EXPERIMENTS / rel)
    assert not touched, f"experiments/{rel} uses sys.path on line(s) {touched}"


@pytest.mark.parametrize("rel", list(scripts()))
def test_scripts_import_at_the_top_or_say_why(rel):
    path = EXPERIMENTS / rel
    lines = path.read_text().splitlines()
    silent = [node.lineno for node in late_imports(path) if not says_why(lines, node)]
    assert not silent, (f"experiments/{rel}: imports inside a function without a comment "
                        f"saying why, line(s) {silent}")


def test_the_script_checks_see_what_they_look_for(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import sys\nimport run_table\n\n\ndef g():\n    import claims\n"
                 "    from orgnav_jax import api  # (a reason)\n    sys.path.insert(0, '.')\n")
    assert {"run_table", "claims"} <= imported_names(f) & SCRIPT_NAMES
    lines = f.read_text().splitlines()
    assert [says_why(lines, n) for n in late_imports(f)] == [False, True]
    assert sys_path_lines(f) == [8]
