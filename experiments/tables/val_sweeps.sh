#!/usr/bin/env bash
# The val sweeps behind the package's defaults (docs/results.md, "What val chose"):
# seeds 100 and 101, which no table row uses; each run's files land in
# experiments/results/val_choices/runs/, each sweep's record in its NAME.json and NAME.md,
# and val_choices.py writes choices.json and choices.md from them. Every command resumes
# an interrupted run and skips a finished one, so the script can be run again as is.
# Some runs were made while the defaults differed (IL `state` at weight 1; the TPN's
# `state` placement and `ours` optimiser; the dsavn preset's inner lr 1e-4): the commands
# spell those settings out. savn_optim and savn_act are listed but were not run.
#
#   bash experiments/tables/val_sweeps.sh      # hours to days on 2 CPU cores
set -euo pipefail
cd "$(dirname "$0")/../.."
V=experiments/results/val_choices
O="--out $V --seeds 100 --total-env-steps 2048000"
python experiments/val_sweep.py --name dropout $O --variants baseline-d0=baseline:dropout=0 \
    baseline-d25=baseline:dropout=0.25
python experiments/val_sweep.py --name il $O --variants il-state-w1=il:il_step=state,il_weight=1 \
    il-state-w3=il:il_step=state,il_weight=3 il-state-w0.3=il:il_step=state,il_weight=0.3
python experiments/val_sweep.py --name il_101 --out $V --seeds 101 --total-env-steps 2048000 \
    --variants il-state-w1=il:il_step=state,il_weight=1 il-state-w0.3=il:il_step=state,il_weight=0.3
python experiments/val_sweep.py --name il_more $O --variants il-cause-w0.3=il:il_step=cause,il_weight=0.3 \
    il-state-w0.3-masked=il:il_step=state,il_norm=masked_mean,il_weight=0.3
python experiments/val_sweep.py --name il_more --out $V --seeds 101 --total-env-steps 2048000 \
    --variants il-cause-w0.3=il:il_step=cause,il_weight=0.3
# the optimiser and advantage settings (training.md), at the table's budget
python experiments/val_sweep.py --name optim --out $V --seeds 100 --total-env-steps 5000000 \
    --variants baseline-ours=baseline baseline-release=baseline:optim=release \
    org_il-ours=org_il:il_step=state,il_weight=1 org_il-release=org_il:il_step=state,il_weight=1,optim=release
# the TPN: placement, stage-2 optimiser and test-time lr (tpn_stage2.md) on two bases
python experiments/val_sweep.py --name org_il_base --out $V --seeds 100 --total-env-steps 5000000 \
    --variants org_il-cause-w0.3=org_il
for b in baseline-ours-s100 org_il-cause-w0.3-s100; do
  python -m orgnav_jax.train --stage tpn --base $V/runs/$b --no-test --placement state \
      --optim ours --run-dir $V/runs/$b/tpn
  python -m orgnav_jax.train --stage tpn --base $V/runs/$b --no-test --placement release \
      --optim ours --run-dir $V/runs/$b/tpn-release
  python -m orgnav_jax.train --stage tpn --base $V/runs/$b --no-test --placement release \
      --optim release --run-dir $V/runs/$b/tpn-release-optim
  python experiments/tpn_lr_sweep.py $V/runs/$b/tpn --lrs 0 1e-4 1e-3 1e-2 \
      --out $V/tpn_placement_${b}_tpn.json
  for t in tpn-release tpn-release-optim; do
    python experiments/tpn_lr_sweep.py $V/runs/$b/$t --lrs 1e-4 1e-3 1e-2 \
        --out $V/tpn_placement_${b}_$t.json
  done
done
# SAVN's inner lr and k at 5 M real env steps (savn.md); its optimiser and test-time
# actions (not run)
python experiments/val_sweep.py --name savn --out $V --seeds 100 --total-env-steps 5000000 \
    --variants dsavn-lr1e-4-k6=dsavn:savn_inner_lr=1e-4 \
    dsavn-lr1e-3-k6=dsavn:savn_inner_lr=1e-3 dsavn-lr1e-4-k4=dsavn:savn_steps=4,savn_inner_lr=1e-4 \
    dsavn-lr0=dsavn:savn_inner_lr=0
python experiments/val_sweep.py --name savn_optim $O --variants dsavn-ours=dsavn \
    dsavn-release=dsavn:optim=release
python experiments/savn_act_sweep.py $V/runs/dsavn-lr1e-3-k6-s100 --out $V/savn_act.json
# VTNet (each variant pre-trains first, in runs/NAME-pretrain-s100)
python experiments/val_sweep.py --name vtnet --out $V --seeds 100 --total-env-steps 5000000 \
    --variants vtnet-default=vtnet vtnet-mask=vtnet:vtnet_mask=undetected \
    vtnet-pre4m=vtnet:pretrain_samples=4000000 vtnet-lrscale1=vtnet:pretrained_lr_scale=1
python experiments/val_choices.py
