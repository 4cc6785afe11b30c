"""What val chose (experiments/val_choices.py; docs/results.md, "What val chose"): the
val sweeps of a folder read (sweeps.py's readers), each setting picked, and the record
(choices.json; choices.md). Each choice is the variant with the highest val success (SPL
breaks ties); a choice over several rows or bases takes the mean over them.
tests/test_val_choices.py ties the package's defaults to the record.

To add a choice: its sweep's file name in sweep_files, its pick in choices, its line in
markdown.
"""

from __future__ import annotations

from pathlib import Path

from orgnav_jax.tables.sweeps import read_sweep, read_tpn_sweep

TPN_BASES = {"baseline-ours-s100": "Baseline", "org_il-cause-w0.3-s100": "ORG + IL"}
# stage-2 run name -> (placement, stage-2 optim)
TPN_RUNS = {"tpn": ("state", "ours"), "tpn-release": ("release", "ours"),
            "tpn-release-optim": ("release", "release")}
OPTIM_ROWS = {"baseline": "Baseline", "org_il": "ORG + IL"}
# what the VTNet sweep varies, with the defaults before it (training/config.py)
VTNET_FIELDS = {"pretrain_samples": 1_000_000, "vtnet_mask": "none", "pretrained_lr_scale": 0.1}
# the IL sweep's runs: seed 100 (il), seed 101 (il_101), step and norm at seed 100 (il_more)
IL_SWEEPS = ("il", "il_101", "il_more")


def best(scores: dict[str, dict]) -> str:
    """The key with the highest success, then SPL."""
    return max(scores, key=lambda k: (scores[k]["success"], scores[k]["spl"]))


def mean(records: list[dict]) -> dict:
    return {m: sum(r[m] for r in records) / len(records) for m in ("success", "spl")}


def sweep(*paths: Path) -> dict[str, dict]:
    """val_sweep.py JSONs (runs of one variant may be spread over several) -> {variant:
    {success, spl, overrides, row, seeds}} (mean over seeds)."""
    doc = {}
    for path in paths:
        if path.exists():
            for variant, by_seed in read_sweep(path).items():
                doc.setdefault(variant, {}).update(by_seed)
    out = {}
    for variant, by_seed in doc.items():
        runs = list(by_seed.values())
        out[variant] = {**mean(runs), "overrides": runs[0]["overrides"],
                        "row": runs[0]["row"], "seeds": sorted(by_seed, key=int)}
    return out


def pick_fields(root: Path, names: tuple[str, ...], fields: dict,
                keep=lambda v: True) -> dict:
    """Choices of `fields` ({field: default}) from the sweeps `<name>.json`."""
    scores = {k: v for k, v in sweep(*(root / f"{n}.json" for n in names)).items()
              if keep(v)}
    pick = best(scores)
    source = [f"{n}.json" for n in names if (root / f"{n}.json").exists()]
    return {f: {"value": scores[pick]["overrides"].get(f, default), "variant": pick,
                "val": scores, "from": source} for f, default in fields.items()}


def optim_choice(root: Path) -> dict:
    """ours | release: the mean over OPTIM_ROWS of each setting's best val."""
    scores = sweep(root / "optim.json")
    by = {}
    for variant, r in scores.items():
        row, _, setting = variant.rpartition("-")
        by.setdefault(setting, {})[row] = r
    rows = set.intersection(*(set(r) for r in by.values()))
    means = {s: mean([r[row] for row in rows]) for s, r in by.items()}
    pick = best(means)
    return {"optim": {"value": pick, "variant": f"{pick} (mean of {len(rows)} rows)",
                      "val": scores, "from": "optim.json"}}


def tpn_choice(root: Path) -> dict:
    """placement, stage-2 optim and test-time lr: the best (run, lr) by the mean over
    the bases that have every run."""
    per = {}
    for base in TPN_BASES:
        for run in TPN_RUNS:
            path = root / f"tpn_placement_{base}_{run}.json"
            if path.exists():
                per.setdefault(base, {})[run] = read_tpn_sweep(path)
    bases = [b for b in per if set(per[b]) == set(TPN_RUNS)]
    if not bases:
        return {}
    scores = {}
    for run in TPN_RUNS:
        lrs = set.intersection(*(set(per[b][run]) for b in bases)) - {"0"}
        for lr in sorted(lrs, key=float):      # (a set: its order varies by run)
            scores[f"{run} @ {lr}"] = mean([per[b][run][lr] for b in bases])
    pick = best(scores)
    run, _, lr = pick.partition(" @ ")
    placement, optim = TPN_RUNS[run]
    val = {b: {r: {lr: {m: x[m] for m in ("success", "spl")} for lr, x in res.items()}
               for r, res in per[b].items()} for b in bases}
    source = [f"tpn_placement_{b}_{r}.json" for b in bases for r in TPN_RUNS]
    common = {"variant": pick, "val": val, "mean": scores, "from": source}
    return {"tpn_placement": {"value": placement, **common},
            "tpn_stage2_optim": {"value": optim, **common},
            "tpn_lr": {"value": float(lr), **common}}


def sweep_files(root: Path) -> list[Path]:
    """The val_sweep.py-form JSONs the choices read (each {variant: {seed: record}})."""
    names = ("dropout", *IL_SWEEPS, "optim", "savn", "savn_optim", "savn_act", "vtnet")
    return [root / f"{n}.json" for n in names if (root / f"{n}.json").exists()]


def choices(root: Path) -> dict:
    """{setting: {"value", "variant", "val", "from"}} for each sweep that exists."""
    out = {}
    if (root / "dropout.json").exists():
        out |= pick_fields(root, ("dropout",), {"dropout": 0.0})
    if (root / "il.json").exists():
        out |= pick_fields(root, IL_SWEEPS, {"il_step": "state", "il_norm": "per_step",
                                             "il_weight": 1.0}, keep=lambda v: v["row"] == "il")
    if (root / "optim.json").exists():
        out |= optim_choice(root)
    out |= tpn_choice(root)
    if (root / "savn.json").exists():
        out |= pick_fields(root, ("savn",), {"savn_inner_lr": 1e-4, "savn_steps": 6})
    if (root / "savn_act.json").exists():
        out |= pick_fields(root, ("savn_act",), {"savn_act": "sample"})
    if (root / "savn_optim.json").exists():
        out |= {"savn_optim": pick_fields(root, ("savn_optim",), {"optim": "ours"})["optim"]}
    if (root / "vtnet.json").exists():
        out |= pick_fields(root, ("vtnet",), VTNET_FIELDS)
    return out


def cells(val: dict) -> str:
    """'variant: success / SPL' per variant (x100), with the seeds when more than one."""
    return "; ".join(f"{v}: {100 * r['success']:.1f} / {100 * r['spl']:.1f}"
                     + (f" (seeds {', '.join(r['seeds'])})" if len(r.get("seeds", ())) > 1
                        else "") for v, r in val.items())


def markdown(ch: dict) -> str:
    lines = ["| choice | val success / SPL (seeds 100+) | picked |", "|---|---|---|"]
    simple = (("dropout", "dropout (Baseline, 2 M steps)"),
              ("savn_act", "SAVN's test-time actions (D-SAVN)"),
              ("savn_optim", "SAVN's optimiser (D-SAVN, 5 M real steps)"))
    for name, what in simple[:1]:
        if name in ch:
            lines.append(f"| {what} | {cells(ch[name]['val'])} | {ch[name]['value']} |")
    if "il_step" in ch:
        c = ch["il_step"]
        lines.append(f"| IL step, norm and weight (2 M steps) | {cells(c['val'])} | "
                     f"`{c['variant']}`: il_step {c['value']}, il_norm "
                     f"{ch['il_norm']['value']}, il_weight {ch['il_weight']['value']:g} |")
    if "optim" in ch:
        lines.append(f"| optimiser and advantage (5 M steps) | {cells(ch['optim']['val'])} "
                     f"| {ch['optim']['value']} |")
    if "tpn_lr" in ch:
        c = ch["tpn_lr"]
        for base, runs in c["val"].items():
            for run, res in runs.items():
                lrs = "; ".join(f"{lr}: {100 * r['success']:.1f} / {100 * r['spl']:.1f}"
                                for lr, r in sorted(res.items(), key=lambda x: float(x[0])))
                lines.append(f"| TPN, {TPN_BASES[base]}, `{run}` (1000 val episodes per lr) "
                             f"| {lrs} | |")
        lines.append(f"| TPN placement, stage-2 optimiser, test-time lr (mean of the bases) "
                     f"| {cells(c['mean'])} | `{c['variant']}`: placement "
                     f"{ch['tpn_placement']['value']}, stage-2 optim "
                     f"{ch['tpn_stage2_optim']['value']}, tpn_lr {c['value']:g} |")
    if "savn_inner_lr" in ch:
        c = ch["savn_inner_lr"]
        lines.append(f"| D-SAVN inner lr and k (5 M real steps) | {cells(c['val'])} | "
                     f"`{c['variant']}`: savn_inner_lr {c['value']:g}, savn_steps "
                     f"{ch['savn_steps']['value']} |")
    for name, what in simple[1:]:
        if name in ch:
            lines.append(f"| {what} | {cells(ch[name]['val'])} | {ch[name]['value']} |")
    if "pretrain_samples" in ch:
        c = ch["pretrain_samples"]
        lines.append(f"| VTNet: pre-training samples, attention mask, pre-trained lr scale "
                     f"(5 M steps) | {cells(c['val'])} | `{c['variant']}`: pretrain_samples "
                     f"{c['value']:,}, vtnet_mask {ch['vtnet_mask']['value']}, "
                     f"pretrained_lr_scale {ch['pretrained_lr_scale']['value']:g} |")
    return "\n".join(lines) + "\n"
