"""The paper's claims, checked on a table's runs: paired differences over seeds, with
intervals, a one-sided paired test and a three-level verdict.

    python experiments/claims.py experiments/results/table_5m            # writes the files
    python experiments/claims.py --check experiments/results/table_5m    # recompute all
    python experiments/claims.py --check experiments/results/before_parity/table_5m
                                             # the table made before network parity

TABLE is a run_table.py output directory (spec.json, runs/, results.json, table.md). The
results are read from the runs' own files (OUT/runs/<row>-s<seed>/test_results.json,
.../tpn/test_<variant>.json): every summary is recomputed from the per-episode outcomes
kept in them and must equal the summary stored beside them. For every claim (row vs
reference row, a sign) and each metric (success, SPL), over the seeds both rows have:

- the paired difference per seed (percentage points), its mean, the sample std (ddof 1);
- a 95% t interval of the mean and a one-sided paired t-test (H1: the claimed sign);
- a 95% bootstrap interval that resamples seeds and, within each seed, test episodes
  (the rows share the seeded episode set, so episodes pair too; 2,000 resamples, fixed
  generator seed);
- the verdict: "holds in every seed", "holds on average (k of n seeds)" or "does not
  hold"; and whether the t interval excludes 0.

provenance.md is the table of which code and which machine made each run, generated from
the runs' provenance.json records (provenance_table).

--check recomputes results.json, table.md and claims.md (and provenance.md, where the
table has one) from the runs' files and exits 1 on any difference (CI runs it on the
committed tables).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run_table  # noqa: E402  (the sibling script: result paths, the table)
from orgnav_jax.errors import read_json, run_cli  # noqa: E402  (the CLIs' error convention)

BOOTSTRAP = 2000
LEVEL = 0.95
METRIC_NAMES = {"success": "success", "spl": "SPL"}


def claims(lr: str, spec: dict | None = None) -> list[tuple[str, str, str, int]]:
    """(claim, row, reference row, sign): the claim holds when sign * (row - ref) > 0.
    With `spec` (a table's), the claims of rows added later (later_claims) are listed
    only where the spec has their row, so the claims.md of a table made before them is
    unchanged, and the pre-registered predictions (predicted_claims) follow where the
    spec's preset has them; without, all later claims and no predictions are."""
    later = [c[:4] for c in later_claims(lr) if spec is None or c[4] in spec["rows"]]
    later += predicted_claims(lr, spec)
    tpn = lambda base, v="tpn": f"{base}+{v}@{lr}"
    return [
        # Table 1
        ("Baseline > Random", "baseline", "random", 1),
        ("Baseline > WE", "baseline", "we", 1),
        ("ORG > Baseline", "org", "baseline", 1),
        ("ORG > D-SP", "org", "dsp", 1),
        ("IL > Baseline", "il", "baseline", 1),
        ("ORG + IL > ORG", "org_il", "org", 1),
        ("Baseline + TPN > Baseline", tpn("baseline"), "baseline", 1),
        ("full model > ORG + IL (w/o TPN)", tpn("org_il"), "org_il", 1),
        # Table 1's meta-learning rows (issue 25: SAVN adapts by a learned loss)
        ("D-SAVN > SAVN", "dsavn", "savn", 1),
        ("D-SAVN > Baseline", "dsavn", "baseline", 1),
        ("full model > D-SAVN", tpn("org_il"), "dsavn", 1),
        # Table 2: ablations of the full model
        ("full model > ORG + TPN (w/o IL)", tpn("org_il"), tpn("org"), 1),
        ("full model > IL + TPN (w/o ORG)", tpn("org_il"), tpn("il"), 1),
        ("IL on every step < IL", "il_all", "il", -1),
        ("IL on failed moves < IL", "il_failed", "il", -1),
        ("TPN on every step < TPN (Baseline)", tpn("baseline", "tpn_all"), tpn("baseline"), -1),
        ("TPN on every step < TPN (ORG + IL)", tpn("org_il", "tpn_all"), tpn("org_il"), -1),
        ("TPN random target < TPN (Baseline)", tpn("baseline", "tpn_random"), tpn("baseline"),
         -1),
        ("TPN random target < TPN (ORG + IL)", tpn("org_il", "tpn_random"), tpn("org_il"), -1),
    ] + later


def later_claims(lr: str) -> list[tuple[str, str, str, int, str]]:
    """Claims added after tables were made, as (claim, row, ref, sign, gate): claims(lr,
    spec) lists one where the spec has the row `gate`. VTNet (issue 43; Du, Yu, Zheng,
    ICLR 2021: 72.2 % success against ORG + TPN's 69.3 in its paper, +2.9); its rows
    pre-train on the expert's actions (run_table.py: the budget is stated under table.md).
    D-SP > Baseline (issue 40, the paper's D-SP: the graph concatenated, not replacing the
    detection map) is gated on vtnet, a row of the tables made since: the before-parity
    tables' dsp was the replacing encoder and keep their claims."""
    tpn = lambda base, v="tpn": f"{base}+{v}@{lr}"
    return [
        ("D-SP > Baseline (paper +3.2)", "dsp", "baseline", 1, "vtnet"),
        ("VTNet > Baseline", "vtnet", "baseline", 1, "vtnet"),
        ("VTNet > full model (ORG + IL + TPN; paper +2.9)", "vtnet", tpn("org_il"), 1,
         "vtnet"),
        ("pre-training helps (VTNet > VTNet without pre-training)", "vtnet",
         "vtnet_scratch", 1, "vtnet"),
        ("VTNet + TPN > VTNet", tpn("vtnet"), "vtnet", 1, tpn("vtnet")),
    ]


def predicted_claims(lr: str, spec: dict | None) -> list[tuple[str, str, str, int]]:
    """The predictions registered for the calibrated benchmark (docs/results.md, "The
    calibrated table: predictions", commit e68b2c8) that no claim above states: listed
    for a table on the `calibrated` preset only."""
    if spec is None or spec["config"].get("scene_preset") != "calibrated":
        return []
    return [("full model > Baseline (paper +12.9)", f"org_il+tpn@{lr}", "baseline", 1),
            ("D-SP > WE", "dsp", "we", 1)]


def t_quantile(p: float, df: int) -> float:
    from scipy import stats
    return float(stats.t.ppf(p, df))


def paired(results: dict, row: str, ref: str, metric: str = "success"):
    """-> (differences in points (n,), seeds) over the seeds both rows have."""
    seeds = sorted(set(results.get(row, {})) & set(results.get(ref, {})), key=int)
    d = np.array([100 * (results[row][s][metric] - results[ref][s][metric]) for s in seeds])
    return d, seeds


def bootstrap_interval(episodes: dict, row: str, ref: str, seeds: list[str], metric: str,
                       resamples: int = BOOTSTRAP, level: float = LEVEL):
    """95% percentile interval (points) of the mean paired difference, resampling seeds
    and, within each drawn seed, episodes; None if a run lacks per-episode outcomes or
    the two rows' episode sets differ in size."""
    diffs = []
    for s in seeds:
        a, b = episodes.get(row, {}).get(s), episodes.get(ref, {}).get(s)
        if a is None or b is None or len(a[metric]) != len(b[metric]):
            return None
        diffs.append(100 * (np.asarray(a[metric], np.float64) -
                            np.asarray(b[metric], np.float64)))
    d = np.stack(diffs)                                   # (n seeds, E episodes)
    n, e = d.shape
    rng = np.random.default_rng(0)
    means = np.empty(resamples)
    for i in range(resamples):
        pick = rng.integers(0, n, n)
        cols = rng.integers(0, e, (n, e))
        means[i] = d[pick[:, None], cols].mean()
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def statistics(d: np.ndarray, sign: int) -> dict:
    """Paired differences (n,) -> mean, sample std, t interval, one-sided p, verdict."""
    n = len(d)
    mean = float(d.mean())
    out = {"n": n, "differences": [round(float(x), 2) for x in d], "mean": mean,
           "std": float(d.std(ddof=1)) if n > 1 else None, "interval": None, "p": None}
    if n > 1:
        se = d.std(ddof=1) / np.sqrt(n)
        half = t_quantile((1 + LEVEL) / 2, n - 1) * se
        out["interval"] = (mean - half, mean + half)
        if se > 0:
            from scipy import stats
            out["p"] = float(stats.t.sf(sign * mean / se, n - 1))
        else:
            out["p"] = 0.0 if sign * mean > 0 else 1.0
    k = int((sign * d > 0).sum())
    out["seeds_holding"] = k
    if k == n:
        out["verdict"] = "holds in every seed"
    elif sign * mean > 0:
        out["verdict"] = f"holds on average ({k} of {n} seeds)"
    else:
        out["verdict"] = "does not hold"
    lo_hi = out["interval"]
    out["excludes_0"] = bool(lo_hi and (lo_hi[0] > 0 or lo_hi[1] < 0))
    return out


def interval_text(iv) -> str:
    return f"[{iv[0]:+.1f}, {iv[1]:+.1f}]" if iv else "-"


def claim_rows(results: dict, episodes: dict, lr: str,
               spec: dict | None = None) -> list[dict]:
    """Every claim's statistics for success and SPL (None where not measured); `spec`:
    the table's (claims)."""
    out = []
    for name, row, ref, sign in claims(lr, spec):
        entry = {"claim": name, "row": row, "ref": ref, "sign": sign}
        for metric in METRIC_NAMES:
            d, seeds = paired(results, row, ref, metric)
            if not seeds:
                entry[metric] = None
                continue
            st = statistics(d, sign)
            st["seeds"] = seeds
            st["bootstrap"] = bootstrap_interval(episodes, row, ref, seeds, metric)
            entry[metric] = st
        out.append(entry)
    return out


def full_model_best(results: dict, lr: str) -> str:
    """Whether ORG + IL + TPN has the highest mean success of the rows on the same seeds."""
    full = f"org_il+tpn@{lr}"
    if full not in results:
        return "The full model (ORG + IL + TPN) is not measured yet.\n"
    seeds = set(results[full])
    means = {row: np.mean([100 * r[s]["success"] for s in seeds]) for row, r in results.items()
             if seeds <= set(r)}
    best = max(means, key=means.get)
    gap = means[full] - max((v for k, v in means.items() if k != full), default=means[full])
    verdict = "the best row" if best == full else f"not the best row (best: {best})"
    return (f"The full model (ORG + IL + TPN) is {verdict} in mean test success over seeds "
            f"{','.join(sorted(seeds, key=int))}: {gap:+.1f} points against the next row.\n")


def table(results: dict, episodes: dict, lr: str, spec: dict | None = None) -> str:
    """claims.md: one line per claim (of the table's `spec`: claims), success and SPL."""
    lines = ["| claim | seeds | success diff (points): mean [95% t interval] | bootstrap "
             "interval | p (one-sided) | verdict | SPL diff: mean [95% t interval] | "
             "SPL verdict |", "|---|---|---|---|---|---|---|---|"]
    for c in claim_rows(results, episodes, lr, spec):
        s, p = c["success"], c["spl"]
        if s is None:
            lines.append(f"| {c['claim']} | not measured | | | | | | |")
            continue
        pval = f"{s['p']:.3f}" if s["p"] is not None else "-"
        zero = ", interval excludes 0" if s["excludes_0"] else ""
        lines.append(
            f"| {c['claim']} | {','.join(s['seeds'])} | {s['mean']:+.1f} "
            f"{interval_text(s['interval'])} | {interval_text(s['bootstrap'])} | {pval} | "
            f"{s['verdict']}{zero} | {p['mean']:+.1f} {interval_text(p['interval'])} | "
            f"{p['verdict']} |")
    return "\n".join(lines) + "\n\n" + full_model_best(results, lr)


def category_groups() -> dict[str, list[str]]:
    """The target categories by their part in the generator's co-occurrence rules:
    anchored small objects (catalog.ANCHORS keys), anchors (what they are placed by, not
    themselves anchored) and the others."""
    from orgnav_jax.constants import CATEGORIES
    from orgnav_jax.scenes.synthetic.catalog import ANCHORS
    anchored = [c for c in CATEGORIES if c in ANCHORS]
    anchors = [c for c in CATEGORIES if c not in ANCHORS and
               any(c in a for a in ANCHORS.values())]
    return {"anchored": anchored, "anchors": anchors,
            "others": [c for c in CATEGORIES if c not in anchored + anchors]}


def per_category(out: Path, row: str = "org", ref: str = "baseline") -> str:
    """Markdown: `row` vs `ref` success per target category and per group
    (category_groups), paired by seed, with 95% t intervals (test split). Every results
    file is read as read_table_dir reads it (its summary must equal its per-episode
    outcomes) and must keep per-episode outcomes."""
    from orgnav_jax.constants import CATEGORIES
    spec = read_spec_of(out)
    for r in (row, ref):
        if r not in spec["rows"]:
            raise ValueError(f"--per-category {r}: not a row of {out / 'spec.json'} "
                             f"(rows: {', '.join(spec['rows'])})")
    docs = {}
    for r in (row, ref):
        for seed in spec["seeds"]:
            path = run_table.existing_results(out, r, seed)
            if path is not None:
                doc = read_results_doc(path)
                if "per_episode" not in doc:
                    raise ValueError(f"{path}: no per-episode outcomes (written before "
                                     "they were kept): --per-category needs them")
                docs.setdefault(r, {})[str(seed)] = doc
    seeds = sorted(set(docs.get(row, {})) & set(docs.get(ref, {})), key=int)
    if not seeds:
        return f"{row} vs {ref}: no seed has both rows yet\n"

    def rate(doc, cats) -> float | None:
        rec = doc["per_episode"]
        idx = {CATEGORIES.index(c) for c in cats}
        hits = [o == 0 for o, t in zip(rec["outcome"], rec["target"]) if t in idx]
        return float(np.mean(hits)) if hits else None

    lines = [f"{row} vs {ref}, test success (points) paired over seeds "
             f"{','.join(seeds)}:", "",
             "| group | category | episodes / seed | " + f"{ref} | {row} | difference: "
             "mean [95% t interval] | verdict |", "|---|---|---|---|---|---|---|"]
    for group, cats in category_groups().items():
        for cat in [*cats, f"all {group}"]:
            members = cats if cat.startswith("all ") else [cat]
            a = [rate(docs[row][s], members) for s in seeds]
            b = [rate(docs[ref][s], members) for s in seeds]
            if any(x is None for x in a + b):
                continue
            n_ep = sum(t in {CATEGORIES.index(c) for c in members}
                       for t in docs[row][seeds[0]]["per_episode"]["target"])
            d = 100 * (np.array(a) - np.array(b))
            st = statistics(d, 1)
            name = f"**{cat}**" if cat.startswith("all ") else cat
            lines.append(f"| {group} | {name} | {n_ep} | {100 * np.mean(b):.1f} | "
                         f"{100 * np.mean(a):.1f} | {st['mean']:+.1f} "
                         f"{interval_text(st['interval'])} | {st['verdict']} |")
    return "\n".join(lines) + "\n"


def compact(results: dict, episodes: dict, lr: str, spec: dict | None = None) -> str:
    """The README's claims table: seeds, mean success difference with its 95% t
    interval, and the verdict (measured claims only)."""
    lines = ["| claim | seeds | success difference, points: mean [95% interval] | verdict |",
             "|---|---|---|---|"]
    for c in claim_rows(results, episodes, lr, spec):
        s = c["success"]
        if s is None:
            continue
        zero = "; interval excludes 0" if s["excludes_0"] else ""
        lines.append(f"| {c['claim']} | {len(s['seeds'])} | {s['mean']:+.1f} "
                     f"{interval_text(s['interval'])} | {s['verdict']}{zero} |")
    return "\n".join(lines) + "\n"


def before_after(out: Path, before: Path) -> str:
    """Markdown, one line per claim measured in both tables: success before -> after
    (mean [95% t interval], seeds), the verdict's level, and "verdict changed" where the
    level (every seed / on average / does not hold) differs. Claims match by name."""
    def measured(table_dir: Path) -> dict[str, dict]:
        spec, results, episodes = read_table_dir(table_dir)
        return {c["claim"]: c["success"] for c in
                claim_rows(results, episodes, lr_tag(spec), spec)
                if c["success"] is not None}
    old, new = measured(before), measured(out)
    level = lambda v: v.split(" (")[0]
    text = lambda s: (f"{s['mean']:+.1f} {interval_text(s['interval'])}, {s['verdict']}"
                      + ("" if " of " in s["verdict"] else f" ({len(s['seeds'])} seeds)"))
    return "\n".join(
        f"- {name}: {text(old[name])} -> {text(s)}"
        + ("; **verdict changed**" if level(old[name]["verdict"]) != level(s["verdict"])
           else "")
        for name, s in new.items() if name in old) + "\n"


def read_results_doc(path: Path) -> dict:
    """A results JSON as api.evaluate writes it, checked: an object with an `overall`
    object of numbers; when it keeps `per_episode` outcomes, the summary recomputed from
    them must equal the stored one. ValueError naming the file otherwise."""
    from orgnav_jax.errors import is_number, read_field, read_object
    from orgnav_jax.evaluation import episodes_from_record, summarize
    doc = read_object(read_json(path, "a results JSON"), path)
    stored = read_object(read_field(doc, "overall", path), f"{path}: field 'overall'")
    bad = [k for k, v in stored.items() if not is_number(v)]
    if bad:
        raise ValueError(f"{path}: field 'overall': expected numbers, got {bad[0]!r}: "
                         f"{stored[bad[0]]!r}")
    if "per_episode" not in doc:
        return doc
    try:
        per = episodes_from_record(read_object(doc["per_episode"],
                                               f"{path}: field 'per_episode'"))
        again = summarize(per)
    except (KeyError, TypeError, IndexError, ValueError) as err:
        raise ValueError(f"{path}: field 'per_episode' is malformed "
                         f"({type(err).__name__}: {err})") from None
    bad = [k for k in stored if k in again and
           not np.isclose(stored[k], again[k], rtol=0, atol=1e-12)]
    if bad or set(again) != set(stored):
        raise ValueError(f"{path}: the stored summary differs from its per-episode "
                         f"outcomes in {bad or 'its keys'}")
    doc["_per"] = per
    return doc


def read_results(path: Path) -> tuple[dict, dict | None]:
    """A results JSON -> (its stored overall summary, its per-episode arrays: success,
    spl, ... (E,) each; None for results written before per-episode outcomes were kept).
    The summary is recomputed from the per-episode outcomes and must equal the stored one
    (read_results_doc: ValueError naming the file otherwise)."""
    doc = read_results_doc(path)
    return doc["overall"], doc.get("_per")


def read_spec_of(out: Path) -> dict:
    """TABLE/spec.json of a run_table.py output directory (ValueError naming what is
    missing)."""
    if not out.is_dir():
        raise ValueError(f"{out}: not a directory (expected a run_table.py output "
                         "directory with spec.json)")
    spec_path = out / "spec.json"
    if not spec_path.is_file():
        raise ValueError(f"{spec_path}: missing (run_table.py --spec writes it)")
    return run_table.read_spec(spec_path)


def read_table_dir(out: Path) -> tuple[dict, dict, dict]:
    """A table directory's spec and, from its runs' files (read_results: every summary
    checked against its per-episode outcomes), results[row][seed] = overall summary and
    episodes[row][seed] = per-episode arrays (success, spl); results written before
    per-episode outcomes were kept are taken as stored, without a bootstrap."""
    spec = read_spec_of(out)
    results: dict = {}
    episodes: dict = {}
    for row in spec["rows"]:
        for seed in spec["seeds"]:
            path = run_table.existing_results(out, row, seed)
            if path is None:
                continue
            stored, per = read_results(path)
            if per is not None:
                episodes.setdefault(row, {})[str(seed)] = {
                    "success": per["success"], "spl": per["spl"]}
            # a pre-trained row's extra budget beside its metrics (run_table.py)
            results.setdefault(row, {})[str(seed)] = dict(
                stored, **run_table.pretrain_budget(out, row, seed))
    return spec, results, episodes


def lr_tag(spec: dict) -> str:
    """The test-time learning rate tag of the table's TPN rows (the first @LR)."""
    tags = [r.partition("@")[2] for r in spec["rows"] if "@" in r]
    return tags[0] if tags else "1e-3"


def table_run_dirs(out: Path, spec: dict) -> list[Path]:
    """The run directories a table's rows read, in the spec's order, each once: a row's
    run (a TPN row's: its base run's tpn/) and, for a pre-trained row, the seed's
    pre-training before it."""
    dirs: list[Path] = []
    for row in spec["rows"]:
        base = row.partition("+")[0]
        for seed in spec["seeds"]:
            found = [run_table.results_path(out, row, seed).parent]
            if base in run_table.PRETRAIN_ROWS:
                found.insert(0, run_table.pretrain_dir(out, base, seed))
            dirs += [d for d in found if d not in dirs]
    return dirs


PROVENANCE_HEADER = """# Which code and which machine made each run

Generated by `python experiments/claims.py TABLE` from the runs' `provenance.json` records
(`--check` recomputes it). A record is one process that trained, resumed or evaluated a
run; runs with the same records are one line. `ROW/tpn` is the TPN (stage 2) of row ROW's
run, which every `ROW+VARIANT@LR` row evaluates; `ROW-pretrain` a pre-training. code: the
commit the process started from (`ORGNAV_CODE` for a copy of the tree on another machine);
uncommitted: whether tracked code under orgnav_jax/ or experiments/ differed from it (what
it counted is in docs/results.md); date: of the record, UTC.

"""


def seed_ranges(seeds: list[str]) -> str:
    """["0", "1", "2", "4"] -> "0-2, 4" (non-numbers after the numbers, as given)."""
    nums = sorted(int(x) for x in seeds if x.isdigit())
    parts: list[str] = []
    for n in nums:
        if parts and n == last + 1:
            parts[-1] = f"{parts[-1].split('-')[0]}-{n}"
        else:
            parts.append(str(n))
        last = n
    return ", ".join(parts + [x for x in seeds if not x.isdigit()])


def what_was_done(dids: list[str]) -> str:
    """A group's records' `did` texts, one clause each, with what they tested gathered at
    the end: ["trained the TPN, tested tpn@1e-4", "reloaded it, tested tpn_all@1e-4"] ->
    "trained the TPN; reloaded it; tested tpn@1e-4, tpn_all@1e-4"."""
    actions: list[str] = []
    tested: list[str] = []
    any_test = False
    for did in dids:
        action, sep, what = did.partition("tested")
        action = action.strip().rstrip(",").strip()
        any_test = any_test or bool(sep)
        actions += [action] if action and action not in actions else []
        what = what.strip()
        tested += [what] if what and what not in tested else []
    return "; ".join(actions + (["tested " + ", ".join(tested) if tested else "tested"]
                                if any_test else []))


def provenance_table(out: Path) -> str:
    """provenance.md: for each group of runs (a row's seeds; ROW/tpn; ROW-pretrain) and
    each distinct record (code, uncommitted changes, device, CPU, jax), the seeds, what
    the processes did and their dates; finished runs without records say so (a run still
    training, with neither, is left out). ValueError naming a
    provenance.json that cannot be read."""
    spec = read_spec_of(out)
    groups: dict[tuple, dict] = {}
    for run in table_run_dirs(out, spec):
        if not run.is_dir():
            continue                                    # not run yet
        if not (run / "provenance.json").exists() and not any(run.glob("test*.json")):
            continue                                    # still training: nothing recorded
        top, *rest = run.relative_to(out / "runs").parts
        match = re.fullmatch(r"(.+)-s(\d+)", top)
        name, seed = (match[1], match[2]) if match else (top, "-")
        name = "/".join([name, *rest])
        records = run_table.read_provenance(run / "provenance.json")
        for rec in records or [None]:
            sig = (None if rec is None else
                   (str(rec.get("code", "?"))[:7], rec.get("uncommitted_changes"),
                    rec.get("device", "not recorded"), rec.get("cpu", "?"),
                    rec.get("jax", "?")))
            entry = groups.setdefault((name, sig), {"seeds": [], "did": [], "dates": []})
            if seed not in entry["seeds"]:
                entry["seeds"].append(seed)
            did = "no provenance.json" if rec is None else \
                re.sub(r"-s\d+\b", "-sS", str(rec.get("did", "?")))
            date = "" if rec is None else str(rec.get("time", ""))[:10]
            entry["did"] += [did] if did not in entry["did"] else []
            entry["dates"] += [date] if date and date not in entry["dates"] else []
    lines = ["| runs | seeds | what the processes did | code | uncommitted | device | CPU "
             "| jax | date |", "|---|---|---|---|---|---|---|---|---|"]
    for (name, sig), e in groups.items():
        seeds = seed_ranges(e["seeds"])
        dates = sorted(e["dates"])
        date = "" if not dates else dates[0] if len(dates) == 1 else \
            f"{dates[0]} to {dates[-1]}"
        code, dirty, device, cpu, jax_version = sig or ("-",) * 5
        dirty = "-" if sig is None else "yes" if dirty else "no"
        lines.append(f"| {name} | {seeds} | {what_was_done(e['did'])} | {code} | {dirty} | "
                     f"{device} | {cpu} | {jax_version} | {date} |")
    return PROVENANCE_HEADER + "\n".join(lines) + "\n"


def expected_files(out: Path) -> dict[str, str]:
    """results.json, table.md, claims.md and provenance.md as the runs' files give them."""
    spec, results, episodes = read_table_dir(out)
    return {"results.json": json.dumps(results, indent=1),
            "table.md": run_table.table_text(results),
            "claims.md": table(results, episodes, lr_tag(spec), spec),
            "provenance.md": provenance_table(out)}


# tables made before provenance.md existed do not have it: --check compares it where present
OPTIONAL_FILES = ("provenance.md",)


def write_all(out: Path) -> dict[str, str]:
    """Write results.json, table.md, claims.md and provenance.md of `out` from its runs'
    files (all read and checked first: a bad file writes nothing), each atomically."""
    files = expected_files(out)
    for name, text in files.items():
        tmp = out / f".{name}.tmp"
        tmp.write_text(text)
        tmp.replace(out / name)
    return files


def check(out: Path) -> list[str]:
    """The files of `out` that differ from what its runs give (empty: all agree)."""
    bad = []
    for name, text in expected_files(out).items():
        path = out / name
        if not path.exists() and name in OPTIONAL_FILES:
            continue
        if not path.exists():
            bad.append(f"{path}: missing")
        elif name.endswith(".json"):
            if read_json(path) != json.loads(text):
                bad.append(f"{path}: differs from the runs' test results")
        elif path.read_text() != text:
            bad.append(f"{path}: differs from what the runs' files give")
    return bad


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("table", help="a run_table.py output directory (with spec.json)")
    ap.add_argument("--per-category", nargs=2, metavar=("ROW", "REF"), default=None,
                    help="print ROW vs REF success per target category and group "
                         "(anchored small objects, anchors, others), e.g. org baseline")
    ap.add_argument("--compact", action="store_true",
                    help="print the README's short claims table (measured claims only)")
    ap.add_argument("--before", metavar="TABLE", default=None,
                    help="print each claim measured in both tables as before (TABLE) -> "
                         "after (this table), e.g. experiments/results/before_parity/table_5m")
    ap.add_argument("--check", action="store_true",
                    help="recompute results.json, table.md, claims.md (and provenance.md "
                         "where present) from the runs' files; exit 1 on any difference, "
                         "write nothing")
    args = ap.parse_args(argv)
    out = Path(args.table)
    read_spec_of(out)                     # a missing or bad table: one line, nothing written
    if args.per_category:
        print(per_category(out, *args.per_category))
        return 0
    if args.compact:
        spec, results, episodes = read_table_dir(out)
        print(compact(results, episodes, lr_tag(spec), spec))
        return 0
    if args.before:
        print(before_after(out, Path(args.before)), end="")
        return 0
    if args.check:
        bad = check(out)
        for line in bad:
            print(f"check failed: {line}", file=sys.stderr)
        if not bad:
            names = ["results.json", "table.md", "claims.md"] + \
                [n for n in OPTIONAL_FILES if (out / n).exists()]
            print(f"{out}: {', '.join(names)} agree with the runs' files")
        return 1 if bad else 0
    print(write_all(out)["claims.md"])
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
