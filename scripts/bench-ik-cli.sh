#!/usr/bin/env bash
# Whole-process IK comparison on one CSV job: `rigbridge ik` (the FABRIK planner) against
# examples/opw_csv.rs (rs-opw-kinematics' closed form doing the same job: nearest in-limit
# answer to the previous row's, verified by our FK, same output columns).
#
#   scripts/bench-ik-cli.sh [COUNT]     # COUNT poses, default 100000
#
# Environment: CARGO_TARGET_DIR (default target), RUNS (timed runs per tool, default 3),
# SEED (pose generator seed, default 7), KEEP_DIR (keep the CSVs there instead of a temp dir).
# Times with hyperfine when installed, else /usr/bin/time -f %e (median of RUNS runs, after
# one untimed warm-up run each). Prints both times and the ratio rigbridge/opw.
set -euo pipefail
cd "$(dirname "$0")/.."

count="${1:-100000}"
runs="${RUNS:-3}"
seed="${SEED:-7}"
target="${CARGO_TARGET_DIR:-target}"
rig=config/irb120.toml

cargo build --release --quiet --bin rigbridge --example opw_csv --example gen_poses
rigbridge="$target/release/rigbridge"
opw_csv="$target/release/examples/opw_csv"
gen_poses="$target/release/examples/gen_poses"

if [[ -n "${KEEP_DIR:-}" ]]; then
  work="$KEEP_DIR"
  mkdir -p "$work"
else
  work="$(mktemp -d)"
  trap 'rm -rf "$work"' EXIT
fi

"$gen_poses" --rig "$rig" --count "$count" --seed "$seed" --output "$work/poses.csv"
echo "poses: $count FK poses of seeded random in-limit configurations (seed $seed), $work/poses.csv"

fabrik_cmd="$rigbridge ik --rig $rig --input $work/poses.csv --output $work/fabrik.csv"
opw_cmd="$opw_csv --rig $rig --input $work/poses.csv --output $work/opw.csv"

if command -v hyperfine >/dev/null 2>&1; then
  hyperfine --warmup 1 --runs "$runs" --export-csv "$work/hyperfine.csv" \
    -n rigbridge "$fabrik_cmd" -n opw_csv "$opw_cmd"
  # Columns: command,mean,stddev,median,user,system,min,max
  fabrik_s="$(awk -F, '$1 == "rigbridge" { print $4 }' "$work/hyperfine.csv")"
  opw_s="$(awk -F, '$1 == "opw_csv" { print $4 }' "$work/hyperfine.csv")"
  timer="hyperfine, median of $runs"
else
  # Median wall time (s) of $runs runs of a command, after one untimed run.
  median_time() {
    local cmd="$1" log="$2"
    $cmd 2>"$log"
    for _ in $(seq "$runs"); do
      /usr/bin/time -f %e -o "$work/time" $cmd 2>>"$log"
      cat "$work/time"
    done | sort -g | awk '{ t[NR] = $1 } END { print (NR % 2) ? t[(NR + 1) / 2] : (t[NR / 2] + t[NR / 2 + 1]) / 2 }'
  }
  fabrik_s="$(median_time "$fabrik_cmd" "$work/fabrik.log")"
  opw_s="$(median_time "$opw_cmd" "$work/opw.log")"
  timer="/usr/bin/time -f %e, median of $runs"
fi

ok_rows() { awk -F, 'NR > 1 && $NF == "ok"' "$1" | wc -l; }
# Rows where both answered and every joint agrees within 1e-6 deg.
agree="$(paste -d, "$work/fabrik.csv" "$work/opw.csv" | awk -F, '
  NR > 1 && $10 == "ok" && $20 == "ok" {
    same = 1
    for (i = 1; i <= 6; i++) { d = $i - $(i + 10); if (d < -1e-6 || d > 1e-6) same = 0 }
    n += same
  }
  END { print n + 0 }')"

echo "timer: $timer"
printf '%-10s %10s %12s\n' tool "wall s" "ok rows"
printf '%-10s %10s %12s\n' rigbridge "$fabrik_s" "$(ok_rows "$work/fabrik.csv")/$count"
printf '%-10s %10s %12s\n' opw_csv "$opw_s" "$(ok_rows "$work/opw.csv")/$count"
echo "same answer (all joints within 1e-6 deg): $agree/$count rows"
awk -v f="$fabrik_s" -v o="$opw_s" -v n="$count" 'BEGIN {
  printf "per pose, whole process: rigbridge %.3f us, opw_csv %.3f us\n", 1e6 * f / n, 1e6 * o / n
  printf "ratio rigbridge/opw_csv = %.2f\n", f / o
}'
