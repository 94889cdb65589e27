#!/usr/bin/env python3
"""The default graph against what a lab engineer would write with OpenCV, on the same frames,
in the same run (issue 20's anchor).

Usage: python3 scripts/graph_vs_opencv.py [--frames N] [--rounds R]
Needs: pip install opencv-python-headless numpy; a release build (cargo build --release).

`microstereo synth` renders N frames of the default scene (1280×1024, 10 drifting cells) to
PNG pairs. Each round then runs, in turn:
- the default graph (launch.toml, one process per node) with its capture reading those
  files as fast as it can (`source = "files"`; the entrance drops what the graph cannot
  take), and reads its summary's frames/s and capture → last output latency;
- an OpenCV loop over the same files with 2 threads: read both views, StereoSGBM-3WAY on
  the full frame (16 disparities, block 3), and on each view local variance (box filters of
  I and I², window 2·3+1 as the graph's segment) → 0–255 → Otsu → connected components →
  external contours.
Printed per round: both rates and the graph's over OpenCV's; then the medians. The machines
are shared and their speed drifts, so only the ratio within a round means much.
"""
import argparse, glob, os, re, statistics, subprocess, sys, tempfile, time

import cv2
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RADIUS = 3


def segment(img):
    f = img.astype(np.float32)
    k = (2 * RADIUS + 1, 2 * RADIUS + 1)
    mean = cv2.boxFilter(f, -1, k, borderType=cv2.BORDER_REFLECT)
    sq = cv2.boxFilter(f * f, -1, k, borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(sq - mean * mean, 0))
    norm = cv2.normalize(np.log1p(std), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    _, mask = cv2.threshold(norm, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return n - 1, len(contours)


def opencv_loop(pairs):
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=16, blockSize=3,
                                 P1=8 * 9, P2=32 * 9, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    t = time.perf_counter()
    for lp, rp in pairs:
        left = cv2.imread(lp, cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(rp, cv2.IMREAD_GRAYSCALE)
        sgbm.compute(left, right)
        segment(left)
        segment(right)
    return len(pairs) / (time.perf_counter() - t)


def graph(binary, launch, frames):
    out = subprocess.run([binary, "run", launch, "--frames", str(frames)], capture_output=True,
                         text=True, check=True).stdout
    m = re.search(r"([\d.]+) frames/s; capture → last output latency ([\d.]+) ms", out)
    if not m:
        sys.exit("no summary line in the graph's output:\n" + out)
    return float(m.group(1)), float(m.group(2))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--bin", default=os.path.join(ROOT, "target/release/microstereo"))
    a = ap.parse_args()
    cv2.setNumThreads(2)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([a.bin, "synth", "-o", tmp, "--width", "1280", "--height", "1024",
                        "--cells", "10", "--frames", str(a.frames)], check=True,
                       stdout=subprocess.DEVNULL)
        pairs = list(zip(sorted(glob.glob(os.path.join(tmp, "f*_left.png"))),
                         sorted(glob.glob(os.path.join(tmp, "f*_right.png")))))
        launch = open(os.path.join(ROOT, "launch.toml")).read()
        source = ('params = { source = "files", left = "%s", right = "%s" }'
                  % (os.path.join(tmp, "f*_left.png"), os.path.join(tmp, "f*_right.png")))
        launch, n = re.subn(r'params = \{ source = "synthetic"[^}]*\}', source, launch)
        if n != 1:
            sys.exit("launch.toml's capture is not the synthetic source this script replaces")
        path = os.path.join(tmp, "files.toml")
        open(path, "w").write(launch)
        print("round  graph frames/s  latency ms  opencv frames/s  graph/opencv")
        ratios, ours, theirs = [], [], []
        for r in range(a.rounds):
            fps, latency = graph(a.bin, path, len(pairs))
            cv = opencv_loop(pairs)
            ours.append(fps), theirs.append(cv), ratios.append(fps / cv)
            print(f"{r + 1:5}  {fps:14.2f}  {latency:10.1f}  {cv:15.2f}  {fps / cv:12.3f}")
        print(f"median {statistics.median(ours):13.2f}  {'':10}  "
              f"{statistics.median(theirs):15.2f}  {statistics.median(ratios):12.3f}")


if __name__ == "__main__":
    main()
