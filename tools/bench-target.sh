#!/usr/bin/env bash
# On-target benchmark of the firmware under QEMU (netduinoplus2, -icount shift=0):
# Drive::control instructions per control tick for each model (PIL runs checked tick by tick
# against the in-process core), flash and static RAM of the release ELF, peak stack.
#   tools/bench-target.sh            # table on stdout, non-zero exit if a run fails or differs;
#                                    # the last line is one JSON object with every figure
#   tools/bench-target.sh --check tools/bench-target.json
#                                    # also fails when a figure exceeds the checked-in one (CI)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo fw-qemu --quiet
exec cargo run --release --quiet -p hil-sim --bin qemu-run -- --bench "$@"
