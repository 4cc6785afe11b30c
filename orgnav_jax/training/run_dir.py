"""A run directory's guard rails: its kind, its lock, its config and its metrics log.

    with open_run_dir(run_dir, cfg, resume, load_saved):   # checked and locked
        ... restore the latest checkpoint if resuming ...
        write_config(run_dir, cfg)
        log = MetricsLog(run_dir, resume_from=step)
        ...

Layout (both training stages):
    config.json        the config (written atomically; it marks the directory as a run)
    .lock              {"pid", "host", "started"} while a process trains in it
    checkpoints/ best/ orbax checkpoints (training/checkpoints.py)
    metrics.jsonl tb/  logs (MetricsLog)

Guarantees: a fresh run refuses a non-empty directory (another run, or anything else);
two processes never train in one directory (the lock; a lock left by a process that no
longer runs on this host is taken over with a notice); --resume compares the saved config
with the requested one except for the budget (which may grow), locations (run_dir,
scenes_dir, base_dir: a copied or moved run resumes where it now is) and the number of
devices (a run may resume on more or fewer devices: training/scale.py).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import socket
import sys
import time
from pathlib import Path

from orgnav_jax.errors import (
    UserError, field_error, is_int, read_int, read_object, read_str, shown,
)
from orgnav_jax.safe_write import write_text_atomic

CONFIG_FILE = "config.json"
LOCK_FILE = ".lock"
METRICS_FILE = "metrics.jsonl"
BUDGET_FIELDS = ("total_env_steps", "total_episodes",   # a resume may extend these
                 "pretrain_samples")
LOCATION_FIELDS = ("run_dir", "scenes_dir", "base_dir",   # a resume follows the given ones
                   "pretrained")
PLACEMENT_FIELDS = ("devices",)   # where a run computes, not what: a resume may change it


STAGES = {"nav": "training", "tpn": "TPN (stage 2)",   # the kinds of run, in words
          "pretrain": "VTNet pre-training"}


def seed_run_dir(run_dir: str, seed: int) -> str:
    """The run directory of one seed of a population: <run_dir>-s<seed>."""
    return f"{str(run_dir).rstrip('/')}-s{seed}"


def read_config(run_dir: str | os.PathLike, cls, stage: str, versions: tuple[int, ...],
                upgrades: dict[int, dict] | None = None,
                renames: dict[int, dict[str, str]] | None = None,
                values: dict[int, dict[str, dict]] | None = None,
                required: dict[str, str] | None = None):
    """config.json of a run directory -> cls(**fields).validate(), after checking that it
    is JSON, of this `stage`, of one of `versions` (upgrades[v]: the values of fields a
    version-v config lacks; renames[v]: old field name -> new; values[v][field]: old
    value -> the value that means it now) with known field names, the `required` fields
    present (field -> why: a field whose default changed without a new version, so that
    its absence says nothing), every field's type and range checked (cls.validate:
    check_types, check_ranges); one-line errors naming the file and the field."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: {run_dir} is not a {STAGES[stage]} run "
                                "directory")
    try:
        doc = json.loads(path.read_text())
    except (ValueError, RecursionError) as err:
        raise ValueError(f"{path}: not a valid config JSON ({type(err).__name__})") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object of config fields")
    found = doc.pop("stage", "nav")
    if found != stage:
        if not isinstance(found, str) or found not in STAGES:
            raise field_error(path, "stage", f"one of {list(STAGES)}", found)
        raise ValueError(f"{path}: not a {STAGES[stage]} run, but a {STAGES[found]} one")
    version = doc.pop("version", None)
    if not is_int(version) or version not in versions:
        raise ValueError(f"{path}: config version {shown(version)}, this orgnav_jax reads "
                         f"versions {list(versions)}")
    renamed = (renames or {}).get(version, {})
    doc = {renamed.get(k, k): v for k, v in doc.items()}
    for field, meaning in (values or {}).get(version, {}).items():
        if field in doc and isinstance(doc[field], str) and doc[field] in meaning:
            doc[field] = meaning[doc[field]]
    doc = {**(upgrades or {}).get(version, {}), **doc}
    bad = sorted(set(doc) - {f.name for f in dataclasses.fields(cls)})
    if bad:
        raise ValueError(f"{path}: unknown config field(s) {bad}")
    for field, why in (required or {}).items():
        if field not in doc:
            raise ValueError(f"{path}: field {field!r} is missing: {why}")
    try:
        return cls(**doc).validate()
    except ValueError as err:      # "config field 'lr': ..." -> "<path>: config field ..."
        raise ValueError(f"{path}: {err}") from None


class RunDirLocked(UserError):
    """Another live process trains in this run directory."""


def is_run_dir(path: str | os.PathLike) -> bool:
    """Whether `path` holds a run of this program (a config.json with a version)."""
    try:
        doc = json.loads((Path(path) / CONFIG_FILE).read_text())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and "version" in doc


def saved_steps(run_dir: str | os.PathLike, sub: str = "checkpoints") -> list[int]:
    """The steps of a run's latest-N checkpoints (RUN/checkpoints/<step>/; sub="best":
    the best-on-val one), read from the directory names (no jax, nothing created),
    ascending; [] when there are none. A save still in progress or killed (orbax's
    `<step>.orbax-checkpoint-tmp-*`) is not one."""
    try:
        names = [p.name for p in (Path(run_dir) / sub).iterdir() if p.is_dir()]
    except OSError:
        return []
    return sorted(int(n) for n in names if n.isdigit())


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:      # exists, owned by someone else
        return True
    return True


class RunLock:
    """An exclusive lock file in a run directory: {"pid", "host", "started"}.

    Created with O_EXCL, so of two processes only one gets it. A lock whose process no
    longer runs on this host is stale and taken over (with a notice on stderr); a lock
    held by a live process, or by another host, raises RunDirLocked naming the holder."""

    def __init__(self, run_dir: str | os.PathLike):
        self.path = Path(run_dir) / LOCK_FILE
        self.held = False

    def _holder(self) -> dict | None:
        try:
            doc = json.loads(self.path.read_text())
            return doc if isinstance(doc, dict) else None
        except (OSError, ValueError):
            return None

    def acquire(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        for _ in range(5):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                holder = self._holder()
                if holder is None:
                    if time.time() - _mtime(self.path) < 5:   # being written right now
                        time.sleep(0.2)
                        continue
                    raise RunDirLocked(f"{self.path.parent} is locked by {self.path}, which "
                                       "cannot be read; delete it if no process trains there")
                pid, host = holder.get("pid"), holder.get("host")
                if host == me["host"] and isinstance(pid, int) and not _alive(pid):
                    self._take_over_stale(pid)
                    continue
                raise RunDirLocked(f"{self.path.parent} is in use by process {pid} on {host} "
                                   f"(lock file {self.path}); wait until it ends, or delete the "
                                   "lock file if that process is gone")
            with os.fdopen(fd, "w") as f:
                json.dump(me, f)
            self.held = True
            return self
        raise RunDirLocked(f"could not lock {self.path.parent} (lock file {self.path})")

    def _take_over_stale(self, pid: int) -> None:
        aside = self.path.with_name(f"{LOCK_FILE}.stale.{os.getpid()}")
        try:
            os.rename(self.path, aside)      # atomic: one of several takers wins
        except FileNotFoundError:
            return
        aside.unlink(missing_ok=True)
        print(f"note: {self.path.parent}: took over the lock of process {pid}, which no "
              "longer runs", file=sys.stderr)

    def release(self) -> None:
        if self.held and (self._holder() or {}).get("pid") == os.getpid():
            self.path.unlink(missing_ok=True)
        self.held = False

    def __enter__(self) -> "RunLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return time.time()


def config_differences(saved, wanted) -> list[str]:
    """Fields (other than budget, locations and placement) where two configs differ, as
    'f: a -> b'. The word-vector file is a location too where the saved run keeps the
    sha256 of its vectors (compared as a field: the same vectors at another path)."""
    skip = set(BUDGET_FIELDS) | set(LOCATION_FIELDS) | set(PLACEMENT_FIELDS)
    if getattr(saved, "word_vectors_sha256", None) is not None:
        skip.add("word_vectors")
    return [f"{f.name}: {getattr(saved, f.name)!r} -> {getattr(wanted, f.name)!r}"
            for f in dataclasses.fields(saved)
            if f.name not in skip and getattr(saved, f.name) != getattr(wanted, f.name)]


def check_run_dir(run_dir: str | os.PathLike, cfg, resume: bool, load_saved) -> None:
    """Before a run starts. A fresh run needs an absent or empty directory. --resume needs
    a run directory whose saved config (load_saved(run_dir)) equals cfg except that the
    budget may grow (the run then continues to the larger budget, matching a run started
    with it when the old budget ended on an evaluation and checkpoint chunk) and the
    locations may differ (a copied or moved run)."""
    run_dir = Path(run_dir)
    if not resume:
        if run_dir.exists() and not run_dir.is_dir():
            raise FileExistsError(f"--run-dir {run_dir} is a file, expected a directory")
        entries = sorted(p.name for p in run_dir.iterdir() if p.name != LOCK_FILE) \
            if run_dir.is_dir() else []
        if entries and is_run_dir(run_dir):
            raise FileExistsError(f"--run-dir {run_dir} already holds a run: pass --resume "
                                  "to continue it, or choose another --run-dir")
        if entries:
            shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
            raise FileExistsError(f"--run-dir {run_dir} is a non-empty directory that is not "
                                  f"a run ({shown}); it is left untouched: choose another "
                                  "--run-dir")
        return
    if not is_run_dir(run_dir):
        raise FileNotFoundError(f"--resume: {run_dir} holds no run ({CONFIG_FILE} is "
                                "missing or not a run config)")
    saved = load_saved(run_dir)
    diff = config_differences(saved, cfg)
    if diff:
        raise ValueError(f"--resume: {run_dir}/{CONFIG_FILE} differs from the requested "
                         f"config ({'; '.join(diff)}); resume with the same options (or none)")
    for f in BUDGET_FIELDS:
        if hasattr(cfg, f) and getattr(cfg, f) < getattr(saved, f):
            raise ValueError(f"--resume: {f} {getattr(cfg, f)} is below the run's "
                             f"{getattr(saved, f)}; a resume may only extend the budget")


class open_run_dir:
    """Context: check the directory (check_run_dir) and lock it; the lock is released on
    exit, whatever happens. The caller writes config.json (write_config) once it has
    restored the checkpoint it resumes from, so a failed resume changes nothing."""

    def __init__(self, run_dir, cfg, resume: bool, load_saved):
        self.run_dir, self.cfg, self.resume, self.load_saved = Path(run_dir), cfg, resume, \
            load_saved
        self.lock = RunLock(self.run_dir)

    def __enter__(self) -> Path:
        check_run_dir(self.run_dir, self.cfg, self.resume, self.load_saved)  # before writing
        self.lock.acquire()
        try:
            check_run_dir(self.run_dir, self.cfg, self.resume, self.load_saved)  # now locked
        except BaseException:
            self.lock.release()
            raise
        return self.run_dir

    def __exit__(self, *exc) -> None:
        self.lock.release()


def write_config(run_dir: str | os.PathLike, cfg) -> None:
    """config.json of a run directory, written atomically."""
    write_text_atomic(Path(run_dir) / CONFIG_FILE, cfg.to_json())


def read_metrics(run_dir: str | os.PathLike, step_name: str = "env_steps",
                 skip_broken: bool = False) -> list[dict]:
    """The typed reader of a run's metrics.jsonl (MetricsLog writes it) -> its records,
    in file order. Each line is a JSON object {"kind": a string ("train", "val"),
    <step_name>: an int >= 0 (env_steps; episodes for stage 2), metric: a number, ...}
    (nan and inf are numbers: a mean over no episodes). ValueError naming the file, the
    line and the field otherwise; with skip_broken, lines that are not JSON at all (the
    last line of a killed run) are skipped. FileNotFoundError when the file is missing."""
    path = Path(run_dir) / METRICS_FILE
    out = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        where = f"{path} line {n}"
        try:
            rec = json.loads(line)
        except (ValueError, RecursionError):
            if skip_broken:
                continue
            raise ValueError(f"{where}: not valid JSON (expected one JSON object a "
                             "line)") from None
        read_object(rec, where, "a JSON object {kind, " + step_name + ", metric: number}")
        read_str(rec, "kind", where)
        read_int(rec, step_name, where, hi=None)
        for key, value in rec.items():
            if key != "kind" and (isinstance(value, bool) or
                                  not isinstance(value, (int, float))):
                raise field_error(where, key, "a number", value)
        out.append(rec)
    return out


def drop_metrics_after(run_dir: str | os.PathLike, step: int,
                       step_name: str = "env_steps") -> int:
    """Cut a run's metrics.jsonl back to the records at or before `step` (what a resume
    from the checkpoint at `step` keeps: it writes the later ones again), atomically ->
    the number of records dropped (0 when there is no file). A line cut by a kill is
    dropped; a malformed record is an error (read_metrics)."""
    path = Path(run_dir) / METRICS_FILE
    if not path.exists():
        return 0
    records = read_metrics(run_dir, step_name, skip_broken=True)
    keep = [rec for rec in records if rec[step_name] <= step]
    write_text_atomic(path, "".join(json.dumps(rec) + "\n" for rec in keep))
    return len(records) - len(keep)


class MetricsLog:
    """Appends one JSON object per record to metrics.jsonl and, if tensorboardX is
    installed, the same scalars to TensorBoard event files under tb/.

    resume_from=step (a resumed run) first drops the records written after that
    checkpoint step (they are written again), in the file and in TensorBoard."""

    def __init__(self, run_dir: Path, step_name: str = "env_steps",
                 resume_from: int | None = None):
        self.path, self.step_name = Path(run_dir) / METRICS_FILE, step_name
        if resume_from is not None:
            drop_metrics_after(run_dir, resume_from, step_name)
        try:
            # tensorboardX on first use (~0.7 s): run directories are read where no run
            # is logged (api, the tables, the command lines' --help)
            from tensorboardX import SummaryWriter
            purge = None if resume_from is None else resume_from + 1
            self.tb = SummaryWriter(str(Path(run_dir) / "tb"), purge_step=purge)
        except ImportError:  # logs stay readable as JSONL
            self.tb = None

    def write(self, kind: str, step: int, values: dict) -> None:
        with self.path.open("a") as f:
            f.write(json.dumps({"kind": kind, self.step_name: step, **values}) + "\n")
        if self.tb:
            for k, v in values.items():
                if isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(f"{kind}/{k}", v, step)
            self.tb.flush()

    def close(self) -> None:
        if self.tb:
            self.tb.close()
