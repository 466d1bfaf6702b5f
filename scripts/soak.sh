#!/usr/bin/env bash
# The full soak (docs/robustness.md): NanoTrack v2's fp32 and int8 plans, each tracking
# building4 looped for FRAMES frames (default 100,000), memory, descriptors and frame time
# sampled every 1,000. Writes target/soak/<plan>.json and .log and prints each run's verdict.
#
#   bash scripts/soak.sh [FRAMES]
#
# PRL_BIN=path/to/prl runs that binary instead of building the release one (such as the dev
# build `cargo test` leaves in target/debug/prl: its dependencies and the runtime are optimised).
set -euo pipefail
cd "$(dirname "$0")/.."
frames=${1:-100000}
shared=${PRL_SHARED:-$(cd .. && pwd)/shared}
work=target/soak
mkdir -p "$work"
source scripts/prl-bin.sh
use_prl release
seq="$shared/data/uav123_10fps/building4"
if [ ! -f "$work/fp32/plan.json" ]; then
    $prl import nanotrack --out "$work/model" >/dev/null
    $prl compile --model "$work/model" --out "$work/fp32" >/dev/null
fi
if [ ! -f "$work/int8/plan.json" ]; then
    $prl quantize --plan "$work/fp32" --calib "$shared/data/uav123_10fps/wakeboard7" --frames-per-seq 16 \
        --method minmax --budget 4 --min-macs 1000000 --min-out-channels 16 --out "$work/int8" >/dev/null
fi
# Both plans at once, one thread each (a machine with two cores or more gives each its own);
# each run's samples go to target/soak/<plan>.log.
pids=()
for p in fp32 int8; do
    $prl soak --plan "$work/$p" --sequence "$seq" --frames "$frames" --every 1000 --json "$work/$p.json" \
        >"$work/$p.log" 2>&1 &
    pids+=($!)
done
status=0
for i in 0 1; do
    p=$([ $i = 0 ] && echo fp32 || echo int8)
    wait "${pids[$i]}" || status=1
    echo "== $p"
    tail -2 "$work/$p.log"
done
exit $status
