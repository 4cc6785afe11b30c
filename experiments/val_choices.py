"""What val chose: read the val sweeps, pick each setting, write the record.

    python experiments/val_choices.py            # experiments/results/val_choices/

Reads the sweeps of experiments/results/val_choices (made with seed 100, which no table
row uses; the commands are in docs/results.md):
- dropout.json: the Baseline with dropout 0 and 0.25 (2 M env steps, best val);
- il.json: IL variants (step, norm, weight) at the chosen dropout (2 M env steps);
- tpn_lr_<base>.json: the TPN's test-time learning rate on a Baseline and an ORG + IL
  base (5 M env steps, 40 k stage-2 episodes, 1000 val episodes per lr);
- savn.json: D-SAVN's inner lr and segment length k (2 M env steps), used by both SAVN
  rows.
Each choice is the variant with the highest val success (SPL breaks ties). It writes
choices.json (the choices with their val numbers; tests/test_val_choices.py ties the
package's defaults to it) and choices.md (the table in docs/results.md).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

OUT = Path(__file__).resolve().parent / "results" / "val_choices"
TPN_BASES = {"baseline-d0-s100": "Baseline", "org_il-s100": "ORG + IL"}


def best(scores: dict[str, dict]) -> str:
    """The key with the highest success, then SPL."""
    return max(scores, key=lambda k: (scores[k]["success"], scores[k]["spl"]))


def sweep(path: Path) -> dict[str, dict]:
    """A val_sweep.py JSON -> {variant: {success, spl, overrides, seeds}} (mean over
    seeds)."""
    doc = json.loads(path.read_text())
    out = {}
    for variant, by_seed in doc.items():
        runs = list(by_seed.values())
        out[variant] = {"success": sum(r["success"] for r in runs) / len(runs),
                        "spl": sum(r["spl"] for r in runs) / len(runs),
                        "overrides": runs[0]["overrides"], "row": runs[0]["row"],
                        "seeds": sorted(by_seed, key=int)}
    return out


def choices(root: Path = OUT) -> dict:
    """{setting: {"value", "val", "from"}} for dropout, the IL fields and tpn_lr."""
    out = {}
    drop = sweep(root / "dropout.json")
    pick = best(drop)
    out["dropout"] = {"value": drop[pick]["overrides"]["dropout"], "variant": pick,
                      "val": drop, "from": "dropout.json"}
    il = sweep(root / "il.json")
    il_only = {k: v for k, v in il.items() if v["row"] == "il"}
    pick = best(il_only)
    fields = il_only[pick]["overrides"]
    for name, default in (("il_step", "state"), ("il_norm", "per_step"),
                          ("il_weight", 1.0)):
        out[name] = {"value": fields.get(name, default), "variant": pick, "val": il,
                     "from": "il.json"}
    if (root / "savn.json").exists():
        savn = sweep(root / "savn.json")
        pick = best(savn)
        for name, default in (("savn_inner_lr", 1e-4), ("savn_steps", 6)):
            out[name] = {"value": savn[pick]["overrides"].get(name, default),
                         "variant": pick, "val": savn, "from": "savn.json"}
    per_base = {}
    for base in TPN_BASES:
        path = root / f"tpn_lr_{base}.json"
        if path.exists():
            per_base[base] = json.loads(path.read_text())["results"]
    if per_base:
        lrs = set.intersection(*(set(r) for r in per_base.values()))
        mean = {lr: {m: sum(r[lr][m] for r in per_base.values()) / len(per_base)
                     for m in ("success", "spl")} for lr in lrs}
        pick = best(mean)
        out["tpn_lr"] = {"value": float(pick), "variant": f"lr {pick}",
                         "val": {b: {lr: {m: r[m] for m in ("success", "spl")}
                                     for lr, r in res.items()}
                                 for b, res in per_base.items()},
                         "from": [f"tpn_lr_{b}.json" for b in per_base]}
    return out


def markdown(ch: dict) -> str:
    lines = ["| choice | val success / SPL (seed 100) | picked |", "|---|---|---|"]
    for name in ("dropout", "il_step"):
        c = ch[name]
        cells = "; ".join(f"{v}: {100 * r['success']:.1f} / {100 * r['spl']:.1f}"
                          for v, r in c["val"].items())
        what = ("dropout (Baseline, 2 M steps)" if name == "dropout"
                else "IL step, norm and weight (2 M steps)")
        picked = (str(c["value"]) if name == "dropout" else
                  f"`{c['variant']}`: il_step {ch['il_step']['value']}, il_norm "
                  f"{ch['il_norm']['value']}, il_weight {ch['il_weight']['value']:g}")
        lines.append(f"| {what} | {cells} | {picked} |")
    if "savn_inner_lr" in ch:
        c = ch["savn_inner_lr"]
        cells = "; ".join(f"{v}: {100 * r['success']:.1f} / {100 * r['spl']:.1f}"
                          for v, r in c["val"].items())
        lines.append(f"| D-SAVN inner lr and k (2 M steps) | {cells} | `{c['variant']}`: "
                     f"savn_inner_lr {c['value']:g}, savn_steps "
                     f"{ch['savn_steps']['value']} |")
    if "tpn_lr" in ch:
        for base, res in ch["tpn_lr"]["val"].items():
            cells = "; ".join(f"{lr}: {100 * r['success']:.1f} / {100 * r['spl']:.1f}"
                              for lr, r in sorted(res.items(), key=lambda x: float(x[0])))
            lines.append(f"| TPN test-time lr, {TPN_BASES[base]} (1000 val episodes) | "
                         f"{cells} | {ch['tpn_lr']['value']:g} (mean of both bases) |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ch = choices()
    (OUT / "choices.json").write_text(json.dumps(ch, indent=1) + "\n")
    text = markdown(ch)
    (OUT / "choices.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
