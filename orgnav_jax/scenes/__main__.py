"""python -m orgnav_jax.scenes: build, inspect, render, import, export or convert scene
sets (the commands: scenes/cli.py)."""

from __future__ import annotations

import sys

from orgnav_jax.errors import run_cli
from orgnav_jax.scenes.cli import main

if __name__ == "__main__":
    sys.exit(run_cli(main))
