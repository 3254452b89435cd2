# Quality metrics for a CGAL medit mesh: tets, dihedral angles, per-label volume, interface axis-alignment.
import numpy as np, meshio, json, sys
def metrics(mesh, info, centre=None):
    pts = mesh.points
    ci = [i for i, cb in enumerate(mesh.cells) if cb.type == 'tetra']
    T = np.vstack([mesh.cells[i].data for i in ci])
    L = np.concatenate([mesh.cell_data['medit:ref'][i] for i in ci]).astype(int)
    P = pts[T]                                                      # (n,4,3)
    vol = np.einsum('ij,ij->i', P[:, 1] - P[:, 0], np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 0])) / 6
    # dihedral angles: faces opposite vertex k; normal n_k; angle between faces a,b = pi - angle(n_a, n_b)
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    N = np.stack([np.cross(P[:, b] - P[:, a], P[:, c] - P[:, a]) for a, b, c in faces], 1)
    N *= np.sign(vol)[:, None, None]
    N /= np.linalg.norm(N, axis=2, keepdims=True)
    ang = [np.degrees(np.pi - np.arccos(np.clip((N[:, a] * N[:, b]).sum(1), -1, 1)))
           for a in range(4) for b in range(a + 1, 4)]
    ang = np.stack(ang, 1)
    mind = ang.min(1)
    vv = info['vx'] ** 3
    vols = {int(l): float(np.abs(vol[L == l]).sum()) for l in np.unique(L)}
    verr = {l: 100 * (vols[l] / (info['counts'][str(l)] * vv) - 1) for l in vols}
    # interfaces between two different labels
    F = np.sort(np.concatenate([T[:, [1, 2, 3]], T[:, [0, 2, 3]], T[:, [0, 1, 3]], T[:, [0, 1, 2]]]), 1)
    FL = np.tile(L, 4)
    key = F[:, 0].astype(np.int64) * len(pts) ** 2 + F[:, 1].astype(np.int64) * len(pts) + F[:, 2]
    o = np.argsort(key, kind='stable'); ks = key[o]
    same = np.nonzero(ks[1:] == ks[:-1])[0]
    a, b = o[same], o[same + 1]
    itf = F[a][FL[a] != FL[b]]
    tn = np.cross(pts[itf[:, 1]] - pts[itf[:, 0]], pts[itf[:, 2]] - pts[itf[:, 0]])
    tarea = np.linalg.norm(tn, axis=1); tn /= tarea[:, None]
    axis_frac = float((tarea * (np.abs(tn).max(1) > 0.98)).sum() / tarea.sum())
    # edge length vs distance from centre (grading check)
    out = dict(tets=len(T), verts=len(pts), min_dih=float(mind.min()), p1_dih=float(np.percentile(mind, 1)),
               n_below10=int((mind < 10).sum()), vol_err_pct={k: round(v, 2) for k, v in verr.items()},
               max_abs_vol_err_pct=round(max(abs(v) for v in verr.values()), 2),
               itf_tris=len(itf), itf_axis_aligned_area_frac=round(axis_frac, 3))
    if centre is not None:
        cc = P.mean(1); d = np.linalg.norm(cc - np.array(centre), axis=1)
        el = np.linalg.norm(P[:, 1] - P[:, 0], axis=1)
        out['mean_edge_by_dist'] = {f'{lo}-{lo+10}mm': round(float(el[(d >= lo) & (d < lo + 10)].mean()), 2)
                                    for lo in (0, 10, 20, 30, 40, 60) if ((d >= lo) & (d < lo + 10)).any()}
    return out
if __name__ == '__main__':
    info = json.load(open(__import__('os').environ.get('INFO', 'out/crop.json')))
    m = meshio.read(sys.argv[1])
    print(json.dumps(metrics(m, info, info['centre_mm'])))
