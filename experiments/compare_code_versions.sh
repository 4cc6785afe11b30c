#!/usr/bin/env bash
# Does code version OLD train exactly like the working tree on this machine?
#
#   bash experiments/compare_code_versions.sh c425636
#
# Trains the same short run (ORG + IL, tiny scenes, seed 1, dropout 0.25, 204,800 env
# steps) with the commit OLD (a git worktree in a temporary folder, its own scene cache)
# and with this checkout, then compares every metrics.jsonl record (timing fields aside)
# and the test results. Prints "identical" or "DIFFER"; exits 1 when they differ.
set -euo pipefail
old=${1:?usage: compare_code_versions.sh OLD_COMMIT}
top=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d -t orgnav-compare-XXXX)
git -C "$top" worktree add -f -q "$work/old" "$old"
trap 'git -C "$top" worktree remove --force "$work/old"; rm -rf "$work"' EXIT
for v in old new; do
  src=$([ $v = old ] && echo "$work/old" || echo "$top")
  (cd "$src" && ORGNAV_CACHE="$work/cache-$v" PYTHONPATH="$src" python -m orgnav_jax.train \
     --preset org_il --scene-preset tiny --seed 1 --dropout 0.25 --total-env-steps 204800 \
     --updates-per-chunk 10 --eval-every-chunks 4 --run-dir "$work/run-$v" --quiet \
     > "$work/$v.log" 2>&1) || { echo "the $v run failed: $work/$v.log"; cat "$work/$v.log"; exit 2; }
done
python - "$work" <<'PY'
import json, sys
work = sys.argv[1]
def records(v):
    return [{k: x for k, x in json.loads(line).items() if k != "steps_per_s"}
            for line in open(f"{work}/run-{v}/metrics.jsonl")]
tests = [json.load(open(f"{work}/run-{v}/test_results.json"))["overall"] for v in ("old", "new")]
same = records("old") == records("new") and all(tests[1][k] == v for k, v in tests[0].items())
print(f"{len(records('old'))} metrics records and the test results:",
      "identical" if same else "DIFFER")
print("old", tests[0]); print("new", {k: tests[1][k] for k in tests[0]})
sys.exit(0 if same else 1)
PY
