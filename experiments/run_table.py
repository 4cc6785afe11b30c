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
resumed when it has checkpoints: rerun the same command after an interruption), is
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
import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

from orgnav_jax.constants import DEFAULT_SCENE_PRESET
from orgnav_jax import api
from orgnav_jax.train import PRETRAIN_PIPELINES
from orgnav_jax.errors import INT32_MAX, is_int, read_json, run_cli, shown
from orgnav_jax.training.run_dir import RunLock, is_run_dir
from orgnav_jax.training.config import TABLE_ROWS, VTNET_PRESETS, add_config_arguments, \
    get_config, overrides_from_args

METRICS = ("success", "spl", "success_L5", "spl_L5")
# failure analysis columns: (result key, column label, scale); see docs/evaluation.md
FAILURE_METRICS = (("wrong_done", "wrong Done", 100), ("timeout", "timeout", 100),
                   ("revisits", "revisits/ep", 1), ("failed_moves", "failed moves/ep", 1))
# test-time variants of a TPN row (TPNConfig fields)
TPN_VARIANTS = {"tpn": {}, "tpn_all": {"when": "all"}, "tpn_random": {"target": "random"},
                "tpn_cosine": {"deadlock": "cosine", "placement": "state"},   # (release: visited only)
                "tpn_train_mode": {"tpn_train_mode": True}}   # the release's dropout confound


# the rows: the Tables' presets and VTNet's (issue 43)
ROWS = {**TABLE_ROWS, **VTNET_PRESETS}
# rows whose A2C run starts from a supervised pre-training of the seed, as `--preset
# vtnet` does: the CLI's list (train.PRETRAIN_PIPELINES), in OUT/runs/<row>-pretrain-s<seed>
PRETRAIN_ROWS = PRETRAIN_PIPELINES


SPEC_KEYS = {"out": str, "rows": list, "seeds": list, "config": dict, "tpn": dict}
SPEC_OPTIONAL = {"about": str, "population": bool}


def results_path(out: Path, row: str, seed: int | str) -> Path:
    """Where a row's test results for one seed live: OUT/runs/ROW-sS/test_results.json, or
    for BASE+VARIANT[@LR] OUT/runs/BASE-sS/tpn/test_VARIANT[@LR].json."""
    base, plus, variant = row.partition("+")
    run_dir = out / "runs" / f"{base}-s{seed}"
    return run_dir / "tpn" / f"test_{variant}.json" if plus else run_dir / "test_results.json"


def existing_results(out: Path, row: str, seed: int | str) -> Path | None:
    """results_path(out, row, seed) if that file exists, None if it does not; a path
    that cannot be looked at (a symbolic link loop, a link that leads nowhere, no
    permission) is a ValueError naming it, never taken as "not run yet" (a run of the
    table would otherwise drop out of it without a word)."""
    path = results_path(out, row, seed)
    try:
        path.stat()
        return path
    except FileNotFoundError:
        pass
    except OSError as err:
        raise ValueError(f"{path}: cannot be read ({err.strerror}; a symbolic link loop?)"
                         ) from None
    p = path
    while p != out and p != p.parent:         # absent, unless a link on the way is broken
        if p.is_symlink() and not p.exists():
            raise ValueError(f"{p}: a symbolic link that leads nowhere")
        p = p.parent
    return None


def read_provenance(path: Path) -> list:
    """RUN_DIR/provenance.json: a list of per-process records ([] when absent); ValueError
    naming the file otherwise."""
    if not path.exists():
        return []
    records = read_json(path, "a provenance JSON")
    if not isinstance(records, list) or not all(isinstance(x, dict) for x in records):
        raise ValueError(f"{path}: expected a list of provenance records")
    return records


def provenance(top: Path | None = None) -> dict:
    """What made a run: the code version (of the checkout `top`, default this one), the
    machine, the time. "uncommitted_changes": tracked code under orgnav_jax/ or
    experiments/ differs from the commit; the tables' own files (experiments/results/,
    which a running campaign rewrites) do not count, nor do file modes (a copied tree
    can lose an executable bit). "code": ORGNAV_CODE where set (a copy of the tree on
    another machine: experiments/gpu_streams/run.sh sets it to the commit of the clean
    tree it copied), else HEAD. "device": what JAX ran on."""
    top = top or Path(__file__).resolve().parents[1]
    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=top, capture_output=True,
                                  text=True).stdout.strip()
        except FileNotFoundError:                  # no git on the machine
            return ""
    cpu = next((line.split(":", 1)[1].strip() for line in
                Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor()) \
        if Path("/proc/cpuinfo").exists() else platform.processor()
    import jax
    device = jax.devices()[0]
    return {"code": os.environ.get("ORGNAV_CODE") or git("rev-parse", "HEAD") or "unknown",
            "uncommitted_changes": bool(git("-c", "core.fileMode=false", "status",
                                            "--porcelain", "--untracked-files=no",
                                            "--", "orgnav_jax", "experiments",
                                            ":(exclude)experiments/results")),
            "cpu": cpu, "device": f"{device.platform} {device.device_kind}",
            "jax": jax.__version__, "python": platform.python_version(),
            "time": now()}


def now() -> str:
    """The time of a provenance record: UTC, to the second, ISO 8601."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


_STARTED: dict = {}      # provenance() when this process started: the code it runs


def record_provenance(run_dir: Path, what: str) -> None:
    """Append this process and what it did to RUN_DIR/provenance.json (after the work: a
    fresh run directory must be empty when training starts): the code version and
    machine of the process as it started ("code", "uncommitted_changes": what ran),
    and the time of the record."""
    path = run_dir / "provenance.json"
    records = read_provenance(path)
    run_dir.mkdir(parents=True, exist_ok=True)
    started = _STARTED or provenance()
    record = dict(started, started=started["time"], time=now(), did=what)
    tmp = run_dir / ".provenance.json.tmp"
    tmp.write_text(json.dumps(records + [record], indent=1))
    tmp.replace(path)


def check_run_files(out: Path, rows: list[str], seeds: list[int]) -> None:
    """Before any work: every run's results and provenance.json that exist can be read
    (a truncated provenance.json would otherwise stop the table after an evaluation
    wrote its results)."""
    for row in rows:
        for seed in seeds:
            results = existing_results(out, row, seed)
            if results is not None:
                read_results_overall(results)
            base_dir = out / "runs" / f"{row.partition('+')[0]}-s{seed}"
            read_provenance(base_dir / "provenance.json")
            if row.partition("+")[0] in PRETRAIN_ROWS:
                read_provenance(pretrain_dir(out, row.partition("+")[0], seed) /
                                "provenance.json")
            if "+" in row:
                read_provenance(base_dir / "tpn" / "provenance.json")


def read_results_overall(path: Path) -> dict:
    """The `overall` summary of a results JSON (ValueError naming the file)."""
    doc = read_json(path, "a results JSON")
    if not isinstance(doc, dict) or not isinstance(doc.get("overall"), dict):
        raise ValueError(f"{path}: expected a results JSON with an 'overall' object")
    return doc["overall"]


def run_tpn(row: str, seed: int, out: Path, overrides: dict, tpn_fields: dict) -> dict:
    """BASE+VARIANT: train (or reuse) the base row and its TPN, evaluate the variant."""
    from orgnav_jax.tpn.config import get_tpn_config
    base, variant = row.split("+")
    variant, _, lr = variant.partition("@")
    run_one(base, seed, out, overrides)
    results = results_path(out, row, seed)
    tpn_dir = results.parent
    if existing_results(out, row, seed) is not None:
        return read_results_overall(results)
    cfg = get_tpn_config(**tpn_fields, base_dir=str(tpn_dir.parent), seed=seed,
                         run_dir=str(tpn_dir))
    # trains, continues an interrupted run, or (finished) only reloads it
    resumed = is_run_dir(tpn_dir)
    api.train_tpn(cfg, resume=resumed, progress=sys.stderr.isatty())
    test_time = dict(TPN_VARIANTS[variant], **({"tpn_lr": float(lr)} if lr else {}))
    metrics = api.evaluate_run(tpn_dir, "test", out=results, progress=False,
                               **test_time)["overall"]
    record_provenance(tpn_dir, f"{'finished or reloaded' if resumed else 'trained'} the "
                               f"TPN, tested {variant}{'@' + lr if lr else ''}")
    return metrics


def pretrain_dir(out: Path, row: str, seed: int | str) -> Path:
    """Where a PRETRAIN_ROWS row's seed is pre-trained: OUT/runs/ROW-pretrain-sS (the
    directory `--preset vtnet --seeds` uses for RUN_DIR = OUT/runs/ROW)."""
    return out / "runs" / f"{row}-pretrain-s{seed}"


def pretrain_seed(row: str, seed: int, out: Path, overrides: dict) -> Path:
    """The pre-training of a PRETRAIN_ROWS row's seed (api.pretrain_for the row's config,
    as `--preset vtnet` makes it): trained, resumed when partial, reused without work
    when finished -> its directory (the A2C run's `pretrained`)."""
    pre = pretrain_dir(out, row, seed)
    resumed = is_run_dir(pre)
    cfg = get_config(row, **{**overrides, "seed": seed})
    if api.pretrain_for(cfg, pre, progress=sys.stderr.isatty()):
        record_provenance(pre, f"{'resumed and finished' if resumed else 'trained'} the "
                               f"pre-training ({cfg.pretrain_samples:,} samples)")
    return pre


def pretrain_budget(out: Path, row: str, seed: int | str) -> dict:
    """What a row's seed got on top of the table's budget: for a row of PRETRAIN_ROWS
    (or a TPN row on one) its pre-training's samples (whole batches), batch and best val
    accuracy (from the pre-training's config.json and metrics.jsonl); {} for other rows
    and where the pre-training is not there."""
    from orgnav_jax.training.pretrain import load_pretrain_config
    from orgnav_jax.training.run_dir import read_metrics
    base = row.partition("+")[0]
    pre = pretrain_dir(out, base, seed)
    if base not in PRETRAIN_ROWS or not is_run_dir(pre):
        return {}
    cfg = load_pretrain_config(pre)
    val = [r["accuracy"] for r in read_metrics(pre, "samples", skip_broken=True)
           if r["kind"] == "val" and "accuracy" in r]
    return {"pretrain_samples": cfg.total_samples,
            "pretrain_batch": cfg.pretrain_batch,
            **({"pretrain_val_accuracy": max(val)} if val else {})}


def run_one(row: str, seed: int, out: Path, overrides: dict) -> dict:
    """Train (or resume, or skip) one row and seed -> its test metrics. Row `random`:
    the random policy on the same test episodes, its actions sampled with `seed`."""
    results = results_path(out, row, seed)
    run_dir = results.parent
    if existing_results(out, row, seed) is not None:
        return read_results_overall(results)
    if row == "random":
        metrics = api.evaluate_policy(
            "random", "test", overrides.get("scene_preset", DEFAULT_SCENE_PRESET),
            scenes_dir=overrides.get("scenes_dir"), seed=seed, out=results,
            progress=False)["overall"]
        record_provenance(run_dir, "tested")
        return metrics
    pre = pretrain_dir(out, row, seed) if row in PRETRAIN_ROWS else None
    cfg = get_config(row, **{**overrides, "seed": seed, "run_dir": str(run_dir),
                             **({"pretrained": str(pre)} if pre else {})})
    resumed = is_run_dir(run_dir)
    if pre and not resumed:          # once the A2C run has started, its start is fixed
        pretrain_seed(row, seed, out, overrides)
    api.train(cfg, resume=resumed, progress=sys.stderr.isatty())
    metrics = api.test_run(run_dir, progress=False)["overall"]
    record_provenance(run_dir, f"{'resumed and finished' if resumed else 'trained'}"
                               f"{f' from {pre.name}' if pre else ''}, tested")
    return metrics


def train_row_population(row: str, seeds: list[int], out: Path, overrides: dict) -> None:
    """Train the seeds of navigation row `row` that lack test results in one program
    (OUT/runs/<row>-s<seed>); seeds whose runs were started separately are left to
    run_one (a population resumes only runs at a common checkpoint), as are SAVN rows.
    A PRETRAIN_ROWS row pre-trains its seeds first, one by one (pretrain_seed), and
    seed S starts from OUT/runs/<row>-pretrain-sS."""
    todo = [s for s in seeds
            if not (out / "runs" / f"{row}-s{s}" / "test_results.json").exists()]
    started = [is_run_dir(out / "runs" / f"{row}-s{s}") for s in todo]
    pre = {"pretrained": str(out / "runs" / f"{row}-pretrain")} if row in PRETRAIN_ROWS \
        else {}                          # train_seeds: seed S's is <pretrained>-sS
    cfg = get_config(row, **{**overrides, "run_dir": str(out / "runs" / row), **pre})
    if len(todo) < 2 or (any(started) and not all(started)) or cfg.savn:
        return                          # SAVN trains one seed per program (docs/savn.md)
    if pre and not all(started):
        for s in todo:
            pretrain_seed(row, s, out, overrides)
    api.train_seeds(cfg, todo, resume=all(started), progress=sys.stderr.isatty())
    for s in todo:
        record_provenance(out / "runs" / f"{row}-s{s}",
                          f"trained in one program with seeds {' '.join(map(str, todo))}"
                          f"{f' from {row}-pretrain-s{s}' if pre else ''}")


def row_name(text: str) -> str:
    """Validate a --rows entry: ROW (a ROWS name or random), or BASE+VARIANT[@LR]."""
    base, plus, variant = text.partition("+")
    variant, at, lr = variant.partition("@")
    ok = (base in ROWS or (base == "random" and not plus)) and \
        (not plus or variant in TPN_VARIANTS) and (plus or not at)
    try:
        ok = ok and (not at or float(lr) >= 0)
    except ValueError:
        ok = False
    if not ok:
        raise argparse.ArgumentTypeError(
            f"unknown row {text!r}: expected one of {sorted(ROWS)}, or BASE+VARIANT"
            f"[@LR] with VARIANT in {sorted(TPN_VARIANTS)}")
    if plus and ROWS[base].get("savn"):
        raise argparse.ArgumentTypeError(f"row {text!r}: a SAVN run cannot be a TPN base "
                                         "(docs/savn.md)")
    return text


def sample_std(v: np.ndarray) -> float:
    """The sample standard deviation (ddof 1); 0 for a single value."""
    return float(v.std(ddof=1)) if len(v) > 1 else 0.0


def paired_gain(results: dict, row: str) -> str:
    """A TPN row's success minus its base row's, per seed: 'mean ± sample std' (percent
    points), or '' for rows without a base or without shared seeds."""
    base = row.partition("+")[0]
    seeds = sorted(set(results[row]) & set(results.get(base, {}))) if "+" in row else []
    if not seeds:
        return ""
    d = 100 * np.array([results[row][s]["success"] - results[base][s]["success"]
                        for s in seeds])
    return f"{d.mean():+.1f} ± {sample_std(d):.1f}"


def mean_std(by_seed: dict[str, dict], key: str, scale: float = 100.0) -> str:
    """'mean ± sample std' of one metric over seeds, or '-' where a seed's results lack
    it (results of runs made before the metric existed)."""
    if not by_seed or any(key not in r for r in by_seed.values()):
        return "-"
    v = scale * np.array([r[key] for r in by_seed.values()], np.float64)
    return f"{v.mean():.1f} ± {sample_std(v):.1f}"


def table_text(results: dict[str, dict[str, dict]]) -> str:
    """results[row][seed] = metrics -> markdown table of mean ± sample std over seeds:
    METRICS in percent; TPN rows also show their success gain over their base row,
    paired by seed; then the failure analysis (FAILURE_METRICS: wrong Done and timeout
    in percent of episodes, revisits and failed moves per episode; '-' for older
    results). Rows whose seeds were pre-trained (pretrain_budget) are marked † and their
    pre-training's budget is stated under the table (pretrain_notes)."""
    head = ["row", "seeds", "Success", "SPL", "Success (L>=5)", "SPL (L>=5)",
            "gain vs base"] + [label for _, label, _ in FAILURE_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row, by_seed in results.items():
        cells = [mean_std(by_seed, m) for m in METRICS] + [paired_gain(results, row)]
        cells += [mean_std(by_seed, k, scale) for k, _, scale in FAILURE_METRICS]
        mark = " †" if any("pretrain_samples" in r for r in by_seed.values()) else ""
        lines.append(f"| {row}{mark} | {len(by_seed)} | " + " | ".join(cells) + " |")
    notes = pretrain_notes(results)
    return "\n".join(lines) + "\n" + ("\n" + "\n".join(notes) + "\n" if notes else "")


def pretrain_notes(results: dict[str, dict[str, dict]]) -> list[str]:
    """One line per row marked † in table_text: its pre-training's budget per seed (the
    pretrain_budget fields of its results), extra supervision the other rows lack."""
    out = []
    for row, by_seed in results.items():
        got = {s: r for s, r in by_seed.items() if "pretrain_samples" in r}
        if not got:
            continue
        span = lambda key: "-".join(f"{v:,}" for v in sorted({r[key] for r in got.values()}))
        acc = {s: r for s, r in got.items() if "pretrain_val_accuracy" in r}
        out.append(f"† {row}: before the table's A2C budget, each seed's visual transformer "
                   f"was pre-trained with supervision of the expert's actions on "
                   f"{span('pretrain_samples')} (state, target) samples (batches of "
                   f"{span('pretrain_batch')}; best val accuracy "
                   f"{mean_std(acc, 'pretrain_val_accuracy')} %, {len(got)} seeds): "
                   "supervision the other rows do not get.")
    return out


def write_table(out: Path, results: dict[str, dict[str, dict]]) -> str:
    """OUT/table.md (table_text) and OUT/results.json (results[row][seed] = overall),
    each written atomically."""
    text = table_text(results)
    for name, body in (("table.md", text), ("results.json", json.dumps(results, indent=1))):
        tmp = out / f".{name}.tmp"
        tmp.write_text(body)
        tmp.replace(out / name)
    return text


def write_outputs(out: Path, results: dict, spec: dict | None) -> str:
    """The table files: with a spec, results.json, table.md, claims.md and provenance.md
    recomputed from the runs' files (claims.py); without, write_table. -> table.md's text."""
    if spec is None:
        return write_table(out, results)
    from claims import write_all          # the sibling script (it imports this one)
    return write_all(out)["table.md"]


def read_spec(path: str | Path) -> dict:
    """A table spec (JSON: out, rows, seeds, config, tpn) -> dict; ValueError naming the
    file and the field otherwise."""
    if Path(path).is_dir():
        raise ValueError(f"table spec {path}: a directory, expected a JSON file")
    try:
        spec = json.loads(Path(path).read_text())
    except ValueError as err:
        raise ValueError(f"table spec {path}: not JSON ({err})") from None
    if not isinstance(spec, dict):
        raise ValueError(f"table spec {path}: expected a JSON object")
    for key, kind in SPEC_KEYS.items():
        if key not in spec or not isinstance(spec[key], kind):
            raise ValueError(f"table spec {path}: field {key!r} missing or not a "
                             f"{kind.__name__}")
    unknown = sorted(set(spec) - set(SPEC_KEYS) - set(SPEC_OPTIONAL))
    if unknown:
        raise ValueError(f"table spec {path}: unknown field(s) {unknown}")
    for key, kind in SPEC_OPTIONAL.items():
        if key in spec and not isinstance(spec[key], kind):
            raise ValueError(f"table spec {path}: field {key!r} is not a {kind.__name__}")
    if not spec["rows"]:
        raise ValueError(f"table spec {path}: field 'rows': expected at least one row")
    try:
        for row in spec["rows"]:
            if not isinstance(row, str):
                raise argparse.ArgumentTypeError(f"expected row names (strings), got {row!r}")
            row_name(row)
    except argparse.ArgumentTypeError as err:
        raise ValueError(f"table spec {path}: field 'rows': {err}") from None
    if not spec["seeds"] or not all(is_int(x) and 0 <= x <= INT32_MAX for x in spec["seeds"]):
        raise ValueError(f"table spec {path}: field 'seeds': expected integers >= 0, got "
                         f"{shown(spec['seeds'])}")
    for key in ("rows", "seeds"):
        if len(set(spec[key])) != len(spec[key]):
            raise ValueError(f"table spec {path}: field {key!r}: an entry appears twice")
    if not spec["out"]:
        raise ValueError(f"table spec {path}: field 'out': expected a directory, got ''")
    get_config("baseline", **spec["config"])          # names a bad field or value
    from orgnav_jax.tpn.config import get_tpn_config
    get_tpn_config(base_dir="runs/x", **spec["tpn"])
    return spec


def write_curves(out: Path, results: dict[str, dict[str, dict]]) -> Path | None:
    """OUT/curves.png: val success and SPL against env steps (mean and min-max band over
    seeds) of the rows that train a navigation model (TPN rows have no val curve of
    their own). Never ends a sweep: a missing matplotlib or metrics.jsonl is a warning."""
    runs = [out / "runs" / f"{row}-s{seed}" for row, by_seed in results.items()
            if "+" not in row for seed in by_seed]
    runs = [r for r in runs if (r / "metrics.jsonl").exists()]
    if not runs:
        return None
    try:
        from orgnav_jax.plots import plot_curves
        path = out / "curves.png"
        plot_curves(runs, path, quiet=True)
        return path
    except Exception as err:                    # noqa: BLE001 (curves are optional)
        print(f"warning: no learning curves ({type(err).__name__}: {err})", file=sys.stderr)
        return None


# the files run_table.py (re)writes in --out (claims.py too, with a spec)
TABLE_FILES = ("spec.json", "results.json", "table.md", "claims.md", "provenance.md",
               "curves.png")


def check_out(out: Path, spec_path: str | None) -> None:
    """--out must be new, or a table run_table.py made (it holds runs/ or a results.json
    of rows and seeds), or hold none of the table files it rewrites (TABLE_FILES): a
    folder with the user's own spec.json or table.md is refused before anything is
    written; so is a spec that lies at OUT/spec.json, which the table would replace.
    Other files in --out are never touched."""
    if not out.exists():
        return
    if not out.is_dir():
        raise ValueError(f"--out {out}: not a directory")
    if spec_path is not None and (out / "spec.json").exists() and \
            Path(spec_path).resolve() == (out / "spec.json").resolve():
        raise ValueError(f"--spec {spec_path}: lies at OUT/spec.json, which the table "
                         "rewrites: keep the spec outside its output directory")
    saved = out / "results.json"
    if saved.exists():
        doc = read_json(saved, "a results JSON")
        if not (isinstance(doc, dict) and all(
                isinstance(v, dict) and all(isinstance(r, dict) for r in v.values())
                for v in doc.values())):
            raise ValueError(f"--out {out}: its results.json is not a table's "
                             "(results[row][seed] = metrics): not overwritten; choose a "
                             "new directory")
        return
    if (out / "runs").is_dir():
        return
    present = [name for name in TABLE_FILES if (out / name).exists() or
               (out / name).is_symlink()]
    if present:
        raise ValueError(f"--out {out}: holds {', '.join(present)} that run_table.py did "
                         "not write (no runs/, no results.json): choose a new directory "
                         "(nothing was written)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    rows = sorted(ROWS) + [f"{b}+{v}" for b in sorted(ROWS) for v in TPN_VARIANTS]
    ap.add_argument("--rows", nargs="+", default=["baseline", "il", "org", "org_il", "il_all"],
                    type=row_name, metavar="ROW",
                    help="rows: " + ", ".join(rows) + " (TPN rows may end in @LR)")
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
    _STARTED.update(provenance())          # at start: the code this process loaded
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
    check_run_files(out, args.rows, args.seeds)
    out.mkdir(parents=True, exist_ok=True)
    with RunLock(out):        # one table writer per --out (results.json is rewritten)
        if spec is not None:
            (out / "spec.json").write_text(json.dumps(spec, indent=1) + "\n")
        # without a spec, rows of earlier invocations with the same --out stay in the
        # table; with one, the table is exactly what the spec's runs hold
        saved = out / "results.json"
        results: dict[str, dict[str, dict]] = (read_json(saved, "a results JSON")
                                               if saved.exists() and spec is None else {})
        # seed-major (a partial table covers all rows); with a population, row-major:
        # all seeds of a row train in one program, then are tested, then the next row
        order = ([(seed, row) for row in args.rows for seed in args.seeds] if args.population
                 else [(seed, row) for seed in args.seeds for row in args.rows])
        for seed, row in order:
            base = row.partition("+")[0]
            if args.population and base != "random" and seed == args.seeds[0]:
                train_row_population(base, args.seeds, out, overrides)
            metrics = (run_tpn(row, seed, out, overrides, tpn_fields) if "+" in row
                       else run_one(row, seed, out, overrides))
            metrics = dict(metrics, **pretrain_budget(out, row, seed))
            results.setdefault(row, {})[str(seed)] = metrics
            print(f"{row} seed {seed}: " + ", ".join(f"{m} {100 * metrics[m]:.1f}"
                                                      for m in METRICS), flush=True)
            write_outputs(out, results, spec)
        print(write_outputs(out, results, spec))
        curves = write_curves(out, results)
        if curves:
            print(f"learning curves: {curves}")


if __name__ == "__main__":
    sys.exit(run_cli(main))
