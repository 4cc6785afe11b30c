"""What val chose: read the val sweeps, pick each setting, write the record.

    python experiments/val_choices.py            # experiments/results/val_choices/

Reads the sweeps of experiments/results/val_choices, made on the release's networks
(issues 39-41; seeds 100+, which no table row uses; the commands are in docs/results.md
and docs/training.md). The sweeps made before parity are kept, unchanged, in
experiments/results/before_parity/val_choices.
- dropout.json: the Baseline with dropout 0 and 0.25 (2 M env steps, best val);
- il.json, il_101.json, il_more.json: IL variants (step, norm, weight; 2 M env steps;
  seed 100, the weights again with seed 101, step and norm; mean over each variant's
  seeds);
- optim.json: the optimiser and advantage settings, ours against the release's, on the
  Baseline and ORG + IL (5 M env steps): variants `<row>-ours`, `<row>-release`;
- tpn_placement_<base>_<run>.json: the TPN's test-time lr sweep (1000 val episodes per
  lr) of each stage-2 variant on each base (5 M env steps, 40 k stage-2 episodes): run
  `tpn` (placement state, stage-2 optimiser ours), `tpn-release` (placement release),
  `tpn-release-optim` (placement release, the release's stage-2 optimiser and cap);
  lr 0 (the base alone) is in the `tpn` run's file;
- savn.json: D-SAVN's inner lr and segment length k (5 M real env steps, issue 40),
  both SAVN rows;
- savn_act.json: D-SAVN's val success with greedy and with sampled test-time actions
  (variants `greedy`, `sample`; the same trained runs);
- savn_optim.json: D-SAVN with our optimiser against SAVN's release's (`dsavn-ours`,
  `dsavn-release`);
- vtnet.json: VTNet's pre-training budget, attention mask and pre-trained lr scale, one
  at a time against the defaults (5 M env steps; `vtnet-default`, `vtnet-pre4m`,
  `vtnet-mask`, `vtnet-lrscale1`).
A file not made yet gives no choice (the defaults then stay, and the test skips it).
Each choice is the variant with the highest val success (SPL breaks ties); a choice over
several rows or bases takes the mean over them (the tables library's choices.py). It writes choices.json (the choices with
their val numbers; tests/test_val_choices.py ties the package's defaults to it) and
choices.md (docs/results.md links it). Every file is read, through a typed reader,
before either is written: a truncated or malformed sweep file is one line naming it and
its field, exit 2 (so is an option: the script takes none but --check).

    python experiments/val_choices.py --check    # recompute both; exit 1 on a difference
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from orgnav_jax.errors import run_cli
from orgnav_jax.tables import pages
from orgnav_jax.tables.choices import choices, markdown

OUT = Path(__file__).resolve().parent / "results" / "val_choices"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="recompute choices.json and choices.md from the sweeps; exit 1 on "
                         "a difference")
    args = ap.parse_args(argv)
    ch = choices(OUT)
    text = markdown(ch)
    status = pages.regenerate({OUT / "choices.json": json.dumps(ch, indent=1) + "\n",
                               OUT / "choices.md": text}, args.check)
    if not args.check:
        print(text)
    return status


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
