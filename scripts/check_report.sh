#!/usr/bin/env bash
# Opens each report.html given in headless Chromium: the page's own script must count
# every figure as shown (loaded, with a width), and a screenshot of the page must come
# out. Usage: scripts/check_report.sh DIR/report.html [...]; exit 1 on the first failure.
set -euo pipefail
browser=$(command -v chromium || command -v chromium-browser || command -v google-chrome || true)
if [ -z "$browser" ]; then
  echo "no Chromium to open the report with (apt-get install chromium)"; exit 1
fi
flags=(--headless --no-sandbox --disable-gpu --hide-scrollbars --virtual-time-budget=5000)
for page in "$@"; do
  url="file://$(realpath "$page")"
  dom=$("$browser" "${flags[@]}" --dump-dom "$url" 2>/dev/null)
  figures=$(grep -o 'data-figures="[0-9]*"' <<<"$dom" | grep -o '[0-9]\+' || echo 0)
  shown=$(grep -o 'data-shown="[0-9]*"' <<<"$dom" | grep -o '[0-9]\+' || echo 0)
  shot=$(mktemp --suffix=.png)
  "$browser" "${flags[@]}" --window-size=1400,2000 --screenshot="$shot" "$url" >/dev/null 2>&1
  size=$(stat -c %s "$shot")
  echo "$page: $shown of $figures figures shown in Chromium; screenshot $size bytes"
  if [ "$figures" -lt 4 ] || [ "$shown" != "$figures" ] || [ "$size" -lt 20000 ]; then
    echo "$page: the page does not show its figures"; exit 1
  fi
done
