#!/usr/bin/env python3
"""Stereo calibration fixture for the rectify node's tests (tests/data/calibration/).

Calibrates the OpenCV sample chessboard pairs (left01..14 / right01..14) once with OpenCV
(pip install opencv-python-headless) and writes:
  - opencv_chessboard_stereo.yaml: K1, D1, K2, D2, R, T and OpenCV's own R1, R2, P1, P2;
  - opencv_chessboard_{left,right}_camera_info.yaml: the same calibration as two ROS
    camera_info files (rectification_matrix = R1/R2, projection_matrix = P1/P2);
  - opencv_chessboard_corners.json: the 9x6 corners of every pair (left and right in the
    same board order) with the largest row difference OpenCV's rectification leaves.

Usage: scripts/stereo_calibration_fixture.py [PAIRS_DIR] [OUT_DIR]

The sub-pixel window is (5,5), i.e. 11x11 px: the squares are 25-35 px wide, and the
usual (11,11) (23x23 px) reaches the neighbouring corners on boards seen at a slant and
moved single corners by up to 3.6 px (pairs 2 and 5). The two cameras are then refined
jointly (CALIB_USE_INTRINSIC_GUESS). Measured: RMS 0.215 px, baseline 83.18 mm; OpenCV's
rectified corners: every board row (mean of 9 corners) on the same row within 0.22 px,
95 % of corners within 0.33 px, the worst corner 0.68 px.
"""
import cv2, numpy as np, json, os, sys

src = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
    os.path.dirname(__file__), '../../shared/data/calibration/opencv-chessboard-pairs')
out = sys.argv[2] if len(sys.argv) > 2 else os.path.join(
    os.path.dirname(__file__), '../tests/data/calibration')
pat = (9, 6)
square_mm = 25.0
size = (640, 480)
objp = np.zeros((54, 3), np.float32)
objp[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * square_mm
crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)

O, L, R, names = [], [], [], []
for i in range(1, 15):
    l = cv2.imread(f'{src}/left{i:02d}.jpg', 0)
    r = cv2.imread(f'{src}/right{i:02d}.jpg', 0)
    if l is None or r is None:
        continue
    ok1, c1 = cv2.findChessboardCorners(l, pat)
    ok2, c2 = cv2.findChessboardCorners(r, pat)
    if not (ok1 and ok2):
        print(f'pair {i}: board not found in both views, skipped')
        continue
    c1 = cv2.cornerSubPix(l, c1, (5, 5), (-1, -1), crit)
    c2 = cv2.cornerSubPix(r, c2, (5, 5), (-1, -1), crit)
    # The detector may list one view's corners from the other end of the board.
    if np.dot((c1[8] - c1[0]).ravel(), (c2[8] - c2[0]).ravel()) < 0:
        c2 = c2[::-1].copy()
    O.append(objp); L.append(c1); R.append(c2); names.append(i)
if not names:
    sys.exit(f'no chessboard pairs found in {src}')

_, K1, D1, _, _ = cv2.calibrateCamera(O, L, size, None, None)
_, K2, D2, _, _ = cv2.calibrateCamera(O, R, size, None, None)
rms, K1, D1, K2, D2, Rm, T, _, _ = cv2.stereoCalibrate(
    O, L, R, K1, D1, K2, D2, size, flags=cv2.CALIB_USE_INTRINSIC_GUESS)
R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(K1, D1, K2, D2, size, Rm, T, alpha=0)
print(f'RMS {rms:.3f} px, baseline {np.linalg.norm(T):.2f} mm, pairs {names}')

os.makedirs(out, exist_ok=True)
fs = cv2.FileStorage(f'{out}/opencv_chessboard_stereo.yaml', cv2.FILE_STORAGE_WRITE)
for k, v in dict(K1=K1, D1=D1, K2=K2, D2=D2, R=Rm, T=T, R1=R1, R2=R2, P1=P1, P2=P2).items():
    fs.write(k, v)
fs.write('image_width', size[0]); fs.write('image_height', size[1])
fs.release()


def data(m, rows, cols):
    vals = ', '.join(repr(float(x)) for x in np.asarray(m).ravel())
    return f'  rows: {rows}\n  cols: {cols}\n  data: [{vals}]\n'


# ROS's Tx = -fx*B has B in metres; OpenCV's P2 shares T's unit (mm here).
P2m = P2.copy()
P2m[0, 3] *= 1e-3
for side, K, D, Rr, P in [('left', K1, D1, R1, P1), ('right', K2, D2, R2, P2m)]:
    with open(f'{out}/opencv_chessboard_{side}_camera_info.yaml', 'w') as f:
        f.write(f'image_width: {size[0]}\nimage_height: {size[1]}\ncamera_name: {side}\n')
        f.write('camera_matrix:\n' + data(K, 3, 3))
        f.write('distortion_model: plumb_bob\n')
        f.write('distortion_coefficients:\n' + data(D, 1, 5))
        f.write('rectification_matrix:\n' + data(Rr, 3, 3))
        f.write('projection_matrix:\n' + data(P, 3, 4))

pairs, rows, every = [], [], []
for n, c1, c2 in zip(names, L, R):
    r1 = cv2.undistortPoints(c1, K1, D1, R=R1, P=P1).reshape(-1, 2)
    r2 = cv2.undistortPoints(c2, K2, D2, R=R2, P=P2).reshape(-1, 2)
    dy = r1[:, 1] - r2[:, 1]
    every += list(np.abs(dy))
    rows.append(float(np.abs(dy.reshape(6, 9).mean(1)).max()))
    pairs.append(dict(pair=n,
                      left=[[round(float(x), 3), round(float(y), 3)] for x, y in c1.reshape(-1, 2)],
                      right=[[round(float(x), 3), round(float(y), 3)] for x, y in c2.reshape(-1, 2)],
                      opencv_dy_max=round(float(np.abs(dy).max()), 4)))
with open(f'{out}/opencv_chessboard_corners.json', 'w') as f:
    json.dump(pairs, f)
every = np.sort(every)
print('OpenCV rectified: board rows within %.3f px; corners median %.3f, p95 %.3f, worst %.3f px'
      % (max(rows), every[len(every) // 2], every[int(len(every) * 0.95)], every[-1]))
