"""Node orderings of the cell types, shared by geometry (which builds meshes) and fem (which solves
them), so neither imports the other. Order is VTK's (and FElupe's)."""

import numpy as np

# VTK tetra10: local (corner, corner) pair of each midpoint node 4..9.
TET10_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
# gmsh tetra10 -> VTK tetra10: gmsh puts edge (3,2) at 8 and (3,1) at 9.
GMSH_TO_VTK_TET10 = np.array([0, 1, 2, 3, 4, 5, 6, 7, 9, 8])
