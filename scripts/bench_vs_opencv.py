#!/usr/bin/env python3
"""Times microstereo and OpenCV StereoSGBM (MODE_SGBM_3WAY) on the same images, same run.

Usage: python3 scripts/bench_vs_opencv.py [--rounds N] [--repeat K] [--paths 4|8]
Needs: pip install opencv-python-headless numpy; a release build (cargo build --release).

The machines are shared and their speed drifts from one second to the next, so the two
are interleaved: each round runs `microstereo bench` (K runs per mode, median) and then K
SGBM runs (median) on each pair, and the ratio is taken within the round. Printed per pair:
the median over rounds of SGBM-3WAY ms, microstereo paper and quality ms (whole pipeline:
both directions, LR check, post-processing), and the median of the per-round ratios.
"""
import argparse, json, os, subprocess, sys, tempfile, time

import cv2
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def time_sgbm(left, right, repeat):
    # The settings of the anchor: 3-way, block 3, its filters on, left border padded.
    nd = 64
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=nd, blockSize=3, P1=8 * 3 * 3, P2=32 * 3 * 3,
        disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
        preFilterCap=63, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    lp = cv2.copyMakeBorder(left, 0, 0, nd, 0, cv2.BORDER_REPLICATE)
    rp = cv2.copyMakeBorder(right, 0, 0, nd, 0, cv2.BORDER_REPLICATE)
    runs = []
    for _ in range(repeat):
        t = time.perf_counter()
        sgbm.compute(lp, rp)
        runs.append((time.perf_counter() - t) * 1e3)
    return float(np.median(runs))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/microstereo"))
    ap.add_argument("--paths", choices=["4", "8"], help="SGM paths of quality mode")
    a = ap.parse_args()
    cv2.setNumThreads(os.cpu_count() or 1)
    rows = {}  # pair -> list of (sgbm, paper, quality) per round
    with tempfile.TemporaryDirectory() as tmp:
        js = os.path.join(tmp, "bench.json")
        images = {}
        for _ in range(a.rounds):
            paths = ["--paths", a.paths] if a.paths else []
            subprocess.run([a.bin, "bench", "--overwrite", "--repeat", str(a.repeat), "--json", js,
                            "--write-pairs", tmp] + paths, check=True, stdout=subprocess.DEVNULL)
            ours = json.load(open(js))
            if not images:
                for name, (l, r) in {
                    "cones": ("tests/data/cones/im2.png", "tests/data/cones/im6.png"),
                    "synth1280": (os.path.join(tmp, "synth1280_left.png"),
                                  os.path.join(tmp, "synth1280_right.png")),
                }.items():
                    images[name] = tuple(cv2.imread(os.path.join(ROOT, p), cv2.IMREAD_GRAYSCALE)
                                         for p in (l, r))
            for name, (left, right) in images.items():
                lines = {x["mode"]: x["total_ms"] for x in ours if x["pair"] == name}
                if len(lines) == 2:
                    sg = time_sgbm(left, right, a.repeat)
                    rows.setdefault(name, []).append((sg, lines["paper"], lines["quality"]))
    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; whole pipelines; "
          f"{a.rounds} interleaved rounds of {a.repeat} runs; quality with "
          f"{a.paths or 'the default'} paths")
    print(f"{'pair':<10} {'SGBM-3WAY ms':>12} {'paper ms':>9} {'ratio':>6} {'quality ms':>10} {'ratio':>6}")
    for name, r in rows.items():
        r = np.array(r)
        sg, p, q = np.median(r, axis=0)
        rp, rq = np.median(r[:, 1] / r[:, 0]), np.median(r[:, 2] / r[:, 0])
        print(f"{name:<10} {sg:>12.1f} {p:>9.1f} {rp:>6.2f} {q:>10.1f} {rq:>6.2f}")


if __name__ == "__main__":
    sys.exit(main())
