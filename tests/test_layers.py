"""The packages import only downward, in the data-flow order of the README's layout:
no module imports a layer above its own (function-level imports included), so there is
no import cycle between packages."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "orgnav_jax"

# lowest first; a module may import its own layer and those below
LAYERS = (
    ("constants", "errors", "safe_write", "tree", "compile_cache"),
    ("scenes",),
    ("episodes", "offline_episodes", "env", "reference_env"),
    ("models",),
    ("gymnax_env",),     # env + the models' feature decoding, as a gymnax Environment
    ("evaluation",),
    ("training",),
    ("tpn",),
    ("api", "plots"),
    ("train", "evaluate"),                   # the command-line entry points
)
LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}
# command-line entry points inside a package sit on top of everything
ENTRY_POINTS = {"scenes/__main__.py", "scenes/offline/cli.py"}


def top_part(module: str) -> str | None:
    """'orgnav_jax.scenes.offline.reader' -> 'scenes'; other packages -> None."""
    parts = module.split(".")
    return parts[1] if parts[0] == "orgnav_jax" and len(parts) > 1 else None


def imported_parts(path: Path) -> set[str]:
    """The orgnav_jax top-level parts a file imports, anywhere in it."""
    parts = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = ([f"orgnav_jax.{a.name}" for a in node.names]
                     if node.module == "orgnav_jax" else [node.module])
        else:
            continue
        parts |= {p for p in map(top_part, names) if p}
    return parts


def modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel != "__init__.py" and rel not in ENTRY_POINTS:
            yield rel


def test_every_top_level_part_has_a_layer():
    parts = {p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    parts |= {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert parts == set(LAYER)


@pytest.mark.parametrize("rel", list(modules()))
def test_imports_go_only_downward(rel):
    own = rel.split("/")[0].removesuffix(".py")
    above = {p for p in imported_parts(PACKAGE / rel) if LAYER[p] > LAYER[own]}
    assert not above, f"orgnav_jax/{rel} ({own}) imports a higher layer: {sorted(above)}"


def test_the_check_sees_function_level_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from orgnav_jax.tpn.config import X\n    import orgnav_jax.api\n"
                 "from orgnav_jax import episodes\n")
    assert imported_parts(f) == {"tpn", "api", "episodes"}
