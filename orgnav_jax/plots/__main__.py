"""python -m orgnav_jax.plots (see orgnav_jax.plots)."""

import sys

from orgnav_jax.errors import run_cli
from orgnav_jax.plots.cli import main

if __name__ == "__main__":
    sys.exit(run_cli(main))
