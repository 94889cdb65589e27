#!/usr/bin/env python3
"""Times microstereo and OpenCV StereoSGBM (MODE_SGBM_3WAY) on the same images, same run.

Usage: python3 scripts/bench_vs_opencv.py [--repeat N]
Needs: pip install opencv-python-headless numpy; a release build (cargo build --release).
Prints per pair: SGBM-3WAY median ms, microstereo paper and quality median ms (whole
pipeline: both directions, LR check, post-processing), and the ratios.
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
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/microstereo"))
    a = ap.parse_args()
    cv2.setNumThreads(os.cpu_count() or 1)
    with tempfile.TemporaryDirectory() as tmp:
        js = os.path.join(tmp, "bench.json")
        subprocess.run([a.bin, "bench", "--repeat", str(a.repeat), "--json", js,
                        "--write-pairs", tmp], check=True)
        ours = json.load(open(js))
        pairs = {
            "cones": (os.path.join(ROOT, "tests/data/cones/im2.png"),
                      os.path.join(ROOT, "tests/data/cones/im6.png")),
            "synth1280": (os.path.join(tmp, "synth1280_left.png"),
                          os.path.join(tmp, "synth1280_right.png")),
        }
        print(f"\nOpenCV {cv2.__version__}, {cv2.getNumThreads()} threads; whole pipelines, median of {a.repeat}")
        print(f"{'pair':<10} {'SGBM-3WAY ms':>12} {'paper ms':>9} {'ratio':>6} {'quality ms':>10} {'ratio':>6}")
        for name, (l, r) in pairs.items():
            lines = {x["mode"]: x for x in ours if x["pair"] == name}
            if not lines:
                continue
            left = cv2.imread(l, cv2.IMREAD_GRAYSCALE)
            right = cv2.imread(r, cv2.IMREAD_GRAYSCALE)
            sg = time_sgbm(left, right, a.repeat)
            p, q = lines["paper"]["total_ms"], lines["quality"]["total_ms"]
            print(f"{name:<10} {sg:>12.1f} {p:>9.1f} {p / sg:>6.2f} {q:>10.1f} {q / sg:>6.2f}")


if __name__ == "__main__":
    sys.exit(main())
