# Crop right hemipelvis, remap labels, add soft tissue + fat from HU, write INR (+ CGAL-style weights INR).
import json, os, sys
from pathlib import Path

import nibabel as nib
import numpy as np
from scipy import ndimage as ndi
from pygalmesh import save_inr
D = os.path.join(os.environ.get('NEEDLETISSUE_DATA', '../shared/data'), 'pelvis_ct', '')
OUT = Path(sys.argv[1] if len(sys.argv) > 1 else 'out')
OUT.mkdir(exist_ok=True)
seg = np.asarray(nib.load(D + 'example_seg_fast_force_split.nii.gz').dataobj)
ct = np.asarray(nib.load(D + 'example_ct.nii.gz').dataobj).astype(np.float32)
sl = (slice(52, 112), slice(8, 74), slice(0, 66))   # around label 78 (hip right): i 58-105, j 15-65, k 0-60
s, c = seg[sl], ct[sl]
lab = np.zeros(s.shape, np.uint8)
body = ndi.binary_fill_holes(ndi.median_filter((c > -500).astype(np.uint8), 3).astype(bool))
fat = ndi.median_filter(((c > -190) & (c < -30)).astype(np.uint8), 3).astype(bool)
lab[body] = 1                 # other soft tissue / organs
lab[body & fat] = 9           # adipose from HU
for src, dst in {78: 2, 76: 3, 25: 4, 81: 5, 83: 6, 85: 7, 89: 8}.items():
    lab[s == src] = dst       # hip R, femur R, sacrum, glut max/med/min R, iliopsoas R
lab = np.pad(lab, 2)          # background shell so volumes are closed
vx = 3.0
save_inr(lab, (vx, vx, vx), str(OUT / 'crop.inr'))
# CGAL 5.5 generate_label_weights equivalent (needs ITK there): max over labels of Gaussian-blurred 255*indicator
sigma = vx  # mm, CGAL default-ish (sigma = max voxel size)
w = np.zeros(lab.shape, np.float32)
for l in np.unique(lab):
    w = np.maximum(w, ndi.gaussian_filter((lab == l).astype(np.float32) * 255, sigma / vx))
save_inr(np.clip(w, 0, 255).astype(np.uint8), (vx, vx, vx), str(OUT / 'crop_w.inr'))
u, n = np.unique(lab, return_counts=True)
idx = np.argwhere(lab == 2); cen = idx.mean(0); p = idx[np.argmin(((idx - cen) ** 2).sum(1))]
info = dict(shape=lab.shape, counts={int(a): int(b) for a, b in zip(u, n)}, vx=vx,
            centre_mm=(p * vx).tolist())
json.dump(info, open(OUT / 'crop.json', 'w')); print(info)
