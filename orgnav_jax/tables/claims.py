"""The paper's claims, checked on a table's runs (claims.md; docs/results.md, "The
claims"): each claim is a row against a reference row with a sign; for success and SPL,
over the seeds both rows have, the paired difference per seed with its t interval,
bootstrap interval, one-sided p and three-level verdict (stats.statistics).

    claims(lr, spec)            the claims of a table (its spec decides the later ones)
    claims_table(...)           claims.md;  compact(...) the README's short form
    not_converged_note(...)     claims.md's note on rows the convergence rule has not passed
    before_after(out, before)   each claim in two tables, and whether its verdict changed
    per_category(out, row, ref) a row against another per target category

To add a claim: a line in `claims` (a claim of the paper's tables), `later_claims` (one
whose row came after tables were made: gated on a row, so older tables' claims.md stay
as they are) or `predicted_claims` (a registered prediction of the calibrated tables).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES
from orgnav_jax.scenes.synthetic.catalog import ANCHORS
from orgnav_jax.tables import stats
from orgnav_jax.tables.layout import existing_results, run_dir
from orgnav_jax.tables.rows import Row, lr_tag
from orgnav_jax.tables.runs import check_run_scenes, read_results_doc, read_table_dir
from orgnav_jax.tables.spec import read_table_spec, table_scenes

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


# the presets whose tables were pre-registered with predictions (docs/results.md: "The
# calibrated table: predictions", commit e68b2c8; "The converged table: predictions")
PREDICTED_PRESETS = ("calibrated", "calibrated_22m")


def predicted_claims(lr: str, spec: dict | None) -> list[tuple[str, str, str, int]]:
    """The predictions registered for the calibrated benchmarks that no claim above
    states: listed for a table on a PREDICTED_PRESETS preset only (named in its spec, or
    the default: a spec naming no preset was dropped from them; its runs are checked to
    be on it, runs.check_run_scenes)."""
    if spec is None or table_scenes(spec["config"]) not in PREDICTED_PRESETS:
        return []
    return [("full model > Baseline (paper +12.9)", f"org_il+tpn@{lr}", "baseline", 1),
            ("D-SP > WE", "dsp", "we", 1)]


def claim_rows(results: dict, episodes: dict, lr: str,
               spec: dict | None = None) -> list[dict]:
    """Every claim's statistics for success and SPL (None where not measured); `spec`:
    the table's (claims)."""
    out = []
    for name, row, ref, sign in claims(lr, spec):
        entry = {"claim": name, "row": row, "ref": ref, "sign": sign}
        for metric in METRIC_NAMES:
            d, seeds = stats.paired(results, row, ref, metric)
            if not seeds:
                entry[metric] = None
                continue
            st = stats.statistics(d, sign)
            st["seeds"] = seeds
            st["bootstrap"] = stats.bootstrap_interval(episodes, row, ref, seeds, metric)
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


def claims_table(results: dict, episodes: dict, lr: str, spec: dict | None = None) -> str:
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
            f"{stats.interval_text(s['interval'])} | {stats.interval_text(s['bootstrap'])} | {pval} | "
            f"{s['verdict']}{zero} | {p['mean']:+.1f} {stats.interval_text(p['interval'])} | "
            f"{p['verdict']} |")
    return "\n".join(lines) + "\n\n" + full_model_best(results, lr)


def not_converged_note(lr: str, spec: dict, rows: list[str]) -> str:
    """claims.md's note for a table whose spec has "converged": true, given its rows that
    have not converged by the rule (convergence_page.table_convergence): those rows and
    the claims of the spec's rows whose row or reference row is one of them or builds on
    one (a TPN row on its base), which are not judged at convergence."""
    if not rows:
        return ("\nEvery trained row has converged by the convergence rule at its last val "
                "evaluation (convergence.md).\n")
    affected = [name for name, row, ref, _ in claims(lr, spec)
                if row in spec["rows"] and ref in spec["rows"]
                and {Row.of(row).base, Row.of(ref).base} & set(rows)]
    head = (f"\n**Not converged** by the convergence rule at their last val evaluation "
            f"(convergence.md): {', '.join(rows)}. ")
    if not affected:
        return head + "No claim of the table compares them.\n"
    return head + "Their claims are not judged at convergence:\n\n" + "".join(
        f"- {name}\n" for name in affected)


def category_groups() -> dict[str, list[str]]:
    """The target categories by their part in the generator's co-occurrence rules:
    anchored small objects (catalog.ANCHORS keys), anchors (what they are placed by, not
    themselves anchored) and the others."""
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
    spec = read_table_spec(out)
    for r in (row, ref):
        if r not in spec["rows"]:
            raise ValueError(f"--per-category {r}: not a row of {out / 'spec.json'} "
                             f"(rows: {', '.join(spec['rows'])})")
    docs = {}
    for r in (row, ref):
        for seed in spec["seeds"]:
            path = existing_results(out, r, seed)
            if path is not None:
                check_run_scenes(run_dir(out, r, seed), table_scenes(spec["config"]))
                doc = read_results_doc(path, "test", table_scenes(spec["config"]))
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
            st = stats.statistics(d, 1)
            name = f"**{cat}**" if cat.startswith("all ") else cat
            lines.append(f"| {group} | {name} | {n_ep} | {100 * np.mean(b):.1f} | "
                         f"{100 * np.mean(a):.1f} | {st['mean']:+.1f} "
                         f"{stats.interval_text(st['interval'])} | {st['verdict']} |")
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
                     f"{stats.interval_text(s['interval'])} | {s['verdict']}{zero} |")
    return "\n".join(lines) + "\n"


def before_after(out: Path, before: Path) -> str:
    """Markdown, one line per claim measured in both tables: success before -> after
    (mean [95% t interval], seeds), the verdict's level, and "verdict changed" where the
    level (every seed / on average / does not hold) differs. Claims match by name."""
    def measured(table_dir: Path) -> dict[str, dict]:
        spec, results, episodes = read_table_dir(table_dir)
        return {c["claim"]: c["success"] for c in
                claim_rows(results, episodes, lr_tag(spec["rows"]), spec)
                if c["success"] is not None}
    old, new = measured(before), measured(out)
    level = lambda v: v.split(" (")[0]
    text = lambda s: (f"{s['mean']:+.1f} {stats.interval_text(s['interval'])}, {s['verdict']}"
                      + ("" if " of " in s["verdict"] else f" ({len(s['seeds'])} seeds)"))
    return "\n".join(
        f"- {name}: {text(old[name])} -> {text(s)}"
        + ("; **verdict changed**" if level(old[name]["verdict"]) != level(s["verdict"])
           else "")
        for name, s in new.items() if name in old) + "\n"
