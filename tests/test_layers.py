"""The packages import only downward, in the data-flow order of the README's layout:
no module imports a layer above its own (function-level imports included), so there is
no import cycle between packages. No module is exempt: the command lines sit on top."""

from __future__ import annotations

import ast
import io
import tokenize
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


# ---- the package's own imports (issue 66): at the top of each module, where a reader
# sees the import graph; inside a function only where a heavy optional dependency (torch,
# matplotlib) or a light importer (api, the command lines' --help: no jax) needs it, few,
# each saying why on its line or the comment line above; no cycle between modules

FUNCTION_IMPORTS_LIMIT = 30     # function-level imports in orgnav_jax/: fewer than this


def function_imports(path: Path) -> list[ast.stmt]:
    """The import statements inside a function (at any depth) of a file."""
    found = []

    def visit(node, inside: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if inside and isinstance(child, (ast.Import, ast.ImportFrom)):
                found.append(child)
            visit(child, inside or isinstance(child, (ast.FunctionDef,
                                                      ast.AsyncFunctionDef, ast.Lambda)))
    visit(ast.parse(path.read_text()), False)
    return found


def comment_lines(path: Path) -> tuple[set[int], set[int]]:
    """(lines holding a comment, lines holding nothing but a comment) of a file."""
    anywhere, alone = set(), set()
    for tok in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if tok.type == tokenize.COMMENT:
            anywhere.add(tok.start[0])
            if not tok.line[:tok.start[1]].strip():
                alone.add(tok.start[0])
    return anywhere, alone


def explained(node: ast.stmt, comments: tuple[set[int], set[int]]) -> bool:
    """Whether an import has a comment on one of its lines or a comment line above it."""
    anywhere, alone = comments
    return bool(anywhere & set(range(node.lineno, node.end_lineno + 1))) or \
        node.lineno - 1 in alone


def test_function_level_imports_are_few_and_each_says_why():
    found, silent = [], []
    for rel in modules():
        path = PACKAGE / rel
        comments = comment_lines(path)
        for node in function_imports(path):
            found.append(f"orgnav_jax/{rel}:{node.lineno}")
            if not explained(node, comments):
                silent.append(found[-1])
    assert not silent, ("function-level imports without a comment saying why (on the "
                        f"import or the line above): {silent}")
    assert len(found) < FUNCTION_IMPORTS_LIMIT, (
        f"{len(found)} function-level imports in orgnav_jax/ (fewer than "
        f"{FUNCTION_IMPORTS_LIMIT} expected; import at the top): {found}")


def module_imports(module: str, path: Path) -> set[str]:
    """The package's modules that importing `module` (at `path`) imports: its import
    statements outside functions (class bodies and if/try blocks run on import), each
    with the packages above the imported module that are not `module`'s own (their
    __init__ runs first)."""
    found = set()

    def visit(node) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(child, ast.Import):
                found.update(a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.update(f"{child.module}.{a.name}" if is_module(
                    f"{child.module}.{a.name}") else child.module for a in child.names)
            visit(child)
    visit(ast.parse(path.read_text()))
    out = set()
    for name in found:
        parts = name.split(".")
        if parts[0] != "orgnav_jax":
            continue
        while parts and not is_module(".".join(parts)):    # `import a.b.NAME`: a.b
            parts.pop()
        out |= {".".join(parts[:i]) for i in range(2, len(parts) + 1)}
    own = {module.rsplit(".", k)[0] for k in range(module.count("."))}
    return out - own - {module}


def import_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One cycle of a directed graph as [a, b, ..., a], or [] when it has none."""
    state: dict[str, int] = {}           # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        state[node] = 2
        path.pop()
        return []

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return []


def test_no_import_cycle_between_modules():
    graph = {module_name(rel): module_imports(module_name(rel), PACKAGE / rel)
             for rel in modules()}
    cycle = import_cycle(graph)
    assert not cycle, f"an import cycle between modules: {' -> '.join(cycle)}"


def test_the_package_import_checks_see_what_they_look_for(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import os\n\n\nclass C:\n    import json\n\n\ndef g():\n"
                 "    import numpy  # heavy: on first use\n    # why, above\n"
                 "    from orgnav_jax import api\n    x = 1  # a comment above is no reason\n"
                 "    import torch\n\n    def h():\n        import jax\n")
    found = function_imports(f)
    assert [n.lineno for n in found] == [9, 11, 13, 16]
    comments = comment_lines(f)
    assert [explained(n, comments) for n in found] == [True, True, False, False]
    assert import_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == \
        ["a", "b", "c", "a"]
    assert import_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []
    navmodel = PACKAGE / "models" / "navmodel.py"
    assert {"orgnav_jax.models.vtnet", "orgnav_jax.scenes",
            "orgnav_jax.scenes.sceneset", "orgnav_jax.scenes.sceneset.features"} <= \
        module_imports("orgnav_jax.models.navmodel", navmodel)
    assert "orgnav_jax.models" not in module_imports("orgnav_jax.models.navmodel", navmodel)
