#!/usr/bin/env bash
# An estimate of the tracking step's time on the Jetson Orin NX's CPU (8 Cortex-A78AE cores,
# 2.0 GHz), made on an x86 machine, for NanoTrack v2 (fp32, the int8 recipe and the faster
# integer-depthwise plan) and PRL-Track, fp32 and int8, with the
# runtime's operators and with tract's alone (PRL_OPS=tract):
#
#   bash scripts/orin-estimate.sh          # about 30 minutes on 2 cores (PRL-Track under qemu)
#   NANOTRACK_ONLY=1 bash scripts/orin-estimate.sh   # a few minutes
#
# 1. Instructions per step: the aarch64 `prl bench` (scripts/aarch64.sh build) runs under
#    `qemu-aarch64 -cpu cortex-a76` with an instruction-counting plugin
#    (scripts/qemu-insn-count.c), once with 1 and once with 3 timed tracking steps and one
#    template run each (`--template-runs 1`), on one thread: the difference over 2 is one
#    tracking step (crop + resize, search network, post-processing).
# 2. Cycles: the hot blocks through llvm-mca -mcpu=neoverse-n1 (a Cortex-A76 derivative and the
#    closest model LLVM has to the A78: LLVM's cortex-a78 uses the A57 model), 4-wide dispatch
#    (scripts/orin_estimate.py: L1 hits and predicted branches assumed).
# 3. Threads: the serial fraction s from this x86 machine's 1- and 2-thread search times
#    (T2 = T1·(s + (1-s)/2); the median of three alternations), applied to 8 cores:
#    T8 = T1·(s + (1-s)/8) (Amdahl; on the board memory bandwidth and the cluster's shared L3
#    may do worse). These timings are taken first,
#    for every plan, before the emulated counts load both cores.
#
# PRL-Track's fp32 plan is counted twice: direct convolutions (the default) and `prl compile
# --winograd all` (prl-fp32-wg; tract's operators alone have no Winograd, so that row is the
# runtime's only).
#
# Needs what scripts/aarch64.sh installs, plus Debian's llvm-19 (llvm-mca) and gcc; installs
# them when missing. Writes target/orin-estimate/ and prints one table.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
SHARED=${PRL_SHARED_DIR:-$ROOT/../shared}
W=$ROOT/target/orin-estimate
ARM=$ROOT/target/aarch64-unknown-linux-gnu/release/prl
HOST=$ROOT/target/release/prl
SEQ=$SHARED/data/uav123_10fps/building4

bash scripts/aarch64.sh build
if ! command -v llvm-mca-19 >/dev/null; then
    sudo=()
    [ "$(id -u)" = 0 ] || sudo=(sudo)
    "${sudo[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -qq llvm-19 >/dev/null
fi
cargo build --release --bin prl
mkdir -p "$W"
gcc -shared -fPIC -O2 -o "$W/insn-count.so" scripts/qemu-insn-count.c

plans=(nanotrack-fp32 nanotrack-int8 nanotrack-int8-dw)
source scripts/nanotrack-int8-recipe.sh
if [ ! -d "$W/nanotrack-int8" ]; then
    "$HOST" import nanotrack --out "$W/nanotrack-model"
    "$HOST" compile --model "$W/nanotrack-model" --out "$W/nanotrack-fp32"
    "$HOST" quantize --plan "$W/nanotrack-fp32" --calib "$SEQ" "${nanotrack_int8_recipe[@]}" \
        --out "$W/nanotrack-int8" >/dev/null
fi
if [ ! -d "$W/nanotrack-int8-dw" ]; then
    "$HOST" quantize --plan "$W/nanotrack-fp32" --calib "$SEQ" "${nanotrack_int8_dw_recipe[@]}" \
        --out "$W/nanotrack-int8-dw" >/dev/null
fi
if [ -z "${NANOTRACK_ONLY:-}" ]; then
    plans+=(prl-fp32 prl-fp32-wg prl-int8)
    if [ ! -d "$W/prl-int8" ]; then
        "$HOST" compile --checkpoint "$SHARED/fixtures/prl-golden-v1/checkpoint.pth" --out "$W/prl-fp32"
        "$HOST" quantize --plan "$W/prl-fp32" --calib "$SEQ" --frames-per-seq 16 --out "$W/prl-int8" >/dev/null
    fi
    if [ ! -d "$W/prl-fp32-wg" ]; then
        "$HOST" compile --checkpoint "$SHARED/fixtures/prl-golden-v1/checkpoint.pth" --winograd all \
            --out "$W/prl-fp32-wg"
    fi
fi

count() { # plan ops runs
    env PRL_OPS="$2" qemu-aarch64 -L /usr/aarch64-linux-gnu -cpu cortex-a76 -plugin "$W/insn-count.so" \
        -d plugin -D "$W/$1-$2-$3.txt" "$ARM" bench --plan "$W/$1" --sequence "$SEQ" --runs "$3" \
        --template-runs 1 --warm-up 0 --top 0 --threads 1 >/dev/null
}

# The serial fractions, from this machine (the runtime's operators), before anything else runs:
# one- and two-thread runs alternated three times, the median of the three fractions (this
# machine's second core is shared with other VMs: single pairs gave 0.07 to 0.49 for one plan).
# AMX is kept off (and the kernels capped at VNNI): the camera's int8 layers run dot-product
# kernels like VNNI's, and AMX's faster layers leave a larger serial share (an Intel Xeon with
# AMX on, 2026-12-06: int8 s 0.10-0.26, median 0.19).
declare -A serial
for p in "${plans[@]}"; do
    for i in 1 2 3; do
        for t in 1 2; do
            PRL_ISA=vnni TRACT_CPU_ISA=-amx-int8 "$HOST" bench --plan "$W/$p" --sequence "$SEQ" --runs 15 --top 0 \
                --threads $t --json "$W/$p-t$t-$i.json" >/dev/null
        done
    done
    serial[$p]=$(python3 -c "
import json, statistics
def search(f): return next(x['median_ms'] for x in json.load(open(f))['stages'] if x['stage'] == 'search network')
s = [2 * search('$W/$p-t2-%d.json' % i) / search('$W/$p-t1-%d.json' % i) - 1 for i in (1, 2, 3)]
print(min(1.0, max(0.0, statistics.median(s))))")
done

printf '%-16s %-8s %12s %8s %10s %6s %10s %8s\n' plan ops "M insn/step" "IPC" "ms 1 core" "s" "ms 8 core" "FPS"
for p in "${plans[@]}"; do
    s=${serial[$p]}
    opss=(runtime tract)
    [ "$p" = prl-fp32-wg ] && opss=(runtime)
    for ops in "${opss[@]}"; do
        # Two runs side by side (one emulated thread each).
        count "$p" "$ops" 1 &
        count "$p" "$ops" 3
        wait
        python3 scripts/orin_estimate.py "$ARM" "$W/$p-$ops-1.txt" "$W/$p-$ops-3.txt" 2 --json "$W/$p-$ops.json" >/dev/null
        python3 -c "
import json
r = json.load(open('$W/$p-$ops.json')); s = $s
ms1 = r['cycles_per_step'] / 2.0e6; ms8 = ms1 * (s + (1 - s) / 8)
print('%-16s %-8s %12.1f %8.2f %10.1f %6.2f %10.1f %8.1f' % ('$p', '$ops', r['instructions_per_step'] / 1e6, r['ipc_modelled'], ms1, s, ms8, 1e3 / ms8))"
    done
done
