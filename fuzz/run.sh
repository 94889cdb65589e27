#!/usr/bin/env bash
# Builds the fuzz targets with cargo-afl (AFL++ on the stable toolchain) and fuzzes each,
# one after the other: `fuzz/run.sh [EXECS] [SECONDS] [TARGET...]` stops a target at EXECS
# executions (default 1000000) or SECONDS (default 3600), whichever comes first. Prints
# executions, paths and crashes per target; every crash or hang found is copied to
# regressions/TARGET (which tests/fuzz_corpus.rs replays) and the script exits 3 (any
# other failure: the fuzzer could not be installed, built or started).
set -euo pipefail
cd "$(dirname "$0")"
execs=${1:-1000000}
secs=${2:-3600}
shift $(( $# > 2 ? 2 : $# ))
targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=(launch calibration pfm image mcap bridge_line)
if ! command -v cargo-afl >/dev/null; then
  cargo install cargo-afl --locked --version 0.18.2
fi
cargo afl build --release --quiet
export AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_UI=1 \
  AFL_NO_AFFINITY=1
found=0
printf '%-12s %10s %8s %8s %7s %6s %s\n' target execs execs/s paths crashes hangs seconds
mkdir -p out
for t in "${targets[@]}"; do
  out="out/$t"
  log="out/$t.log"
  rm -rf "$out"
  # The coverage map as large as the target's instrumentation asks, and never below the
  # runtime's own 64 KiB (a smaller shared map is written past its end).
  map=$(AFL_DUMP_MAP_SIZE=1 "target/release/$t" || true)
  export AFL_MAP_SIZE=$(( map > 65536 ? map : 65536 ))
  # A hang is an input that takes over a second (the readers take milliseconds;
  # FUZZ_TIMEOUT_MS sets another limit, e.g. on a loaded machine).
  # `-c -`: no CmpLog (cargo-afl asks for it; it needs a nightly build of the target).
  cargo afl fuzz -c - -t "${FUZZ_TIMEOUT_MS:-1000}" -E "$execs" -V "$secs" -i "corpus/$t" -o "$out" "target/release/$t" \
    >"$log" 2>&1 || { echo "afl-fuzz failed on $t:"; tail -20 "$log"; exit 1; }
  stats="$out/default/fuzzer_stats"
  get() { awk -F' *: *' -v k="$1" '$1 == k { print $2 }' "$stats"; }
  printf '%-12s %10s %8s %8s %7s %6s %s\n' "$t" "$(get execs_done)" "$(get execs_per_sec)" \
    "$(get corpus_count)" "$(get saved_crashes)" "$(get saved_hangs)" "$(get run_time)"
  for kind in crashes hangs; do
    for f in "$out/default/$kind"/id:*; do
      [ -e "$f" ] || continue
      found=1
      cp "$f" "regressions/$t/$kind-$(sha1sum "$f" | cut -c1-12)"
    done
  done
done
if [ "$found" -ne 0 ]; then
  echo "crashes or hangs found: copied to regressions/ (replayed by tests/fuzz_corpus.rs)"
  exit 3
fi
