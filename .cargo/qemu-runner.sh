#!/usr/bin/env bash
# Cargo runner for thumbv7em-none-eabihf: runs the ELF ($1) under QEMU with hil-sim's `qemu-run`
# (semihosting exit code, defmt decoded with the ELF's own table, timeout).
# Cargo's build lock is released before runners start, so building the host tool here is fine;
# an explicit host --target keeps the firmware's rustflags away from it.
set -euo pipefail
# QEMU_RUN_BIN: a `qemu-run` already built (CI sets it to the one its host build made: built
# here with an explicit target it would be a second build of hil-sim, about two minutes).
if [ -n "${QEMU_RUN_BIN:-}" ]; then
  exec "$QEMU_RUN_BIN" "$@"
fi
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
host="$(rustc -vV | sed -n 's/^host: //p')"
# QEMU_RUN_PROFILE: the profile qemu-run itself is built with (CI: `ci`, no fat LTO).
exec "${CARGO:-cargo}" run --quiet --profile "${QEMU_RUN_PROFILE:-release}" --manifest-path "$root/Cargo.toml" \
  -p hil-sim --bin qemu-run --target "$host" -- "$@"
