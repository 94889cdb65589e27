#!/usr/bin/env bash
# Segments every reference cell image and prints Dice and the cell-count error against its
# ground truth. Usage: scripts/cells_dice.sh [CELLS_DIR]   (default ../shared/data/cells)
# BBBC003's truth TIFFs are CCITT-compressed, which the Rust TIFF decoder cannot read, so
# they are converted to PNG with Pillow first (pip install pillow). Pillow applies the
# files' WhiteIsZero photometric tag: the embryo, stored as 0 bits, comes out white.
set -euo pipefail
data=${1:-../shared/data/cells}
bin=${MICROSTEREO:-target/release/microstereo}
out=${OUT:-/tmp/microstereo-cells}
mkdir -p "$out/truth"
for img in "$data"/bbbc030/cho*[0-9].png; do
  n=$(basename "$img" .png)
  printf "%-12s " "$n"
  "$bin" segment "$img" -o "$out/$n" --overwrite --truth "$data/bbbc030/${n}_mask.png" | grep truth
done
for img in "$data"/bbbc003/*[0-9].tif; do
  n=$(basename "$img" .tif)
  python3 -c "from PIL import Image; Image.open('$data/bbbc003/${n}_truth.tif').convert('L').save('$out/truth/$n.png')"
  printf "%-12s " "$n"
  # Embryos (~100 µm) at this magnification cover ~25 000 px; debris stays under 1000.
  "$bin" segment "$img" -o "$out/$n" --overwrite --truth "$out/truth/$n.png" --min-area 2000 | grep truth
done
