#!/usr/bin/env bash
# Regenerates recordings/default.mcap: the embedded default graph (launch.toml) with its
# synthetic capture at 640×512 and 5 cells (recordings/default.toml; the full 1280×1024
# frame makes 18 MB of compressed edges per frame), two frames, every edge recorded.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo run --release -- run recordings/default.toml --frames 2 \
  --record recordings/default.mcap --overwrite
cargo run --release -- inspect recordings/default.mcap
