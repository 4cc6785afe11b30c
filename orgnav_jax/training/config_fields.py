"""What both training stages' configs are made of (training/config.py: TrainConfig;
tpn/config.py: TPNConfig): the config version, the run-bookkeeping fields, the allowed
range of a numeric field, the type and range checks, and one command-line option per
field.

    class MyConfig(run_fields(updates_per_chunk=10, eval_every_chunks=5,
                              checkpoint_every_chunks=5, run_dir="")):
        lr: float = 3e-4
    check_types(cfg, "config field"); check_ranges(cfg, {**RUN_RANGES, "lr": POSITIVE}, ...)
    add_field_options(ap, MyConfig, "config fields"); given_options(args, MyConfig)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import numbers

CONFIG_VERSION = 9   # 2: the split LSTM trunk (new parameter layout); 3: il_norm, il_step;
                     # 4: devices, dtype (scale-out; same parameters and checkpoints);
                     # 5: max_steps renamed episode_cap (both stages); 6: the savn fields
                     # (issue 39's net, prev_action came within 6); 7: issues 40 and 41
                     # (target_input, word_vectors, optim, savn_act; the TPN's placement,
                     # optim); 8: savn_segments (issue 40: SAVN refills ended rows at
                     # segment boundaries; its runner holds the running episodes); 9: SAVN's
                     # fast weights keep every LSTM layer's kernels as low-rank slots (its
                     # runner's rows: a tuple per layer; before, the first layer's only)
READABLE_VERSIONS = (2, 3, 4, 5, 6, 7, 8, 9)   # configs and checkpoints this version reads
# Fields renamed since, old name -> new, for the configs of versions before 5 (both stages)
RENAMED = {"max_steps": "episode_cap"}
OLD_RENAMES = {v: RENAMED for v in (2, 3, 4)}
# CLI flags kept under their old names too
OLD_FLAGS = {"episode_cap": "--max-steps"}

INT32_MAX = 2 ** 31 - 1
FLOAT_MAX = 1.7976931348623157e308
# Integer fields are int32 (the env and the jitted loop count in int32), except the
# budgets, counted on the host: at most a trillion env steps (episodes).
BUDGET_MAX = 10 ** 12
BUDGETS_FIELDS = ("total_env_steps", "total_episodes")


# Field metadata: the stages whose jitted programs do not read a field, of "nav" (stage 1),
# "pretrain" (VTNet's pre-training) and "tpn" (stage 2), as run_dir.STAGES names them.
# Runs that differ only in such fields share one compiled program: the programs' cache
# key is the config with them reset (compile_cache.py: computation_of, host_only_fields).
HOST_ONLY = "host_only"
STAGE_NAMES = ("nav", "pretrain", "tpn")


def host_only(default, *stages: str):
    """A config field (its default) that only the host reads in `stages` (none given:
    in every stage): their jitted programs do not read it (HOST_ONLY)."""
    return dataclasses.field(default=default, metadata={HOST_ONLY: stages or STAGE_NAMES})


def host_only_fields(cls, stage: str) -> tuple[str, ...]:
    """The fields of a config class that `stage`'s jitted programs do not read."""
    return tuple(f.name for f in dataclasses.fields(cls)
                 if stage in f.metadata.get(HOST_ONLY, ()))


def run_fields(*, updates_per_chunk: int, eval_every_chunks: int,
               checkpoint_every_chunks: int, run_dir: str):
    """The base dataclass of a stage's config: the fields of its run's bookkeeping (the
    driver's host loop reads them; training/driver.py), with the stage's defaults. All
    but updates_per_chunk (a chunk's length is compiled) are host-only in every stage."""
    spec = (  # name, type, default, host only
        ("updates_per_chunk", int, updates_per_chunk, False),   # jitted updates between
                                                                # the host's logs, checks
        ("eval_every_chunks", int, eval_every_chunks, True),
        ("eval_episodes_per_room_type", int, 50, True),   # val episodes during training
                                                          # (test: 250)
        ("checkpoint_every_chunks", int, checkpoint_every_chunks, True),
        ("keep_checkpoints", int, 2, True),
        ("seed", int, 0, True),            # a traced input (the PRNG key), never static
        ("run_dir", str, run_dir, True),
    )
    cls = dataclasses.make_dataclass(
        "RunFields", [(name, kind, host_only(value) if host else dataclasses.field(
            default=value)) for name, kind, value, host in spec], frozen=True)
    cls.__module__ = __name__
    return cls


@dataclasses.dataclass(frozen=True)
class Range:
    """The allowed values of a numeric config field: lo (<= or <) value (<= or <) hi;
    floats must be finite; `note` explains a special value."""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    note: str = ""

    def ok(self, x) -> bool:
        if isinstance(x, float) and not math.isfinite(x):
            return False
        return ((self.lo is None or (x > self.lo if self.lo_open else x >= self.lo))
                and (self.hi is None or (x < self.hi if self.hi_open else x <= self.hi)))

    def text(self, name: str, integer: bool) -> str:
        """The range in words: "0 < gamma <= 1", "an integer num_envs >= 1"."""
        num = lambda x: f"{x:,}" if float(x).is_integer() and abs(x) >= 1e4 else f"{x:g}"
        if self.lo is not None and self.hi is not None:
            out = (f"{num(self.lo)} {'<' if self.lo_open else '<='} {name} "
                   f"{'<' if self.hi_open else '<='} {num(self.hi)}")
        elif self.lo is not None:
            out = f"{name} {'>' if self.lo_open else '>='} {num(self.lo)}"
            out += "" if integer else ", finite"
        else:
            out = f"a finite {name}"
        out = f"an integer {out}" if integer else out
        return out + (f" ({self.note})" if self.note else "")


COUNT = Range(lo=1)                    # counts, widths, budgets
SEED = Range(lo=0, hi=INT32_MAX)
POSITIVE = Range(lo=0, lo_open=True)   # finite and > 0
NON_NEGATIVE = Range(lo=0)             # finite and >= 0
FINITE = Range()
EPISODE_CAP = Range(lo=1, hi=INT32_MAX - 1)   # the env counts steps in int32
# The ranges of the run_fields (run_dir is a string).
RUN_RANGES: dict[str, Range] = {
    "seed": SEED,
    **{f: COUNT for f in ("updates_per_chunk", "eval_every_chunks",
                          "eval_episodes_per_room_type", "checkpoint_every_chunks",
                          "keep_checkpoints")},
}


def check_types(cfg, prefix: str) -> None:
    """Each field holds a value of its declared kind (int, float, bool, str, None); a
    config read from JSON may not; an integer given for a float field must fit a float.
    ValueError naming the field otherwise."""
    for f in dataclasses.fields(cfg):
        value, kind = getattr(cfg, f.name), type(f.default)
        if kind is bool:
            ok = isinstance(value, bool)
        elif kind is int:
            ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
        elif kind is float:
            ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
            if ok and isinstance(value, numbers.Integral) and abs(value) > FLOAT_MAX:
                raise ValueError(f"{prefix} {f.name!r}: an integer of {len(str(value))} "
                                 "digits, expected a finite number")
        elif f.default is None:
            ok = value is None or isinstance(value, str)
        else:
            ok = isinstance(value, kind)
        if not ok:
            want = {bool: "true or false", int: "an integer", float: "a number",
                    str: "a string"}.get(kind, "a string or null")
            raise ValueError(f"{prefix} {f.name!r}: {value!r}, expected {want}")
        if kind in (int, float) and type(value) not in (int, float):
            # numpy's numbers (np.float32(1e-3), np.int64(8)) as Python's: the config is
            # written as JSON (to_json) and compared with saved ones
            object.__setattr__(cfg, f.name, int(value) if isinstance(
                value, numbers.Integral) else float(value))


def check_ranges(cfg, ranges: dict[str, Range], prefix: str) -> None:
    """ValueError for the first field outside its Range: `<prefix> 'gamma': 2.0, expected
    0 < gamma <= 1`; integers are also int32 (budgets: at most BUDGET_MAX)."""
    for name, rng in ranges.items():
        value = getattr(cfg, name)
        integer = isinstance(value, numbers.Integral)
        if not rng.ok(value):
            raise ValueError(f"{prefix} {name!r}: {value!r}, expected "
                             f"{rng.text(name, integer)}")
        limit = BUDGET_MAX if name in BUDGETS_FIELDS else INT32_MAX
        if integer and not -limit - 1 <= value <= limit:
            raise ValueError(f"{prefix} {name!r}: {value!r}, expected "
                             f"{rng.text(name, integer)} and at most {limit:,}"
                             + (" (int32)" if limit == INT32_MAX else ""))


def budget_notice(field: str, total: int, per_update: int, updates_per_chunk: int,
                  per_update_text: str) -> str | None:
    """The note when a budget (`field` = total) is not whole chunks of updates_per_chunk
    updates of per_update env steps (episodes): a run does num_updates = max(1, total //
    per_update) updates, rounded up to whole chunks (training/driver.py). None if equal."""
    updates = max(1, total // per_update)
    run = math.ceil(updates / updates_per_chunk) * updates_per_chunk * per_update
    if run == total:
        return None
    return (f"note: {field} {total:,} rounds {'up' if run > total else 'down'} to {run:,} "
            f"(whole chunks of {updates_per_chunk} update{'s' * (updates_per_chunk != 1)} "
            f"x {per_update_text})")


def parse_bool(text: str) -> bool:
    """A command-line boolean: 1/true/yes or 0/false/no (any case)."""
    if text.lower() in ("1", "true", "yes"):
        return True
    if text.lower() in ("0", "false", "no"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def add_field_options(ap: argparse.ArgumentParser, cls, title: str, *, prefix: str = "",
                      flags: dict[str, str] | None = None, only=None) -> None:
    """One --option per field of the config class `cls` (all, or those in `only`), in
    an argument group `title`, default None (the preset's or the run's value): --name-
    with-dashes, or flags[name]; the old name too (OLD_FLAGS). The value lands in
    args.<prefix><name> (given_options reads them back)."""
    group = ap.add_argument_group(title)
    for f in dataclasses.fields(cls):
        if only is not None and f.name not in only:
            continue
        kind = {bool: parse_bool, int: int, float: float}.get(type(f.default), str)
        flag = (flags or {}).get(f.name, f.name.replace("_", "-"))
        names = ["--" + flag] + ([OLD_FLAGS[f.name]] if f.name in OLD_FLAGS else [])
        group.add_argument(*names, dest=prefix + f.name, type=kind, default=None,
                           metavar=type(f.default).__name__.upper()
                           if f.default is not None else "STR")


def given_options(args: argparse.Namespace, cls, prefix: str = "") -> dict:
    """{field: value} of the options add_field_options added that were given."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {k[len(prefix):]: v for k, v in vars(args).items()
            if k.startswith(prefix) and k[len(prefix):] in names and v is not None}
