#!/bin/bash
# Train rows of a table spec as parallel streams on one GPU: each stream is its own
# run_table.py process and out dir (/tmp/g/outN), all stopped at DEADLINE s, then packed
# into OUT_DIR by pack.py (the runs' small files, best checkpoints of finished TPN bases,
# the checkpoints of runs that can go on elsewhere, as many as fit). How the 5 M table's
# GPU rows were made (docs/results.md); unpack with: tar xzf OUT_DIR/small.tgz -C
# experiments/results/table_5m, tar xf OUT_DIR/best_ROW.tar -C experiments/results/table_5m
# (cat OUT_DIR/part_runs.tar* | tar x: to resume or test runs), then run_table.py --spec
# SPEC --only ROWS rebuilds the table files from them (their runs are finished).
# SAVN streams: their compile dominates on a GPU (docs/scale_out.md, Figures).
# usage: OUT=OUT_DIR [SPEC=spec.json] bash experiments/gpu_streams/run.sh DEADLINE_S COMMIT
#            "rows of stream 1" "rows of stream 2" ...   (COMMIT: of the clean tree copied)
#        "ROWS @S1 @S2" trains only those seeds (e.g. one SAVN seed per stream: SAVN runs
#        one seed per program); a stream "cmd:COMMAND" runs COMMAND instead, with
#        G=/tmp/g/outN (e.g. a val sweep with --out $G); its runs in $G/runs and records
#        $G/*.json, *.md are packed too
set -u
usage() {
  echo "usage: OUT=OUT_DIR [SPEC=spec.json] bash experiments/gpu_streams/run.sh DEADLINE_S COMMIT \"ROWS\" ..." >&2
  echo "error: $1" >&2; exit 2
}
# every argument checked before anything is written or started
[ $# -ge 3 ] || usage "expected DEADLINE_S, COMMIT and at least one stream, got $# argument(s)"
[[ $1 =~ ^[0-9]+$ ]] && [ "$1" -ge 1 ] || usage "DEADLINE_S '$1': expected whole seconds >= 1"
[ -n "$2" ] || usage "COMMIT is empty: expected the commit of the tree copied"
[ -n "${OUT:-}" ] || usage "OUT is not set: expected OUT=OUT_DIR (the packed results go there)"
[ ! -e "$OUT" ] || [ -d "$OUT" ] || usage "OUT $OUT is not a directory"
[ -z "${SPEC:-}" ] || [ -f "$SPEC" ] || usage "SPEC $SPEC: no such file"
for rows in "${@:3}"; do
  [ -n "${rows// /}" ] || usage "a stream is empty: expected rows of the spec or cmd:COMMAND"
done
mkdir -p "$OUT"
T0=$(date +%s); DL=$1; export ORGNAV_CODE=$2; shift 2
elapsed() { echo $(( $(date +%s) - T0 )); }
# float32 as on CPU (no TF32); each process takes GPU memory as it needs it
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false \
    JAX_DEFAULT_MATMUL_PRECISION=highest
LOG=$OUT/log.txt
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; nproc
  python3 --version
  # what provenance's "uncommitted_changes" will see in this copy of the tree
  echo "git status of the copy:"; git -c core.fileMode=false status --porcelain \
      --untracked-files=no -- orgnav_jax experiments ':(exclude)experiments/results'
} >>"$LOG" 2>&1
# .whl/ (optional, git-ignored): pure-Python wheels of the versions this project pins
# (flax, optax, chex, orbax-checkpoint, tensorboardX) for a machine without a package
# index; if they do not import there, the machine's own packages are used
[ -d .whl ] && python3 -m pip install -q --no-index --no-deps --no-compile \
    --no-cache-dir --upgrade --target /tmp/site .whl/*.whl >>"$LOG" 2>&1
CHECK="import jax, flax, orgnav_jax.api; print(jax.__version__, flax.__version__, jax.devices())"
export PYTHONPATH=/tmp/site:$PWD
if ! python3 -c "$CHECK" >>"$LOG" 2>&1; then
  echo "carried wheels do not import; the machine's packages" >>"$LOG"
  export PYTHONPATH=$PWD
  python3 -c "$CHECK" >>"$LOG" 2>&1
fi
mkdir -p /tmp/g; i=0; pids=()
for rows in "$@"; do                  # stream i: the spec with out /tmp/g/out$i and these rows
  i=$((i+1))
  if [[ $rows == cmd:* ]]; then       # or a command, run with G=/tmp/g/out$i (its runs: $G/runs)
    mkdir -p /tmp/g/out$i
    G=/tmp/g/out$i bash -c "${rows#cmd:}" >/tmp/g/log$i.txt 2>&1 &
  else
    python3 - "$i" "$rows" <<'PY'
import json, os, sys
spec = json.load(open(os.environ.get("SPEC", "experiments/tables/table_5m.json")))
words = sys.argv[2].split()                     # ROWS [@SEED ...]: these seeds only
seeds = [int(w[1:]) for w in words if w.startswith("@")]
spec["out"], spec["rows"] = f"/tmp/g/out{sys.argv[1]}", [w for w in words if w[0] != "@"]
spec["seeds"] = seeds or spec["seeds"]
json.dump(spec, open(f"/tmp/g/spec{sys.argv[1]}.json", "w"))
PY
    python3 experiments/run_table.py --spec /tmp/g/spec$i.json >/tmp/g/log$i.txt 2>&1 &
  fi
  pids+=($!)
  echo "stream $i ($rows): pid $!" >>"$LOG"
done
while true; do                        # until every stream ends or the deadline
  alive=0; for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && alive=1; done
  [ $alive = 0 ] && break
  [ "$(elapsed)" -ge "$DL" ] && { echo "deadline at $(elapsed) s" >>"$LOG"; break; }
  sleep 5
done
for p in "${pids[@]}"; do kill -INT "$p" 2>/dev/null; done; sleep 8
for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null; done
nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv >>"$LOG" 2>&1
echo "packing at $(elapsed) s" >>"$LOG"
python3 experiments/gpu_streams/pack.py "$OUT" >>"$LOG" 2>&1
echo "done at $(elapsed) s" >>"$LOG"
