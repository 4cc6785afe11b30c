"""Fixtures every test file shares: the "tiny" benchmark (16 rooms), built at most once
per pytest session (per xdist worker) and saved once (tiny_dir), sample generated rooms,
and cli_error (a CLI's one-line error and exit code 2); the number of xdist workers.

No on-disk jit cache is set up for the pytest session: on 2 cores, looking every compile
up in one and writing it there cost more than the few programs a test's subprocess could
read back (docs/testing.md).
In one process jit's own cache serves a repeat; a cache the caller sets
(JAX_COMPILATION_CACHE_DIR) is used as is.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import scenes
from orgnav_jax.scenes.synthetic import catalog, layout


def pytest_xdist_auto_num_workers(config) -> int:
    """`-n auto` (pyproject's addopts): one worker per core this process may use, at most
    4: each worker holds its own jax and compiles what it runs (the largest process of a
    2-worker suite reached 4.6 GB resident, `/usr/bin/time -v`,
    docs/history/test-suite-time.md)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(cores or 1, 4))


# A few floorplans of every room type (train numbering), for single-room tests.
SAMPLE_FLOORPLANS: tuple[int, ...] = (1, 2, 3, 201, 202, 203, 301, 302, 303, 401, 402, 403)


@pytest.fixture(scope="session")
def tiny_scenes() -> scenes.SceneSet:
    """scenes.build("tiny", seed=0): 2 train, 1 val, 1 test room per room type."""
    return scenes.build("tiny", seed=0)


@pytest.fixture(scope="session")
def tiny_dir(tmp_path_factory, tiny_scenes) -> str:
    """tiny_scenes saved once per pytest session (read-only for tests: copy it to change
    it)."""
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
