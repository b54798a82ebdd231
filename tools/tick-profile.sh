#!/usr/bin/env bash
# Where a control tick's instructions go: runs the bench moves for one model under QEMU with a
# per-instruction trace (QEMU 7.2: `-singlestep -d exec,nochain`), then counts every instruction
# executed inside `Drive::control` by function and by source line (the innermost line of this
# workspace in the inline chain, via addr2line). Mean per tick; the total matches the bench's
# mean to within the call overhead.
#   tools/tick-profile.sh [MODEL]      # MODEL: none, model1, ..., model4 (default model3); per
#   function (mean and heaviest tick: `operator::eval` is Model 4's own cost), per source file
#   and per source line, the heaviest tick per source file and line, and every tick over 500
#   instructions with its largest source files
# Needs python3 and addr2line (binutils); the trace takes ~1 GB in $TMPDIR for ~10 s.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
model="${1:-model3}"
elf=target/thumbv7em-none-eabihf/release/belt-drive
trace="$(mktemp "${TMPDIR:-/tmp}/tick-trace.XXXXXX")"
trap 'rm -f "$trace"' EXIT
cargo fw-qemu --quiet
cargo build --profile ci --quiet -p hil-sim --bin qemu-run
BELT_QEMU_ARGS="-singlestep -d exec,nochain -D $trace" \
  target/ci/qemu-run --bench --model "$model" "$elf" | grep -E "^model|^[a-z0-9]+ \(" || true
python3 tools/tick-profile.py "$elf" "$trace"
