"""Fixtures every test file shares: the "tiny" benchmark (16 rooms), built at most once
per session and saved once (tiny_dir), sample generated rooms, and cli_error (a CLI's
one-line error and exit code 2).
"""

from __future__ import annotations

import os
import shutil
import tempfile

# One on-disk compile cache for the whole session, set before jax is imported: the same
# small programs compiled in another test's process (the CLI and multi-device
# subprocesses, which inherit the environment) are read back instead of compiled again.
# A cache the caller set is used as is and kept; the session's own is removed at the end.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="orgnav-test-jit-")
    os.environ["ORGNAV_TEST_OWNS_JIT_CACHE"] = os.environ["JAX_COMPILATION_CACHE_DIR"]
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")
# a size bound turns on jax's file lock around cache reads and writes (processes share
# it); jax needs filelock (a dev dependency) for it, and warns on every compile without
try:
    import filelock  # noqa: F401
    os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(8 << 30))
except ImportError:
    pass

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from orgnav_jax import constants as K  # noqa: E402
from orgnav_jax import scenes
from orgnav_jax.scenes.synthetic import catalog, layout

# A few floorplans of every room type (train numbering), for single-room tests.
SAMPLE_FLOORPLANS: tuple[int, ...] = (1, 2, 3, 201, 202, 203, 301, 302, 303, 401, 402, 403)


@pytest.fixture(scope="session")
def tiny_scenes() -> scenes.SceneSet:
    """scenes.build("tiny", seed=0): 2 train, 1 val, 1 test room per room type."""
    return scenes.build("tiny", seed=0)


@pytest.fixture(scope="session")
def tiny_dir(tmp_path_factory, tiny_scenes) -> str:
    """tiny_scenes saved once per session (read-only for tests: copy it to change it)."""
    path = tmp_path_factory.mktemp("scenes") / "tiny"
    scenes.save(tiny_scenes, path)
    return str(path)


@pytest.fixture(scope="session")
def sample_rooms() -> dict[int, layout.Room]:
    """generate_room(0, fp) for a few floorplans of each room type."""
    return {fp: layout.generate_room(0, fp) for fp in SAMPLE_FLOORPLANS}


def _make_room(shape: tuple[int, int] = (9, 9), *, walls=(), furniture=None,
               unreachable=(), objects=(), room_type: str = "kitchen") -> layout.Room:
    """A hand-made Room: an outer wall ring plus

    walls: extra full-height wall cells (i, j);
    furniture: {(i, j): block height in metres} (furniture kind 'table');
    unreachable: free cells that are nevertheless marked not reachable;
    objects: (category name, x, y_centre, z) tuples, sized from the catalog.
    """
    H, W = shape
    wall = np.ones((H, W), bool)
    wall[1:-1, 1:-1] = False
    for i, j in walls:
        wall[i, j] = True
    furn = np.full((H, W), -1, np.int32)
    block = np.where(wall, np.inf, 0.0).astype(np.float32)
    for (i, j), h in (furniture or {}).items():
        furn[i, j] = catalog.FURNITURE_INDEX["table"]
        block[i, j] = h
    reachable = ~wall & (furn < 0) & (block == 0)
    for i, j in unreachable:
        reachable[i, j] = False
    cats = np.array([K.category_index(c) for c, *_ in objects], np.int32)
    centre = np.array([[x, y, z] for _, x, y, z in objects], np.float32).reshape(-1, 3)
    size = np.array([catalog.OBJECTS[c].size for c, *_ in objects], np.float32)
    height = np.array([catalog.OBJECTS[c].height for c, *_ in objects], np.float32)
    return layout.Room(floorplan=1, room_type=room_type, wall=wall, furniture=furn,
                       block_height=block, reachable=reachable, obj_category=cats,
                       obj_center=centre, obj_size=size, obj_height=height, door=(0, 1))


@pytest.fixture
def make_room():
    """Factory for hand-made rooms (see _make_room)."""
    return _make_room


@pytest.fixture
def cli_error(capsys):
    """cli_error(main, argv) -> the `error: ...` line a CLI prints for a user error
    (asserts exit code 2, no traceback, and that the message is the last stderr line)."""
    from orgnav_jax.errors import run_cli

    def call(main, argv) -> str:
        capsys.readouterr()
        rc = run_cli(main, [str(a) for a in argv])
        err = capsys.readouterr().err
        assert rc == 2, f"exit code {rc}, stderr: {err[-2000:]}"
        assert "Traceback" not in err, err
        lines = [line for line in err.splitlines() if line.strip()]
        assert lines and lines[-1].startswith("error: "), err[-2000:]
        return lines[-1]
    return call


def pytest_unconfigure(config):
    """The session's own compile cache goes when the main process ends (not a worker's)."""
    owned = os.environ.get("ORGNAV_TEST_OWNS_JIT_CACHE")
    if owned and not hasattr(config, "workerinput"):
        shutil.rmtree(owned, ignore_errors=True)
