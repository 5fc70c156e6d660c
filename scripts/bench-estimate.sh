#!/bin/sh
# The estimation test bed (issue 16): every truth lens in LENSES (default ../shared/data/lenses
# next to the checkout) and the simulator's singlet at two chromatic strengths, estimated with the
# DEFAULT settings; prints median / p90 / max kernel error per lens and channel, cross-validation
# and wall / CPU seconds. Extra arguments go to `lensrig bench` (e.g. --only achromat, --large).
set -eu
here=$(cd "$(dirname "$0")/.." && pwd)
lenses=${LENSES:-$here/../shared/data/lenses}
cargo build --release --quiet --manifest-path "$here/Cargo.toml"
echo "commit $(git -C "$here" rev-parse --short HEAD); $(uptime)"
exec "$here/target/release/lensrig" bench --testbed "$lenses" "$@"
