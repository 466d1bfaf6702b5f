#!/usr/bin/env bash
# Fuzz every parser of files a user or a model supplies (cargo fuzz / libFuzzer, see fuzz/).
#
#   bash scripts/fuzz.sh [SECONDS] [TARGET...]     # default: 60 s for each of the targets
#   PRL_FUZZ_RUNS=10000000 bash scripts/fuzz.sh 86400 checkpoint   # stop at 10M executions
#   PRL_FUZZ_PROFILE=dev bash scripts/fuzz.sh 15    # unoptimised targets (CI's smoke run)
#
# Installs cargo-fuzz if missing (from crates.io; a stable toolchain: targets are built with
# `--sanitizer none`, and fuzz/src/lib.rs caps single allocations at 1 GiB), seeds each corpus
# from ../shared (fuzz/seeds.py; the plan target's plan is compiled there from the tiny ONNX
# pair it writes), runs each target for SECONDS with a 1 s hang limit and a 2 GiB memory limit,
# and prints one line per target: seconds taken, executions, executions per second, corpus size
# and findings. PRL_FUZZ_RUNS=N stops a target after N executions (or SECONDS, whichever is
# first). Targets are optimised, with debug assertions and overflow checks (cargo fuzz's
# default). PRL_FUZZ_PROFILE=dev builds them unoptimised (cargo fuzz --dev): half the build
# time (5.1-6.5 against 12.3 minutes on 2 cores of an AMD EPYC), at 1/4 to 1/30 of the
# executions a second, with a 10 s hang limit: for short smoke runs; long runs keep the default.
# Findings (crash, timeout, out-of-memory inputs) are in fuzz/artifacts/<target>/; the exit
# status is non-zero when there are any. Corpora grow in target/fuzz-corpus/ across runs.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-60}
shift || true
all=(checkpoint pickle plan onnx_import boxes pysot_json frame)
targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=("${all[@]}")
shared=${PRL_SHARED:-$(cd .. && pwd)/shared}
work=target/fuzz-work
corpus=target/fuzz-corpus
mkdir -p "$work" "$corpus"

command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
command -v ffmpeg >/dev/null || { apt-get update -qq && apt-get install -y -qq ffmpeg >/dev/null; }

# Seeds, and the plan target's plan: the tiny backbone and head seeds.py writes (the smallest
# pair fitting NanoTrack's contract), imported and compiled by seeds.py with prl, so that each
# execution loads a plan of a few kilobytes. PRL_BIN=path/to/prl uses that binary instead of
# building one.
if [ ! -f "$work/seeds.done" ] || [ ! -d "$work/seeds/tiny/plan" ]; then
    source scripts/prl-bin.sh
    use_prl dev
    rm -rf "$work/seeds"
    python3 fuzz/seeds.py "$shared" "$work/seeds" "$prl"
    touch "$work/seeds.done"
fi
plan=$(cd "$work/seeds/tiny/plan" && pwd)

# cargo fuzz's default is optimised with debug assertions and overflow checks (and one codegen
# unit, which makes its build the slow one); its `--release` flag would drop the assertions, so
# the default passes no flag. PRL_FUZZ_PROFILE=dev: `--dev`, unoptimised, assertions on.
case "${PRL_FUZZ_PROFILE:-release}" in
    release) profile=() hang=1 ;;
    dev) profile=(--dev) hang=10 ;;
    *) echo "error: PRL_FUZZ_PROFILE must be release or dev, not '$PRL_FUZZ_PROFILE'" >&2; exit 2 ;;
esac
cargo fuzz build "${profile[@]}" -s none

status=0
printf '%-12s %8s %12s %10s %8s %s\n' target seconds executions "exec/s" corpus findings
for t in "${targets[@]}"; do
    mkdir -p "$corpus/$t" "fuzz/artifacts/$t"
    cp -n "$work/seeds/$t"/* "$corpus/$t/" 2>/dev/null || true
    before=$(ls "fuzz/artifacts/$t" | wc -l)
    log="$work/$t.log"
    start=$SECONDS
    PRL_FUZZ_PLAN="$plan" PRL_SHARED="$shared" cargo fuzz run "${profile[@]}" -s none "$t" "$corpus/$t" -- \
        -max_total_time="$seconds" ${PRL_FUZZ_RUNS:+-runs="$PRL_FUZZ_RUNS"} -timeout=$hang -rss_limit_mb=2048 -print_final_stats=1 \
        -artifact_prefix="fuzz/artifacts/$t/" >"$log" 2>&1 || true
    took=$((SECONDS - start))
    runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' | tail -1)
    runs=${runs:-0}
    found=$(( $(ls "fuzz/artifacts/$t" | wc -l) - before ))
    if [ "$found" -gt 0 ] || ! grep -q 'stat::number_of_executed_units' "$log"; then
        status=1
        grep -E 'panicked|ERROR|SUMMARY|Test unit written|allocation over' "$log" | head -5 >&2 || tail -20 "$log" >&2
    fi
    printf '%-12s %8s %12s %10s %8s %s\n' "$t" "$took" "$runs" "$((runs / (took > 0 ? took : 1)))" \
        "$(ls "$corpus/$t" | wc -l)" "$found"
done
exit $status
