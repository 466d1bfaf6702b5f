# Sourced by the scripts that run `prl` (soak.sh, int8-spread.sh, fuzz.sh): `use_prl PROFILE`
# sets $prl to $PRL_BIN when the environment names a binary, else builds the `prl` of PROFILE
# (`release` or `dev`) and sets $prl to it.
use_prl() {
    if [ -n "${PRL_BIN:-}" ]; then
        prl=$PRL_BIN
    elif [ "$1" = dev ]; then
        cargo build -q --bin prl
        prl=target/debug/prl
    else
        cargo build -q --release --bin prl
        prl=target/release/prl
    fi
}
