# Cleaned variant: one-hot Gaussian (sigma 1 voxel) + argmax, i.e. a voxel-level majority smoothing of the label map.
import numpy as np, json
from scipy import ndimage as ndi
from pygalmesh import save_inr
f = open('out/crop.inr', 'rb'); f.read(256); info = json.load(open('out/crop.json'))
a = np.frombuffer(f.read(), np.uint8).reshape(info['shape'], order='F')
labs = np.unique(a)
sm = np.stack([ndi.gaussian_filter((a == l).astype(np.float32), 1.0) for l in labs])
b = labs[sm.argmax(0)].astype(np.uint8)
save_inr(b, (3.0, 3.0, 3.0), 'out/crop_clean.inr')
u, n = np.unique(b, return_counts=True)
info['counts'] = {int(x): int(y) for x, y in zip(u, n)}
json.dump(info, open('out/crop_clean.json', 'w')); print(info['counts'], 'changed voxels', int((a != b).sum()))
