#!/usr/bin/env python3
"""Stereo calibration fixture for the rectify node (issue 4, not used yet).

Calibrates the OpenCV chessboard pairs in ../shared/data/calibration once with OpenCV
(pip install opencv-python-headless) and writes an OpenCV YAML (K1, D1, K2, D2, R, T and
OpenCV's own R1, R2, P1, P2) plus the detected corners of every pair, which a Rust test
can map through its own Bouguet rectification. Measured: RMS 0.448 px, baseline 83.6 mm;
OpenCV's rectified corners differ in row by at most 0.22-0.82 px on 11 of the 13 pairs
and by 2.6 and 3.6 px on pairs 2 and 5 (left and right corner orders differ there).
"""
import cv2, numpy as np, glob, json, os
d='/work/shared/data/calibration/opencv-chessboard-pairs'
pat=(9,6); sq=25.0
objp=np.zeros((54,3),np.float32); objp[:,:2]=np.mgrid[0:9,0:6].T.reshape(-1,2)*sq
O=[];L=[];R=[]; names=[]
for i in list(range(1,10))+list(range(11,15)):
    l=cv2.imread(f'{d}/left{i:02d}.jpg',0); r=cv2.imread(f'{d}/right{i:02d}.jpg',0)
    ok1,c1=cv2.findChessboardCorners(l,pat); ok2,c2=cv2.findChessboardCorners(r,pat)
    if not(ok1 and ok2): continue
    crit=(cv2.TERM_CRITERIA_EPS+cv2.TERM_CRITERIA_MAX_ITER,30,1e-3)
    c1=cv2.cornerSubPix(l,c1,(11,11),(-1,-1),crit); c2=cv2.cornerSubPix(r,c2,(11,11),(-1,-1),crit)
    # The detector may list one view's corners from the other end of the board.
    if np.dot((c1[8]-c1[0]).ravel(),(c2[8]-c2[0]).ravel())<0: c2=c2[::-1].copy()
    O.append(objp);L.append(c1);R.append(c2);names.append(i)
sz=(640,480)
_,K1,D1,_,_=cv2.calibrateCamera(O,L,sz,None,None)
_,K2,D2,_,_=cv2.calibrateCamera(O,R,sz,None,None)
rms,K1,D1,K2,D2,Rm,T,E,F=cv2.stereoCalibrate(O,L,R,K1,D1,K2,D2,sz,flags=cv2.CALIB_FIX_INTRINSIC)
print('rms',rms,'baseline',np.linalg.norm(T), 'pairs', names)
R1,R2,P1,P2,Q,_,_=cv2.stereoRectify(K1,D1,K2,D2,sz,Rm,T,alpha=0)
fs=cv2.FileStorage('./stereo.yaml',cv2.FILE_STORAGE_WRITE)
for k,v in dict(K1=K1,D1=D1,K2=K2,D2=D2,R=Rm,T=T,R1=R1,R2=R2,P1=P1,P2=P2).items(): fs.write(k,v)
fs.write('image_width',640); fs.write('image_height',480); fs.release()
# corners of every pair, and opencv's rectified corners for reference
out=[]
for n,c1,c2 in zip(names,L,R):
    r1=cv2.undistortPoints(c1,K1,D1,R=R1,P=P1).reshape(-1,2); r2=cv2.undistortPoints(c2,K2,D2,R=R2,P=P2).reshape(-1,2)
    out.append(dict(pair=n,left=c1.reshape(-1,2).tolist(),right=c2.reshape(-1,2).tolist(),rect_dy_max=float(np.abs(r1[:,1]-r2[:,1]).max())))
json.dump(out,open('./corners.json','w'))
print('opencv rectified |dy| max per pair', [round(o['rect_dy_max'],3) for o in out])
