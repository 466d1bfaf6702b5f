#!/usr/bin/env bash
# ONNX Runtime against prl on the same emitted graphs, interleaved in one run (see README.md here).
# Sets up ONNX Runtime from PyPI in a local virtual environment the first time.
set -euo pipefail
cd "$(dirname "$0")/../.."
venv="${PRL_PEER_VENV:-target/peers/venv}"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import onnxruntime, numpy, onnx" 2>/dev/null; then
    echo "setting up ONNX Runtime in $venv" >&2
    python3 -m venv "$venv"
    "$venv/bin/pip" install --quiet --upgrade onnxruntime numpy onnx  # onnx: ORT's quantiser needs it
fi
cargo build --release --quiet --bin prl
exec "$venv/bin/python" benches/peers/onnxruntime_peer.py --prl target/release/prl "$@"
