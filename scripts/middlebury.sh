#!/usr/bin/env bash
# Runs `reconstruct` + `eval` on the four Middlebury sets and prints bad-1 (non-occluded).
# Usage: scripts/middlebury.sh DATA_DIR MODE [extra reconstruct args...]
set -euo pipefail
data=${1:?data dir}; mode=${2:?mode}; shift 2
bin=${MICROSTEREO:-target/release/microstereo}
out=${OUT:-/tmp/microstereo-mb}
sum=0
for set in cones cloth3 reindeer wood2; do
  d=$data/$set
  if [ "$set" = cones ]; then l=im2.png r=im6.png gl=disp2.png gr=disp6.png s=4 max=63
  else l=view1.png r=view5.png gl=disp1.png gr=disp5.png s=2 max=127; fi
  "$bin" reconstruct "$d/$l" "$d/$r" -o "$out/$mode/$set" --overwrite --mode "$mode" \
     --min-disparity 0 --max-disparity $max "$@" > /dev/null
  b=$("$bin" eval "$out/$mode/$set/disparity.pfm" --gt "$d/$gl" --gt-scale $s \
       --gt-right "$d/$gr" --json | python3 -c 'import json,sys; print(json.load(sys.stdin)["nonocc"]["bad_1"])')
  ms=$(python3 -c "import json; print(round(json.load(open('$out/$mode/$set/report.json'))['total_ms'],1))")
  printf "%-9s bad-1 %6.2f %%   %s ms\n" "$set" "$b" "$ms"
  sum=$(python3 -c "print($sum + $b)")
done
python3 -c "print('mean      bad-1 %6.2f %%' % ($sum / 4))"
