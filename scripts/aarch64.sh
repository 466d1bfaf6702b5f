#!/usr/bin/env bash
# The edge build: `prl` and `prl-runtime` cross-compiled for aarch64-unknown-linux-gnu (the
# Jetson Orin NX's Cortex-A78AE cores) on an x86_64 Debian/Ubuntu machine, and checked under
# qemu's user-mode emulation.
#
#   bash scripts/aarch64.sh build   # -> target/aarch64-unknown-linux-gnu/release/prl
#   bash scripts/aarch64.sh test    # build, then check under qemu
#
# Installs what it needs when missing: the Rust target (rustup), Debian's gcc-aarch64-linux-gnu,
# libc6-dev-arm64-cross and qemu-user (apt-get; run as root or with sudo).
#
# `test`, with `../shared` beside the repository ($PRL_SHARED_DIR elsewhere):
#   1. on x86: compile the reference PRL-Track checkpoint, NanoTrack v2 fp32 and an int8
#      NanoTrack plan, and record each plan's inputs and outputs on one real crop;
#   2. under `qemu-aarch64 -cpu cortex-a76` (dot product and fp16, no i8mm, like the A78AE):
#      the runtime's unit tests (every kernel path against its reference), each x86 plan
#      against its x86 recording (`prl verify --plan --tensors`: plans are portable; the
#      int8 plan must run integer kernels), and the golden drift trace on the x86 plan (boxes
#      within 0.05 px of the official tracker's, as on x86).
# Timings under qemu mean nothing; correctness does.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
TARGET=aarch64-unknown-linux-gnu
SHARED=${PRL_SHARED_DIR:-$ROOT/../shared}
QEMU_CPU=${QEMU_CPU:-cortex-a76}

install_tools() {
    if ! rustup target list --installed | grep -qx "$TARGET"; then
        rustup target add "$TARGET"
    fi
    local need=()
    command -v aarch64-linux-gnu-gcc >/dev/null || need+=(gcc-aarch64-linux-gnu)
    [ -e /usr/aarch64-linux-gnu/lib/libc.so.6 ] || need+=(libc6-dev-arm64-cross)
    command -v qemu-aarch64 >/dev/null || need+=(qemu-user)
    if ((${#need[@]})); then
        local sudo=()
        [ "$(id -u)" = 0 ] || sudo=(sudo)
        echo "installing ${need[*]}"
        "${sudo[@]}" apt-get update -qq
        DEBIAN_FRONTEND=noninteractive "${sudo[@]}" apt-get install -y -qq "${need[@]}" >/dev/null
    fi
}

cross_env() {
    export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
    export CC_aarch64_unknown_linux_gnu=aarch64-linux-gnu-gcc
    export AR_aarch64_unknown_linux_gnu=aarch64-linux-gnu-ar
    export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER="qemu-aarch64 -L /usr/aarch64-linux-gnu -cpu $QEMU_CPU"
}

build() {
    install_tools
    cross_env
    cargo build --release --target "$TARGET" --bin prl
    echo "built target/$TARGET/release/prl (copy it and a plan folder to the camera: docs/deploy-orin.md)"
}

check() {
    install_tools
    cross_env
    # One aarch64 build serves every check: the runtime's and the library's unit tests, the
    # tracker test and the `prl` binary it needs (built with the tests' features; separate
    # `cargo build` and `cargo test -p prl-runtime` runs would each rebuild tract, CI's cores
    # cannot spare that). `bash scripts/aarch64.sh build` is the release binary to ship.
    local select=(--release --target "$TARGET" -p prl-runtime -p prl-track)
    cargo test "${select[@]}" --lib --test tracker --no-run
    local work=$ROOT/target/aarch64-check
    # The x86 side only compiles and records plans: the dev build (what `cargo test --workspace`
    # builds; its dependencies and the runtime are optimised) serves, and CI has it already.
    local host=$ROOT/target/debug/prl
    local arm=$ROOT/target/$TARGET/release/prl
    local golden=$SHARED/fixtures/prl-golden-v1
    local calib=$SHARED/data/uav123_10fps/building4
    rm -rf "$work"
    mkdir -p "$work"
    cargo test --workspace --no-run
    echo "== x86: plans and their recorded outputs"
    "$host" compile --checkpoint "$golden/checkpoint.pth" --out "$work/prl-plan"
    "$host" import nanotrack --out "$work/nanotrack-model"
    "$host" compile --model "$work/nanotrack-model" --out "$work/nanotrack-plan"
    "$host" quantize --plan "$work/nanotrack-plan" --calib "$calib" --frames-per-seq 16 --method minmax \
        --budget 4 --min-macs 1000000 --min-out-channels 16 --depthwise --out "$work/nanotrack-int8" >/dev/null
    # Every plan is recorded with the runtime's own operators. The int8 plan's integer layers
    # run as PackedQConv and DepthwiseQConv (`--depthwise`) on both sides (on aarch64 on SDOT,
    # the pointwise ones in the channels-last layouts tract gives NanoTrack's layers there),
    # exact sums requantised alike, so they give the same bytes where the f32 layers between
    # them do. `PRL_OPS=tract-int8` records with tract's integer
    # products instead (they requantise as PackedQConv does).
    for p in prl-plan nanotrack-plan nanotrack-int8; do
        "$host" bench --plan "$work/$p" --runs 1 --top 0 --sequence "$golden/seq_drift" \
            --save-tensors "$work/$p-rec" >/dev/null
    done
    local qemu=(qemu-aarch64 -L /usr/aarch64-linux-gnu -cpu "$QEMU_CPU")
    echo "== aarch64 (qemu -cpu $QEMU_CPU): the runtime's unit tests, NEON and portable paths"
    cargo test "${select[@]}" --lib
    PRL_ISA=generic cargo test "${select[@]}" --lib
    echo "== aarch64: x86 plans against their x86 recordings"
    for p in prl-plan nanotrack-plan; do
        "${qemu[@]}" "$arm" verify --plan "$work/$p" --tensors "$work/$p-rec" --tolerance 1e-4
    done
    # int8: the integer products are exact on both; the f32 layers between them differ in
    # their last bits, which can move an activation across a quantisation step.
    "${qemu[@]}" "$arm" verify --plan "$work/nanotrack-int8" --tensors "$work/nanotrack-int8-rec" \
        --tolerance 1e-3 | tee "$work/int8-verify.txt"
    if ! grep -Eq '^integer products: [1-9][0-9]* nodes' "$work/int8-verify.txt"; then
        echo "error: the int8 plan runs no integer kernel on aarch64" >&2
        exit 1
    fi
    # A PRL-Track frame takes seconds under qemu: AARCH64_TRACE_FRAMES bounds the frames checked
    # (CI checks the first 6 of 40); unset, the whole trace.
    echo "== aarch64: the golden drift trace on the x86 plan (${AARCH64_TRACE_FRAMES:-all} frames, 2 threads)"
    PRL_GOLDEN_DIR=$golden PRL_REFERENCE_PLAN=$work/prl-plan PRL_TEST_THREADS=2 \
        PRL_TRACE_FRAMES=${AARCH64_TRACE_FRAMES:-1000000} \
        cargo test "${select[@]}" --test tracker drift_sequence_matches_the_official_tracker -- --nocapture
    echo "aarch64 checks passed"
}

case "${1:-}" in
    build) build ;;
    test) check ;;
    *)
        echo "usage: bash scripts/aarch64.sh build|test" >&2
        exit 2
        ;;
esac
