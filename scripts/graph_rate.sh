#!/usr/bin/env bash
# The default graph's throughput, two builds side by side: each runs the built-in graph
# with its camera at 60 frames/s (above what the graph takes, so the entrance sets the
# pace) for 450 frames, in turn, three times; prints each run's sustained rate and the
# ratio of the medians. Usage: scripts/graph_rate.sh OLD_BINARY NEW_BINARY
set -euo pipefail
old=${1:?usage: scripts/graph_rate.sh OLD_BINARY NEW_BINARY}
new=${2:?usage: scripts/graph_rate.sh OLD_BINARY NEW_BINARY}
rate() {
  "$1" run --quiet --frames 450 --instance "graphrate$$" --set capture.fps=60 \
    --set manipulator-bridge.listen=127.0.0.1:0 2>&1 |
    grep -o 'sustained [0-9.]* frames/s' | grep -o '[0-9.]*'
}
olds=() news=()
for i in 1 2 3; do
  o=$(rate "$old"); n=$(rate "$new")
  echo "run $i: old $o frames/s, new $n frames/s"
  olds+=("$o"); news+=("$n")
done
median() { printf '%s\n' "$@" | sort -g | sed -n 2p; }
mo=$(median "${olds[@]}"); mn=$(median "${news[@]}")
echo "median: old $mo, new $mn frames/s; new/old $(awk -v a="$mn" -v b="$mo" 'BEGIN { printf "%.3f", a / b }')"
