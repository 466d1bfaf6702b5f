#!/usr/bin/env bash
# What int8 costs in tracking accuracy, as a spread rather than one draw: quantises an fp32 plan
# once per calibration seed (the seed moves the calibration crops' jitter, so each plan's ranges
# and last bits differ a little, as they do between machines and releases), compares every int8
# plan with the fp32 one on held-out sequences in one `prl compare` run, and prints per seed the
# output errors and the ΔAUC on each sequence, then each sequence's worst, median and best.
# One plan's ΔAUC on a short sequence is partly the tracker's chaos (a few frames where the two
# plans pick neighbouring cells send the trajectories apart); the spread says how much.
#
#   bash scripts/int8-spread.sh [SEEDS] [-- QUANTIZE_OPTIONS...]
#
# Defaults: NanoTrack v2 (imported and compiled into target/int8-spread/ if needed), 5 seeds,
# the README's int8 recipe (calibrated on building4), evaluated on wakeboard7 and wakeboard10.
# PRL_PLAN=DIR takes another fp32 plan, PRL_CALIB / PRL_EVAL other sequences (space-separated
# directories), PRL_BIN another binary, PRL_FIRST_SEED the first seed (0; seeds run from it).
# Needs python3 for the summary. Writes target/int8-spread/compare.json and compare.md.
set -euo pipefail
cd "$(dirname "$0")/.."
seeds=5
if [ $# -gt 0 ] && [ "$1" != "--" ]; then
    seeds=$1
    shift
fi
[ "${1:-}" = "--" ] && shift
case $seeds in '' | *[!0-9]* | 0) echo "int8-spread.sh: SEEDS must be a positive whole number, not '$seeds'" >&2; exit 2 ;; esac
first=${PRL_FIRST_SEED:-0}
case $first in '' | *[!0-9]*) echo "int8-spread.sh: PRL_FIRST_SEED must be a whole number, not '$first'" >&2; exit 2 ;; esac
recipe=("$@")
if [ ${#recipe[@]} -eq 0 ]; then
    source scripts/nanotrack-int8-recipe.sh
    recipe=("${nanotrack_int8_recipe[@]}")
fi
shared=${PRL_SHARED:-$(cd .. && pwd)/shared}
data=$shared/data/uav123_10fps
calib=${PRL_CALIB:-$data/building4}
eval_seqs=${PRL_EVAL:-"$data/wakeboard7 $data/wakeboard10"}
work=target/int8-spread
mkdir -p "$work"
source scripts/prl-bin.sh
use_prl release
plan=${PRL_PLAN:-$work/fp32}
if [ -z "${PRL_PLAN:-}" ] && [ ! -f "$plan/plan.json" ]; then
    $prl import nanotrack --out "$work/model" >/dev/null
    $prl compile --model "$work/model" --out "$plan" >/dev/null
fi
calib_args=()
for c in $calib; do calib_args+=(--calib "$c"); done
plans=(--plan "$plan")
for ((s = first; s < first + seeds; s++)); do
    rm -rf "$work/int8-seed$s"
    $prl quantize --plan "$plan" "${calib_args[@]}" "${recipe[@]}" --seed "$s" --out "$work/int8-seed$s" >"$work/int8-seed$s.log"
    plans+=(--plan "$work/int8-seed$s")
done
seq_args=()
for e in $eval_seqs; do seq_args+=(--sequence "$e"); done
$prl compare "${plans[@]}" "${seq_args[@]}" --crops-per-seq 32 --runs 5 --threads 1 \
    --json "$work/compare.json" --markdown "$work/compare.md" >/dev/null
echo "recipe: ${recipe[*]}; calibrated on: $calib"
python3 - "$work/compare.json" <<'EOF'
import json, statistics, sys
d = json.load(open(sys.argv[1]))
fid = {f["plan"]: f for f in d["fidelity"]}
seqs = d["sequences"]
ref = d["plans"][0]["path"]
print("| seed | cls error | loc error | same best cell | " + " | ".join(f"ΔAUC {s['sequence']}" for s in seqs) + " |")
print("|---|---|---|---|" + "---|" * len(seqs))
deltas = {s["sequence"]: [] for s in seqs}
for p in d["plans"][1:]:
    path = p["path"]
    f = fid[path]
    errors = dict(f["errors"])
    row = []
    for s in seqs:
        by = {q["plan"]: q["auc"] for q in s["plans"]}
        delta = 100 * (by[path] - by[ref])
        deltas[s["sequence"]].append(delta)
        row.append(f"{delta:+.1f}")
    seed = path.rsplit("seed", 1)[-1]
    print(f"| {seed} | {errors['cls']:.4f} | {errors['loc']:.4f} | {100 * f['best_cell_agreement']:.1f}% | " + " | ".join(row) + " |")
for name, v in deltas.items():
    print(f"{name}: ΔAUC (points) worst {min(v):+.1f}, median {statistics.median(v):+.1f}, best {max(v):+.1f} over {len(v)} seeds")
EOF
