#!/bin/bash
# The painter's paint job over CiA 402, bridge against our twin's drives, inside the vcan VM
# (docs/painting.md, "Over the protocol links"): config/protocol-paint.toml at RATE_HZ
# (default 50, what the software-emulated VM holds), ten drives on vcan0. Prints the run's
# summary and report and the twin's counts. Takes about four minutes.
#
#   bash scripts/canopen-paint-vm.sh            (after `cargo build --release`)
set -euo pipefail
cd "$(dirname "$0")/.."
rate=${RATE_HZ:-50}
bin=${CARGO_TARGET_DIR:-$PWD/target}/release/rigbridge
[ -x "$bin" ] || { echo "canopen-paint-vm: build first: cargo build --release" >&2; exit 1; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# The run settings name their rig and paint settings relative to their own folder.
cp config/painter.toml config/paint-small.toml "$work/"
sed "s/^rate_hz = .*/rate_hz = $rate/" config/protocol-paint.toml > "$work/run.toml"
cat > "$work/both.sh" <<SCRIPT
mkfifo /tmp/twin_in
$bin twin --canopen vcan0 --config $work/run.toml < /tmp/twin_in > /tmp/twin.out 2>&1 &
twin=\$!
exec 3>/tmp/twin_in
sleep 2
$bin run --config $work/run.toml --link "canopen://vcan0?nodes=1,2,3,4,5,6,7,8,9,10" \
  --report /tmp/run.json --log /tmp/run.mcap > /tmp/run.out 2>&1
status=\$?
kill -TERM \$twin
sleep 2
echo "--- run (exit \$status)"; cat /tmp/run.out
echo "--- twin"; cat /tmp/twin.out
echo "--- report"; cat /tmp/run.json
exit \$status
SCRIPT
VCANVM_FILES="$bin $work" VCANVM_TIMEOUT=${VCANVM_TIMEOUT:-900} \
  bash "${VCANVM_SCRIPT:-../shared/tools/run-in-vcan-vm.sh}" /bin/busybox sh "$work/both.sh"
