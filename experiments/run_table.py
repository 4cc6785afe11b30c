"""Reproduce a table: several rows (training presets) x seeds, equal budgets, test split.

    python experiments/run_table.py --spec experiments/tables/table_5m.json
    python experiments/claims.py --check experiments/results/table_5m

A spec (JSON: out, rows, seeds, config overrides, tpn fields) is the table's one
definition; it is copied to OUT/spec.json, which claims.py reads. Without --spec:

    python experiments/run_table.py --rows baseline il org org_il il_all --seeds 0 1 2 \\
        --total-env-steps 1000000 --out experiments/results/tables

    python experiments/run_table.py --rows baseline baseline+tpn org_il org_il+tpn \\
        org_il+tpn_all org_il+tpn_random --out experiments/results/table2

(The first made the 1 M table of docs/history/results-1m.md before network parity; that
table is kept in experiments/results/before_parity/tables.)

Each (row, seed) trains in OUT/runs/<row>-s<seed> (skipped when its test results exist,
resumed when it has checkpoints: rerun the same command after an interruption; Ctrl-C
first cuts the training runs' metrics.jsonl back to their newest checkpoint, where the
rerun continues, so a stopped table's small files can be committed as they are), is
evaluated on the test split (best-on-val checkpoint, 250 episodes per room type), and
the table is rewritten after every run: OUT/results.json (every run) and OUT/table.md
(mean +- std over seeds, with the failure analysis: wrong Done, timeout, revisits and
failed moves); at the end OUT/curves.png shows the val learning curves of the non-TPN
rows (python -m orgnav_jax.plots curves). Rows already in OUT/results.json from earlier
invocations stay. Extra `--FIELD VALUE` options apply to every row.

The row `random` evaluates the uniform random policy on the same test episodes (seed S
samples its actions) in OUT/runs/random-s<seed>. Every run directory also gets
provenance.json: the code version (git commit, uncommitted changes), CPU, jax version and
time of each process that trained or evaluated it (claims.py tables them in OUT/
provenance.md); results JSONs keep every episode's outcome (per_episode), so claims.py
can pair rows episode by episode.

A row BASE+VARIANT (VARIANT in tpn, tpn_all, tpn_random, tpn_cosine, tpn_train_mode) uses the run of row BASE (trained
first if needed), trains its TPN (stage 2) in OUT/runs/BASE-s<seed>/tpn once, and
evaluates it with that variant of the test-time update (Table 2: "all" updates on every
step, "random" takes a random action as the target; "cosine" detects deadlocks by the
paper's global-feature match instead of the visited set; "train_mode" runs the network
with dropout during the TPN evaluation, as the release did). Baseline+TPN is baseline+tpn; the
full model (ORG+IL+TPN) is org_il+tpn. A suffix @LR sets the test-time learning rate
(default 1e-4), e.g. org_il+tpn@1e-3.

--population trains the seeds of each navigation row in one program (the seeds as a
vmapped population axis of one jitted chunk: api.train_seeds) before the table is
filled; the run directories, resumption and results are the same as without it (seeds
of a row that were started one by one are finished one by one).

A spec with `"converged": true` (population, >= 2 seeds, 1,000-episode val evaluations)
also gets OUT/convergence.md: the convergence rule on every trained row at its budget,
and claims.md names the rows not converged (docs/results.md, "When a row has converged").

A spec with `"extends": BASE` (also converged) makes BASE's table at convergence
(docs/results.md, "Amendment: rows not converged at 22 M"; orgnav_jax/tables/extend.py):
each row BASE has finished is judged by the rule on its own val curves; a row that has
converged there (or that the rule cannot judge: SAVN) is carried over, its runs copied
into OUT with their test results; a row that has not is copied without its test results
and TPN and trains on, its seeds in one program, until the rule holds or the spec's
total_env_steps (the cap), then is tested (its best-on-val checkpoint over the whole run)
and its TPN rows trained again on it; a row BASE is still training is left for a later
invocation. BASE's files are only read.

VTNet's rows (issue 43, docs/vtnet.md): `vtnet` pre-trains each seed's visual
transformer on the expert's actions first (api.pretrain of the seed's PretrainConfig, in
OUT/runs/vtnet-pretrain-s<seed> beside the row's runs: config.json, metrics.jsonl with
the val accuracy, provenance.json), then trains A2C from it (the run's `pretrained`), as
`python -m orgnav_jax.train --preset vtnet` does; `vtnet_scratch` has no pre-training.
A rerun reuses a finished pre-training, resumes a partial one, and skips it once the A2C
run has started. The pre-trainings run one seed at a time (they are minutes each; the
A2C stage of a population still trains its seeds in one program). The pre-training's
budget (samples, batch, best val accuracy) goes into the row's results per seed and a
note under table.md: it is supervision the other rows do not get.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.constants import DEFAULT_SCENE_PRESET
from orgnav_jax.errors import read_json, run_cli
from orgnav_jax.plots import plot_curves
from orgnav_jax.safe_write import write_text_atomic
from orgnav_jax.tables import extend, table_files
from orgnav_jax.tables.layout import (check_out, existing_results, pretrain_dir,
                                      results_path, run_dir)
from orgnav_jax.tables.provenance import process_provenance, record_provenance, work_recorded
from orgnav_jax.tables.rows import Row, all_row_names, parse_row
from orgnav_jax.tables.runs import pretrain_budget, read_results
from orgnav_jax.tables.spec import read_spec, table_scenes
from orgnav_jax.tables.table import METRICS
from orgnav_jax.tpn.config import get_tpn_config
from orgnav_jax.training.config import add_config_arguments, get_config, overrides_from_args
from orgnav_jax.training.run_dir import RunLock, drop_metrics_after, is_run_dir, saved_steps

def done_or_none(out: Path, row: Row, seed: int) -> dict | None:
    """A row's test metrics for one seed when its results exist (checked against their
    per-episode outcomes), else None."""
    path = existing_results(out, row, seed)
    return None if path is None else read_results(path)[0]


def rewound_on_interrupt(run_dirs: list[Path], train: Callable[[], object]):
    """train() -> its value. On Ctrl-C, each run's metrics.jsonl is first cut back to the
    run's newest checkpoint, where --resume continues (it writes the later records again),
    so that a stopped table's files are those its resumed runs will keep, and the run's
    provenance records this process's part (the code and machine that trained it to that
    checkpoint); then the interrupt goes on."""
    try:
        return train()
    except KeyboardInterrupt:
        for where in run_dirs:
            steps = saved_steps(where)
            if steps:
                dropped = drop_metrics_after(where, steps[-1])
                record_provenance(where, f"trained to env step {steps[-1]:,}, interrupted")
                print(f"interrupted: {where}/metrics.jsonl kept to env step {steps[-1]:,}, "
                      f"its newest checkpoint ({dropped} later records dropped)",
                      file=sys.stderr, flush=True)
        raise


def run_tpn(row: Row, seed: int, out: Path, overrides: dict, tpn_fields: dict,
            extended: bool = False) -> dict:
    """BASE+VARIANT: train (or reuse) the base row and its TPN, evaluate the variant."""
    run_one(Row(row.base), seed, out, overrides, extended)
    done = done_or_none(out, row, seed)
    if done is not None:
        return done
    results = results_path(out, row, seed)
    tpn_dir = results.parent
    cfg = get_tpn_config(**tpn_fields, base_dir=str(tpn_dir.parent), seed=seed,
                         run_dir=str(tpn_dir))

    def work(resumed: bool) -> dict:
        # trains, continues an interrupted run, or (finished) only reloads it
        api.train_tpn(cfg, resume=resumed, progress=sys.stderr.isatty())
        return api.evaluate_run(tpn_dir, "test", out=results, progress=False,
                                **row.test_time())["overall"]
    return work_recorded(tpn_dir, work, lambda resumed: (
        f"{'finished or reloaded' if resumed else 'trained'} the TPN, tested {row.tpn_tag}"))


def pretrain_seed(row: Row, seed: int, out: Path, overrides: dict) -> Path:
    """The pre-training of a PRETRAIN_ROWS row's seed (api.pretrain_for the row's config,
    as `--preset vtnet` makes it): trained, resumed when partial, reused without work
    when finished -> its directory (the A2C run's `pretrained`)."""
    pre = pretrain_dir(out, row.base, seed)
    resumed = is_run_dir(pre)
    cfg = get_config(row.base, **{**overrides, "seed": seed})
    if api.pretrain_for(cfg, pre, progress=sys.stderr.isatty()):
        record_provenance(pre, f"{'resumed and finished' if resumed else 'trained'} the "
                               f"pre-training ({cfg.pretrain_samples:,} samples)")
    return pre


def run_one(row: Row, seed: int, out: Path, overrides: dict, extended: bool = False) -> dict:
    """Train (or resume, or skip) one row and seed -> its test metrics. Row `random`:
    the random policy on the same test episodes, its actions sampled with `seed`.
    extended (a table that extends another): the row's population trained the run under
    the convergence rule (train_row_population); it is only tested here."""
    done = done_or_none(out, row, seed)
    if done is not None:
        return done
    results = results_path(out, row, seed)
    where = results.parent
    if row.name == "random":
        metrics = api.evaluate_policy(
            "random", "test", overrides.get("scene_preset", DEFAULT_SCENE_PRESET),
            scenes_dir=overrides.get("scenes_dir"), seed=seed, out=results,
            progress=False)["overall"]
        record_provenance(where, "tested")
        return metrics
    pre = pretrain_dir(out, row.base, seed) if row.pretrains else None
    cfg = get_config(row.base, **{**overrides, "seed": seed, "run_dir": str(where),
                                  **({"pretrained": str(pre)} if pre else {})})

    def work(resumed: bool) -> dict:
        if pre and not resumed:          # once the A2C run has started, its start is fixed
            pretrain_seed(row, seed, out, overrides)
        if not extended:
            rewound_on_interrupt([where], lambda: api.train(
                cfg, resume=resumed, progress=sys.stderr.isatty()))
        return api.test_run(where, progress=False)["overall"]
    return work_recorded(where, work, lambda resumed: (
        "tested" if extended else f"{'resumed and finished' if resumed else 'trained'}"
        f"{f' from {pre.name}' if pre else ''}, tested"))


def train_row_population(row: Row, seeds: list[int], out: Path, overrides: dict,
                         extended: bool = False) -> None:
    """Train the seeds of navigation row `row` that lack test results in one program
    (OUT/runs/<row>-s<seed>); seeds whose runs were started separately are left to
    run_one (a population resumes only runs at a common checkpoint), as are SAVN rows.
    A PRETRAIN_ROWS row pre-trains its seeds first, one by one (pretrain_seed), and
    seed S starts from OUT/runs/<row>-pretrain-sS. extended: the row's runs, copied from
    the base table (extend.prepare), train on together until the convergence rule holds
    or the config's total_env_steps (the cap), from their checkpoints (UserError when one
    has none: it would start again from step 0); a resume the rule already stops does no
    more training. A run's provenance records the training only when some ran."""
    todo = [s for s in seeds if not results_path(out, row, s).exists()]
    if extended:
        if todo:
            extend.check_checkpoints(out, row.base, seeds)
            cfg = get_config(row.base, **{**overrides, "run_dir": str(out / "runs" / row.base)})
            summaries = rewound_on_interrupt(
                [run_dir(out, row, s) for s in seeds],
                lambda: api.train_seeds(cfg, seeds, resume=True, progress=sys.stderr.isatty(),
                                        until_converged=True))
            if summaries[0]["chunks_run"]:   # not when the rule held at the checkpoint
                for s in seeds:
                    record_provenance(run_dir(out, row, s), "trained on under the convergence "
                                      f"rule in one program with seeds {' '.join(map(str, seeds))}")
        return
    started = [is_run_dir(run_dir(out, row, s)) for s in todo]
    pre = {"pretrained": str(out / "runs" / f"{row.base}-pretrain")} if row.pretrains \
        else {}                          # train_seeds: seed S's is <pretrained>-sS
    cfg = get_config(row.base, **{**overrides, "run_dir": str(out / "runs" / row.base), **pre})
    if len(todo) < 2 or (any(started) and not all(started)) or cfg.savn:
        return                          # SAVN trains one seed per program (docs/savn.md)
    if pre and not all(started):
        for s in todo:
            pretrain_seed(row, s, out, overrides)
    summaries = rewound_on_interrupt(
        [run_dir(out, row, s) for s in todo],
        lambda: api.train_seeds(cfg, todo, resume=all(started), progress=sys.stderr.isatty()))
    if not summaries[0]["chunks_run"]:
        return                          # a resume that found the runs trained to the end
    for s in todo:
        record_provenance(run_dir(out, row, s),
                          f"trained in one program with seeds {' '.join(map(str, todo))}"
                          f"{f' from {row.base}-pretrain-s{s}' if pre else ''}")


def row_name(text: str) -> str:
    """Validate a --rows entry (rows.parse_row) for argparse."""
    try:
        parse_row(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def write_outputs(out: Path, results: dict, spec: dict | None) -> str:
    """The table files: with a spec, results.json, table.md, claims.md and provenance.md
    recomputed from the runs' files (table_files.write_all); without, table.md and
    results.json of `results` (table_files.write_table). -> table.md's text."""
    if spec is None:
        return table_files.write_table(out, results)
    return table_files.write_all(out)["table.md"]


def write_curves(out: Path, results: dict[str, dict[str, dict]]) -> Path | None:
    """OUT/curves.png: val success and SPL against env steps (mean and min-max band over
    seeds) of the rows that train a navigation model (TPN rows have no val curve of
    their own). Never ends a sweep: a missing metrics.jsonl is a warning."""
    runs = [run_dir(out, row, seed) for row, by_seed in results.items()
            if not Row.of(row).is_tpn for seed in by_seed]
    runs = [r for r in runs if (r / "metrics.jsonl").exists()]
    if not runs:
        return None
    try:
        path = out / "curves.png"
        plot_curves(runs, path, quiet=True)
        return path
    except Exception as err:                    # noqa: BLE001 (curves are optional)
        print(f"warning: no learning curves ({type(err).__name__}: {err})", file=sys.stderr)
        return None


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", nargs="+", default=["baseline", "il", "org", "org_il", "il_all"],
                    type=row_name, metavar="ROW",
                    help="rows: " + ", ".join(all_row_names()) + " (TPN rows may end in @LR)")
    ap.add_argument("--tpn-episodes", type=int, default=None,
                    help="stage-2 training episodes of TPN rows (TPNConfig.total_episodes)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--out", default="experiments/results/tables")
    ap.add_argument("--population", action="store_true",
                    help="train the seeds of each navigation row in one program")
    ap.add_argument("--spec", default=None,
                    help="a table spec (JSON: out, rows, seeds, config, tpn, and optionally "
                         "population), e.g. experiments/tables/table_5m.json; replaces "
                         "--rows, --seeds, --out, --tpn-episodes, --population and the "
                         "config options")
    ap.add_argument("--only", nargs="+", default=None, metavar="ROW",
                    help="with --spec: work on these rows of the spec now (the table files "
                         "are still rebuilt from every run of the spec)")
    add_config_arguments(ap)
    args = ap.parse_args(argv)
    process_provenance()                   # at start: the code this process loaded
    overrides = {k: v for k, v in overrides_from_args(args).items()
                 if k not in ("seed", "run_dir")}
    tpn_fields = {} if args.tpn_episodes is None else {"total_episodes": args.tpn_episodes}
    spec = None
    if args.spec:
        given = [a for a in (argv if argv is not None else sys.argv[1:])
                 if a.startswith("--") and a.split("=")[0] not in ("--spec", "--only")]
        if given:
            ap.error(f"--spec defines the table; drop {given[0].split('=')[0]}")
        spec = read_spec(args.spec)
        args.rows, args.seeds, args.out = spec["rows"], spec["seeds"], spec["out"]
        overrides, tpn_fields = spec["config"], spec["tpn"]
        args.population = spec.get("population", False)
        if args.only:
            bad = [r for r in args.only if r not in spec["rows"]]
            if bad:
                ap.error(f"--only {bad[0]}: not a row of {args.spec}")
            args.rows = args.only
    elif args.only:
        ap.error("--only goes with --spec")
    if not args.seeds or any(x < 0 for x in args.seeds):
        ap.error(f"--seeds: expected integers >= 0, got {args.seeds}")
    out = Path(args.out)
    check_out(out, args.spec)
    table_files.check_run_files(out, args.rows, args.seeds, table_scenes(overrides))
    out.mkdir(parents=True, exist_ok=True)
    extended = spec is not None and "extends" in spec
    with RunLock(out):        # one table writer per --out (results.json is rewritten)
        if spec is not None:
            write_text_atomic(out / "spec.json", json.dumps(spec, indent=1) + "\n")
        if extended:          # copy the base table's finished rows; wait for the others
            states = extend.prepare(Path(spec["extends"]), out, args.rows, args.seeds)
            for base_row, state in states.items():
                print(state.describe(base_row, spec["extends"]), flush=True)
            args.rows = [r for r in args.rows if states[Row.of(r).base].action != extend.WAIT]
        # without a spec, rows of earlier invocations with the same --out stay in the
        # table; with one, the table is exactly what the spec's runs hold
        saved = out / "results.json"
        results: dict[str, dict[str, dict]] = (read_json(saved, "a results JSON")
                                               if saved.exists() and spec is None else {})
        # seed-major (a partial table covers all rows); with a population, row-major:
        # all seeds of a row train in one program, then are tested, then the next row
        order = ([(seed, row) for row in args.rows for seed in args.seeds] if args.population
                 else [(seed, row) for seed in args.seeds for row in args.rows])
        for seed, name in order:
            row = Row.of(name)
            if args.population and row.base != "random" and seed == args.seeds[0]:
                train_row_population(Row(row.base), args.seeds, out, overrides, extended)
            metrics = (run_tpn(row, seed, out, overrides, tpn_fields, extended) if row.is_tpn
                       else run_one(row, seed, out, overrides, extended))
            metrics = dict(metrics, **pretrain_budget(out, name, seed))
            results.setdefault(name, {})[str(seed)] = metrics
            print(f"{name} seed {seed}: " + ", ".join(f"{m} {100 * metrics[m]:.1f}"
                                                      for m in METRICS), flush=True)
            write_outputs(out, results, spec)
        print(write_outputs(out, results, spec))
        curves = write_curves(out, results)
        if curves:
            print(f"learning curves: {curves}")


if __name__ == "__main__":
    sys.exit(run_cli(main))
