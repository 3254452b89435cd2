"""Barrier distances of the anatomical model's contact surfaces at rest (docs/contact.md, "Mechanics").

    PYTHONPATH=src python benchmarks/contact_rest_distances.py [--mesh-size 6 --needle-size 3 --far-size 18]

Builds the `fe pelvis --mesher box --interfaces paper` mesh (sizes: the box mesher's CLI defaults), splits the interfaces as the model
does, builds each interface's collision surface with the virtual gap (0.9 dhat, dhat 0.1 mm) and prints per
interface: split node pairs, collision pairs within dhat, how many are closer than 0.03 mm and the smallest
distance (mm). The sides start coincident, so every pair should start near the gap: a much closer pair
starts where the barrier is far stiffer than intended.
"""

from __future__ import annotations

import argparse
import time

import ipctk
import numpy as np


def main(argv=None):
    from needletissue.fem import TaggedMesh
    from needletissue.fem.contact import ContactSettings, ContactSurface
    from needletissue.fem.contact.item import _collisions
    from needletissue.geometry.pelvis import curve_needles
    from needletissue.models.contact import NeedleContact
    from needletissue.models.pelvis import PelvisConfig
    from needletissue.models.pelvis.model import MATERIALS, build, split_contact

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size", type=float, default=3.0)
    ap.add_argument("--needle-size", type=float)
    ap.add_argument("--far-size", type=float)
    a = ap.parse_args(argv)
    cfg = PelvisConfig(mesher="box", interfaces="paper", mesh_size=a.mesh_size, needle_size=a.needle_size, far_size=a.far_size)
    vol, pm = build(cfg)
    q = TaggedMesh(pm.points, pm.cells, pm.regions, pm.surfaces).to_quadratic()
    q.points = curve_needles(q.points, q.cells, q.regions, pm.needle_axes, pm.site.diameter / 2)
    contact = NeedleContact("paper", {}, ContactSettings(), materials=MATERIALS)
    t0 = time.process_time()
    mesh, _ = split_contact(contact, q, pm.needle_axes, cfg.sliding_radius)
    s = ContactSettings()
    print(f"{len(mesh.cells)} tets; dhat {s.dhat} mm, gap {s.gap:.3f} mm")
    for itf in contact._split:
        surf = ContactSurface.build(mesh.points, [itf], contact.friction, gap=s.gap)
        V = np.asfortranarray(mesh.points[surf.vertices] + surf.offset)
        F = np.asfortranarray(surf.faces, dtype=np.int32)
        cm = ipctk.CollisionMesh(V, np.asfortranarray(ipctk.edges(F), dtype=np.int32), F)
        cm.can_collide = ipctk.make_connected_components_filter(F)
        col = _collisions()
        col.build(cm, V, s.dhat)
        d = np.array([np.sqrt(col[i].compute_distance(col[i].dof(V, cm.edges, cm.faces))) for i in range(len(col))])
        print(f"{itf.name}: {len(itf.nodes_a)} node pairs, {len(col)} collision pairs, {int((d < 0.03).sum())} "
              f"closer than 0.03 mm, smallest {d.min():.3g} mm")
    print(f"split + surfaces: {time.process_time() - t0:.1f} s CPU")


if __name__ == "__main__":
    main()
