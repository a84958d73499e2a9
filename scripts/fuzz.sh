#!/bin/sh
# Fuzzes every file reader with cargo-fuzz (nightly toolchain; `cargo install cargo-fuzz`):
#   scripts/fuzz.sh                 all targets, 1,000,000 executions each
#   scripts/fuzz.sh 100000 bvh      one target, fewer executions
# Inputs that crash land in fuzz/artifacts/<target>/; what the fuzzer learns goes to
# fuzz/target/corpus/<target>/, the committed seeds in fuzz/corpus/ stay as they are.
set -eu
cd "$(dirname "$0")/../fuzz"
runs=${1:-1000000}
[ $# -gt 0 ] && shift
targets=${*:-"bvh deepmimic clip policy model stats rollout shard manifest config"}
# The fuzz binaries are built with cargo-fuzz's own RUSTFLAGS, without the rpath to MuJoCo.
export LD_LIBRARY_PATH="$PWD/../third_party/mujoco${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
# Inputs are written to a scratch file per execution: keep it in memory where possible.
[ -d /dev/shm ] && export TMPDIR=/dev/shm
for t in $targets; do
    mkdir -p "target/corpus/$t"
    echo "== $t: $runs executions"
    cargo +nightly fuzz run -O "$t" "target/corpus/$t" "corpus/$t" -- -runs="$runs" -print_final_stats=1 2>&1 |
        grep -E "^(#[0-9]+.*DONE|Done|stat::number_of_executed_units|stat::average_exec_per_sec)|ERROR|panicked|SUMMARY" || true
done
