"""Scale-out: the device mesh, sharded runner states, processes (docs/scale_out.md).

    init_distributed(coordinator, num_processes, process_id)   # before any device is used
    mesh = make_mesh(cfg.devices)            # None: one device in one process (no sharding)
    check_batch(cfg.num_envs, mesh)          # num_envs must divide by the devices
    runner = place(runner, runner_shardings(runner, mesh))     # env axis over "data"
    scenes = place(scenes, replicated(scenes, mesh))

Data parallel: one mesh axis, "data", over the devices of every process. The env (batch)
axis of the runner state (env states, LSTM carries, fresh, episode returns, and so the
rollout's trajectories inside the jitted chunk) is sharded over it; parameters, the
optimizer state, the PRNG key and the update count are replicated, as is the scene set.
The chunk is the same jitted function of (runner, scenes): XLA partitions it from the
shardings of its inputs (and the constraints `constrain` puts on the runner at the start
and end of every update), and the gradient's mean over the env axis becomes an
all-reduce that XLA inserts. Random numbers do not depend on the sharding (jax's
partitionable threefry), so a run on D devices computes the same function as on one
device; only the order of float reductions (the all-reduce) differs.

Processes: with jax.distributed every process runs the same program on its own devices
(the mesh spans all of them); arrays are global (jax.Array over non-addressable devices)
and every process makes the same calls. Process 0 alone holds the run directory's lock
and writes config.json, the logs and results (`is_primary`); orbax checkpoints are
written by all processes together.
"""

from __future__ import annotations

import socket
import sys
import time
from pathlib import Path

import numpy as np

import jax
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from orgnav_jax.errors import UserError
from orgnav_jax.training.run_dir import open_run_dir

DATA = "data"          # the mesh axis the env batch is sharded over
# RunnerState fields whose leaves have the env batch as their leading axis
BATCH_FIELDS = ("env_state", "carry", "fresh", "ep_return")


# --------------------------------------------------------------------------- processes
DISTRIBUTED_TIMEOUT_S = 300       # jax.distributed's own default, now said out loud


def init_distributed(coordinator: str | None = None, num_processes: int | None = None,
                     process_id: int | None = None, auto: bool = False,
                     timeout_s: int = DISTRIBUTED_TIMEOUT_S) -> None:
    """jax.distributed.initialize with the given coordinator (HOST:PORT, validated), process
    count and id; auto=True lets JAX detect them (Slurm, Open MPI, TPU pods, or the
    environment variables JAX_COORDINATOR_ADDRESS, ...). Prints what it waits for and
    gives up after timeout_s with a UserError. Must run before anything touches a device."""
    given = [x is not None for x in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        raise UserError("--coordinator, --num-processes and --process-id go together "
                        "(or use --distributed to let JAX detect them from the launcher)")
    if not (any(given) or auto):
        return
    if all(given):
        host, port = check_coordinator(coordinator)
        if num_processes < 1 or not 0 <= process_id < num_processes:
            raise UserError(f"--process-id {process_id} --num-processes {num_processes}: "
                            "expected 0 <= process id < number of processes")
        print(f"waiting up to {timeout_s} s for the coordinator at {coordinator} and "
              f"{num_processes} process(es) ...", file=sys.stderr, flush=True)
        if process_id > 0:       # XLA's runtime aborts the process when it gives up
            wait_for_port(host, port, timeout_s)
        _initialize(f"the coordinator at {coordinator} and {num_processes} processes",
                    timeout_s, coordinator, num_processes, process_id)
    else:
        print(f"waiting up to {timeout_s} s for the launcher's processes ...",
              file=sys.stderr, flush=True)
        _initialize("the processes the launcher (Slurm, Open MPI, JAX_COORDINATOR_ADDRESS) "
                    "names", timeout_s)


def check_coordinator(address: str) -> tuple[str, int]:
    """--coordinator HOST:PORT (HOST a name, IPv4 or [IPv6]; PORT 1-65535) -> (host, port);
    UserError otherwise (XLA's runtime crashes on a malformed address)."""
    host, sep, port = str(address).rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    ok_host = bool(host) and all(c.isalnum() or c in ".-_:" for c in host)
    if not sep or not ok_host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise UserError(f"--coordinator {address!r}: expected HOST:PORT with a port "
                        "1-65535 (e.g. node0:12345 or 10.0.0.1:12345)")
    return host, int(port)


def wait_for_port(host: str, port: int, timeout_s: float) -> None:
    """Until the coordinator's port accepts a connection; UserError after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            socket.create_connection((host, port), timeout=2).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise UserError(f"the coordinator at {host}:{port} did not answer within "
                                f"{timeout_s:g} s (is process 0 running, and this address "
                                "reachable?)") from None
            time.sleep(0.5)


def _initialize(what: str, timeout_s: int, *args) -> None:
    """jax.distributed.initialize(*args) with a timeout; UserError naming what it waited
    for when the runtime gives up."""
    try:
        jax.distributed.initialize(*args, initialization_timeout=timeout_s)
    except Exception as err:                      # noqa: BLE001 (XLA's runtime errors)
        if isinstance(err, UserError):
            raise
        text = " ".join(str(err).split())[:300]
        raise UserError(f"jax.distributed could not reach {what} within {timeout_s} s "
                        f"({type(err).__name__}: {text})") from None


def is_primary() -> bool:
    """Whether this process writes the run's files (process 0)."""
    return jax.process_index() == 0


def broadcast_flag(ok: bool) -> bool:
    """Process 0's `ok` on every process (True in a single process)."""
    if jax.process_count() == 1:
        return ok
    return bool(multihost_utils.broadcast_one_to_all(np.int32(ok)))


# --------------------------------------------------------------------------- the mesh
def make_mesh(devices: int = 0) -> Mesh | None:
    """A 1-D mesh ("data") over `devices` devices of every process (0: all local
    devices) -> Mesh, or None for one device in one process (the unsharded program)."""
    local = jax.local_devices()
    n = devices or len(local)
    if n > len(local):
        raise UserError(f"--devices {n}: this process sees {len(local)} "
                        f"{jax.default_backend()} device(s) (on CPU, "
                        "XLA_FLAGS=--xla_force_host_platform_device_count=N makes N)")
    if n == 1 and jax.process_count() == 1:
        return None
    chosen = [d for p in range(jax.process_count())
              for d in [d for d in jax.devices() if d.process_index == p][:n]]
    return Mesh(np.array(chosen), (DATA,))


def mesh_size(mesh: Mesh | None) -> int:
    return 1 if mesh is None else mesh.size


def check_batch(num_envs: int, mesh: Mesh | None) -> None:
    """num_envs must divide by the number of devices the env axis is sharded over."""
    n = mesh_size(mesh)
    if num_envs % n:
        raise UserError(f"num_envs {num_envs} does not divide by the {n} devices of the "
                        f"mesh: choose a multiple of {n} (--num-envs) or other --devices")


def describe(mesh: Mesh | None) -> str:
    """'1 cpu device' / '2 cpu devices in 2 processes'."""
    n = mesh_size(mesh)
    text = f"{n} {jax.default_backend()} device{'s' * (n != 1)}"
    return text + (f" in {jax.process_count()} processes" if jax.process_count() > 1 else "")


# --------------------------------------------------------------------------- shardings
def runner_shardings(runner, mesh: Mesh, population: bool = False):
    """A RunnerState-shaped tree of NamedShardings: the BATCH_FIELDS' leaves sharded on
    their env axis (axis 0; axis 1 with a leading population axis), the rest replicated.
    `runner` may hold arrays or ShapeDtypeStructs."""
    rep = NamedSharding(mesh, P())
    batch = NamedSharding(mesh, P(None, DATA) if population else P(DATA))
    same = lambda tree, s: jax.tree_util.tree_map(lambda _: s, tree)
    fields = {f: same(getattr(runner, f), batch) for f in BATCH_FIELDS}
    other = {f: same(v, rep) for f, v in vars(runner).items() if f not in BATCH_FIELDS}
    return runner.replace(**fields, **other)


def replicated(tree, mesh: Mesh):
    """`tree`'s structure with every leaf replicated over the mesh."""
    rep = NamedSharding(mesh, P())
    return jax.tree_util.tree_map(lambda _: rep, tree)


def place(tree, shardings):
    """Put a tree of local arrays (equal on every process) on the mesh with the given
    per-leaf shardings. One process: jax.device_put; several: each process supplies the
    shards its devices hold (jax.make_array_from_callback)."""
    if jax.process_count() == 1:
        return jax.device_put(tree, shardings)

    def one(x, s):
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, s, lambda idx: host[idx])
    return jax.tree_util.tree_map(one, tree, shardings)


def constrain(runner, mesh: Mesh | None):
    """Inside jit: pin the runner's shardings (no-op without a mesh). Under vmap (a
    population axis) the batched axis stays unsharded."""
    if mesh is None:
        return runner
    return jax.lax.with_sharding_constraint(runner, runner_shardings(runner, mesh))


def local_copy(tree):
    """Replicated global arrays -> their copy on this process's first device (for work
    every process does alone, e.g. the val evaluation); other leaves unchanged."""
    def one(x):
        if isinstance(x, jax.Array) and len(x.sharding.device_set) > 1 \
                and x.is_fully_replicated:
            return x.addressable_shards[0].data
        return x
    return jax.tree_util.tree_map(one, tree)


# --------------------------------------------------------------------------- run dirs
class open_shared_run_dir:
    """open_run_dir (training/run_dir.py: checked and locked) on process 0 alone; every
    process learns whether it succeeded, so that no process starts a collective chunk
    that process 0 will never join. One process: exactly open_run_dir."""

    def __init__(self, run_dir, cfg, resume: bool, load_saved):
        self.run_dir = run_dir
        self.inner = open_run_dir(run_dir, cfg, resume, load_saved) if is_primary() else None

    def __enter__(self):
        err = None
        if self.inner is not None:
            try:
                self.inner.__enter__()
            except BaseException as e:          # told to the others, then raised
                err = e
        ok = broadcast_flag(err is None)
        if err is not None:
            raise err
        if not ok:
            raise UserError(f"process 0 could not open the run directory {self.run_dir} "
                            "(see its error)")
        return Path(self.run_dir)

    def __exit__(self, *exc) -> None:
        if self.inner is not None:
            self.inner.__exit__(*exc)
