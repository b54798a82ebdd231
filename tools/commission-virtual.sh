#!/usr/bin/env bash
# Commissions a virtual drive end to end, as a machine builder would a board on a USB-serial
# adapter: the firmware under QEMU on a simulated stage that is not the paper rig (a 19.2:1
# gearbox), its link on a pseudo-terminal, driven only by `beltctl`.
#
#   1. a fresh storage file: the drive boots unconfigured and refuses to enable;
#   2. beltctl: configuration (tools/commission-config.toml), enable, homing onto the end stop,
#      calibration with the linear scale fitted (recorded on the drive, fitted on the host with
#      hil-sim's fitting code), upload, read-back check; then validation: every compensator
#      places the carriage on the moves of tools/commission-validate.toml, and the one with the
#      lowest arrival RMS on the scale becomes the drive's initial model; save;
#   3. the virtual drive is stopped and started again on the same storage file;
#   4. it must boot configured with the saved record and the chosen model, home, and place the
#      carriage on other targets with it.
#
# Last line: one JSON object (saved_crc, loaded_crc_after_restart, homed, targets,
# arrival_rms_um, arrival_max_um, model, validation_rms_um, coverage_warnings); arrival = the
# scale's reading at rest minus the target; validation_rms_um: each compensator's arrival RMS in
# step 2; coverage_warnings: the validation's and the placement's warnings about moves outside
# the region the calibration covered.
# Environment: COMMISSION_PROFILE (cargo profile, default ci), COMMISSION_KEEP=1 keeps the work
# directory (logs, calibration, plots), COMMISSION_SPEED (the virtual drive's plant time per wall
# time, default 2: twice real time, so that beltctl's longest silence counts double against the
# drive's 0.5 s link watchdog, a margin check as well as half the wait).
set -euo pipefail
cd "$(dirname "$0")/.."

profile=${COMMISSION_PROFILE:-ci}
speed=${COMMISSION_SPEED:-2}
cargo build --profile "$profile" -q -p hil-sim -p belt-tool
elf=target/thumbv7em-none-eabihf/release/belt-drive
[ -f "$elf" ] || cargo fw-qemu
hil_sim=target/$profile/hil-sim
beltctl=target/$profile/beltctl

work=$(mktemp -d "${TMPDIR:-/tmp}/commission.XXXXXX")
store=$work/storage.bin
port=$work/drive
vd_pid=
finish() {
    if [ -n "$vd_pid" ]; then kill "$vd_pid" 2>/dev/null || true; wait "$vd_pid" 2>/dev/null || true; fi
    if [ "${COMMISSION_KEEP:-0}" = 1 ]; then echo "work directory kept: $work" >&2; else rm -rf "$work"; fi
}
trap finish EXIT

# The simulated stage: the paper rig's plant with a 19.2:1 gearbox.
sed 's/^ratio = 23.7222 .*/ratio = 19.2/' hil-sim/presets/paper-rig.toml > "$work/plant.toml"
grep -q '^ratio = 19.2$' "$work/plant.toml"

start_drive() { # $1: log name, $2: where the carriage stands at power-on (mm)
    rm -f "$port"
    "$hil_sim" virtual-drive --plant "$work/plant.toml" --storage "$store" --link "$port" \
        --start-mm "$2" --speed "$speed" --log "$work/$1.log" > "$work/$1.out" 2> "$work/$1.err" &
    vd_pid=$!
    for _ in $(seq 1 200); do
        [ -e "$port" ] && return 0
        kill -0 "$vd_pid" 2>/dev/null || { cat "$work/$1.err" >&2; echo "virtual drive died" >&2; exit 1; }
        sleep 0.1
    done
    echo "virtual drive: no link after 20 s" >&2
    exit 1
}
stop_drive() {
    kill -TERM "$vd_pid"
    wait "$vd_pid" || true
    vd_pid=
}
json_field() { # $1: JSON text, $2: key -> the raw value
    python3 -c 'import json,sys; v=json.loads(sys.argv[1])[sys.argv[2]]; print(json.dumps(v) if not isinstance(v,str) else v)' "$1" "$2"
}
ctl() { "$beltctl" --port "$port" "$@"; }

echo "== 1. first power-on, fresh storage ($store)" >&2
start_drive drive1 120
status=$(ctl status --json)
echo "$status" >&2
[ "$(json_field "$status" configured)" = false ] || { echo "a fresh drive must boot unconfigured" >&2; exit 1; }
if ctl enable 2>"$work/enable.err"; then
    echo "an unconfigured drive enabled" >&2; exit 1
fi
echo "refused as it must be: $(cat "$work/enable.err")" >&2

echo "== 2. configure, home, calibrate, save" >&2
ctl config load tools/commission-config.toml
ctl enable
ctl home
# The machine's geometry and motor (its plant file; the belt's, friction's and carriage's
# physics are identified from the paper rig's) give Model 4's belt observer.
ctl calibrate --out "$work/calibration" --machine "$work/plant.toml" --json \
    | tee "$work/calibrate.json" >&2
# The upload left the drive disabled, still homed.
ctl enable
validation=$(ctl validate --scenario tools/commission-validate.toml --select --json \
    --calibration "$work/calibration" 2> "$work/validate.err") || { cat "$work/validate.err" >&2; exit 1; }
# At once: an enabled drive with no host for 0.5 s of drive time (0.25 s of wall time here)
# stops on its link watchdog, and the parsing below takes a Python start or two.
ctl disable
cat "$work/validate.err" >&2
echo "$validation" >&2
model=$(json_field "$validation" best)
ctl config set "drive.initial_model=$(json_field "$validation" initial_model)"
saved=$(ctl config save --json)
echo "$saved" >&2
saved_crc=$(json_field "$saved" crc)

echo "== 3. restart on the same storage" >&2
stop_drive
start_drive drive2 200
status=$(ctl status --json)
echo "$status" >&2
[ "$(json_field "$status" configured)" = true ] || { echo "the drive did not boot configured" >&2; exit 1; }
[ "$(json_field "$status" model)" = "$model" ] || { echo "the drive did not boot with $model" >&2; exit 1; }
loaded_crc=$(json_field "$status" record_crc)

echo "== 4. home and place the carriage" >&2
ctl enable
homed=false
ctl home && homed=true
ctl move 25 180 60 240 120 40 --json --calibration "$work/calibration" > "$work/moves.json" \
    2> "$work/moves.err" || { cat "$work/moves.err" >&2; exit 1; }
ctl disable
cat "$work/moves.err" >&2
# Moves outside the region the calibration covered (every model extrapolates there).
warnings=$(cat "$work/validate.err" "$work/moves.err" | grep -c '^beltctl: warning:' || true)
cat "$work/moves.json" >&2
summary=$(tail -n 1 "$work/moves.json")
stop_drive

# Nothing in the whole commissioning may trip the drive: a fault here (a link watchdog the host
# let starve, a following error on a calibration move) is a defect of beltctl or the firmware.
if grep -h "fault raised" "$work"/drive*.log >&2; then
    echo "the drive raised a fault during commissioning (above)" >&2
    exit 1
fi

python3 - "$saved_crc" "$loaded_crc" "$homed" "$summary" "$model" "$validation" "$warnings" <<'EOF'
import json, sys
saved, loaded, homed, summary = sys.argv[1], sys.argv[2], sys.argv[3] == "true", json.loads(sys.argv[4])
model, validation, warnings = sys.argv[5], json.loads(sys.argv[6]), int(sys.argv[7])
print(json.dumps({
    "saved_crc": saved,
    "loaded_crc_after_restart": loaded,
    "homed": homed,
    "targets": summary["count"],
    "arrival_rms_um": round(summary["rms_um"], 2),
    "arrival_max_um": round(summary["max_um"], 2),
    "model": model,
    "validation_rms_um": {k: round(v, 2) for k, v in validation["arrival_rms_um"].items()},
    "coverage_warnings": warnings,
}))
EOF
