"""Merge passes over two CSR patterns (sorted column indices per row): where the entries of one lie in the
other, and their union. linsolve._fit's kernels, compiled by Numba on first use (imported there lazily: bonded
runs never need them). Linear in the entries, where a key search was n log n: 0.3 s per tangent of the
one-needle contact model, 9 % of its run (docs/bench.md)."""

import numpy as np
from numba import njit


@njit(cache=True)
def positions(kp, ki, mp, mi, at):
    """at[j] = the slot in pattern k (kp, ki) of pattern m's j-th entry; False (at partly written) as soon as an
    entry of m is not in k."""
    for r in range(len(kp) - 1):
        a, ae = kp[r], kp[r + 1]
        for j in range(mp[r], mp[r + 1]):
            c = mi[j]
            while a < ae and ki[a] < c:
                a += 1
            if a == ae or ki[a] != c:
                return False
            at[j] = a
            a += 1
    return True


@njit(cache=True)
def union(kp, ki, mp, mi):
    """(indptr, indices) of the union of patterns k and m."""
    nrow = len(kp) - 1
    up = np.zeros(nrow + 1, np.int64)
    for r in range(nrow):  # count, then fill
        a, ae, b, be = kp[r], kp[r + 1], mp[r], mp[r + 1]
        c = 0
        while a < ae and b < be:
            if ki[a] <= mi[b]:
                b += ki[a] == mi[b]
                a += 1
            else:
                b += 1
            c += 1
        up[r + 1] = up[r] + c + (ae - a) + (be - b)
    ui = np.empty(up[nrow], ki.dtype)
    for r in range(nrow):
        a, ae, b, be, u = kp[r], kp[r + 1], mp[r], mp[r + 1], up[r]
        while a < ae or b < be:
            if b == be or (a < ae and ki[a] <= mi[b]):
                if b < be and ki[a] == mi[b]:
                    b += 1
                ui[u] = ki[a]
                a += 1
            else:
                ui[u] = mi[b]
                b += 1
            u += 1
    return up, ui
