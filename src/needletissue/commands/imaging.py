"""`needletissue segment`, `mesh`, `thickness`: CT -> tissues -> surfaces + tetrahedral mesh -> thickness.

Coordinates everywhere are physical LPS millimetres as in the image header (SimpleITK convention).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from needletissue.commands import numbers
from needletissue.errors import InputError


def _floats(field: str, text: str | None, n: int):
    v = numbers(field, text, n)
    return None if v is None else list(v)


def register(app: typer.Typer, groups) -> None:
    @app.command("segment")
    def segment_cmd(
        ct: Path = typer.Argument(..., help="CT volume in Hounsfield units: NIfTI/NRRD/MHA file or DICOM "
                                  "series folder."),
        out: Path = typer.Option(..., "--out", help="Output folder (tissues.nii.gz, tissues.json, ...)."),
        labels: Optional[Path] = typer.Option(None, "--labels", help="TotalSegmentator label map on the "
                                              "CT grid (ids 25, 75-78 bone; 80-85, 88-89 muscles)."),
        cortical_thickness: float = typer.Option(1.5, help="Cortical bone thickness, mm (inward offset "
                                                 "of the bone surface)."),
        split_sides: bool = typer.Option(True, help="Keep left/right muscles (gluteus_maximus_left, ...)."),
    ):
        """CT -> tissue label map (bone cortical/cancellous, muscles, adipose) on the CT grid."""
        from needletissue.imaging.segment import SegmentationConfig, segment
        from needletissue.runinfo import staged_output, write_run_files

        cfg = SegmentationConfig(cortical_thickness=cortical_thickness, split_sides=split_sides)
        t0 = time.perf_counter()
        seg = segment(ct, labels, cfg)
        with staged_output(out) as stage:  # a stopped run leaves out as it was
            paths = seg.save(stage)
            results = {"tissues": seg.tissues, "volumes_mm3": seg.stats["volumes_mm3"],
                       "bone_split": seg.stats["bone_split"], "source": seg.stats["source"],
                       "files": {k: str(v) for k, v in paths.items()},
                       "wall_time_s": time.perf_counter() - t0}
            write_run_files(stage, {"ct": str(ct), "labels": str(labels) if labels else None,
                                    "segmentation": seg.stats["config"]}, results)
        typer.echo(f"{len(seg.tissues)} tissues -> {Path(out) / paths['tissues'].name} "
                   f"({results['wall_time_s']:.1f} s)")

    @app.command("mesh")
    def mesh_cmd(
        directory: Path = typer.Argument(..., metavar="DIR", help="Folder written by `segment`."),
        out: Path = typer.Option(..., "--out", help="Output folder (mesh.msh, mesh.vtu, surfaces/)."),
        size: float = typer.Option(3.0, "--size", help="Element size, mm: tetrahedron volume bounded by "
                                   "that of a regular tetrahedron of this edge (paper: 3 mm)."),
        regions: Optional[str] = typer.Option(None, help="Comma-separated tissues to mesh (default all "
                                              "but other_body)."),
        crop: str = typer.Option("pelvis", help="'pelvis' (sacrum and hip bones + 30 mm: the region "
                                 "the models need), 'none' (the whole image) or a box "
                                 "xmin,xmax,ymin,ymax,zmin,zmax in LPS mm."),
        surfaces_out: bool = typer.Option(True, "--surfaces/--no-surfaces",
                                          help="Also write smoothed per-tissue surfaces (STL + VTP)."),
        method: str = typer.Option("smooth", "--method", help="Tissue interfaces: 'smooth' (smoothed "
                                   "shared interfaces, volumes kept, optimised elements; docs/imaging.md) or "
                                   "'voxel' (exact voxel faces, staircases)."),
        fidelity: bool = typer.Option(False, "--fidelity/--no-fidelity", help="Also measure volumes, Dice "
                                      "and Hausdorff 95 % (mm) of the mesh against the label map."),
    ):
        """Tissue label map -> conforming multi-region tetrahedral mesh (gmsh .msh, named physical
        volumes per tissue, physical surfaces `boundary` and `bone_surface`) + quality report."""
        from dataclasses import asdict

        from needletissue.geometry.tetmesh import MeshConfig, tet_mesh
        from needletissue.imaging.segment import Segmentation
        from needletissue.runinfo import staged_output, write_json, write_run_files

        seg = Segmentation.load(directory)
        box = None
        if crop == "pelvis":
            box = seg.bone_box(30.0)
        elif crop != "none":
            box = tuple(_floats("crop", crop, 6))
        cfg = MeshConfig(size=size, regions=regions.split(",") if regions else None, crop=box,
                         method=method).validate()
        # VTK's and TetGen's extension modules loaded whole before any work: a SIGTERM inside their
        # initialisation left a half-made module and the process died of SIGSEGV
        from needletissue.geometry.gmsh_init import import_holding_signals

        import_holding_signals("vtk", "pyvista", "tetgen", "gmsh")
        # every file goes into a hidden folder inside out, moved into place at the end: a run stopped
        # or failed meanwhile leaves out as it was (and out is checked before minutes of meshing)
        with staged_output(out) as stage:
            t0 = time.perf_counter()
            results, view, surfaces_job = {}, None, None
            if surfaces_out:   # independent of the tetrahedral mesh: a child process makes them meanwhile
                from needletissue.geometry.child import start_in_child

                surfaces_job = start_in_child("needletissue.geometry.surfaces:write_surfaces",
                                              {"directory": str(directory), "regions": cfg.regions,
                                               "out": str(stage / "surfaces")}, what="the tissue surfaces")
            try:
                t1 = time.perf_counter()
                mesh = tet_mesh(seg, config=cfg)
                t2 = time.perf_counter()
                mesh.write_msh(stage / "mesh.msh")
                mesh.write_vtu(stage / "mesh.vtu")
                t3 = time.perf_counter()
                if surfaces_job is not None:
                    view = surfaces_job()
            except BaseException:  # the child stopped before the stage is removed: it writes into it
                if surfaces_job is not None:
                    surfaces_job.stop()
                raise
            if view is not None:
                results["surfaces"] = view["reports"]
                bad = [n for n, r in results["surfaces"].items() if not (r["watertight"] and r["manifold"])]
                if bad:
                    typer.echo(f"warning: surfaces not watertight/manifold: {', '.join(bad)}", err=True)
            t4 = time.perf_counter()
            q = mesh.quality()
            if fidelity:
                from needletissue.geometry.fidelity import mesh_fidelity

                results["fidelity"] = asdict(mesh_fidelity(seg, mesh, cfg))
            results.update({"quality": asdict(q), "materials": mesh.materials, "mesh_info": mesh.info,
                            "surfaces_in_msh": {k: int(len(v)) for k, v in mesh.surfaces.items()},
                            "wall_time_s": {"surfaces": view["wall_time_s"] if view else 0.0,
                                            "tet_mesh": t2 - t1, "write": t3 - t2, "surfaces_wait": t4 - t3,
                                            "total": time.perf_counter() - t0}})
            write_json(stage / "mesh.json", {"regions": mesh.materials, "quality": asdict(q)})
            write_run_files(stage, {"dir": str(directory), "mesh": asdict(cfg)}, results)
        typer.echo(f"{q.n_tetrahedra} tetrahedra, {q.n_nodes} nodes, {len(mesh.regions)} regions, "
                   f"min dihedral {q.min_dihedral_deg:.1f} deg, min radius ratio "
                   f"{q.min_radius_ratio:.3f} -> {Path(out) / 'mesh.msh'}")

    @app.command("thickness")
    def thickness_cmd(
        directory: Path = typer.Argument(..., metavar="DIR", help="Folder written by `segment`."),
        entry: Optional[str] = typer.Option(None, "--entry", help="Entry point X,Y,Z in LPS mm (image "
                                            "header frame); negative values: --entry=-10,20,30."),
        direction: Optional[str] = typer.Option(None, "--direction", help="Needle direction DX,DY,DZ "
                                                "(LPS, any length), pointing into the body."),
        site: Optional[str] = typer.Option(None, "--site", help="Instead of --entry/--direction: "
                                           "iliac_crest or supra_acetabular (both sides, mean +- SD)."),
        as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
    ):
        """Thickness of each tissue crossed from the skin to the first bone along a needle path, mm."""
        from needletissue.geometry.thickness import site_thickness, thickness_along
        from needletissue.imaging.segment import Segmentation
        from needletissue.runinfo import to_jsonable

        seg = Segmentation.load(directory)
        if site is not None:
            if entry is not None or direction is not None:
                raise InputError("site", "give either --site or --entry/--direction, not both")
            summ = site_thickness(seg, site)
            if as_json:
                typer.echo(json.dumps(to_jsonable(summ), indent=2))
            else:
                typer.echo(f"{summ.site}: soft-tissue thickness {summ.mean_mm:.2f} +- {summ.sd_mm:.2f} mm "
                           f"(n = {summ.n}, range {summ.min_mm:.1f}..{summ.max_mm:.1f} mm)")
            return
        if entry is None or direction is None:
            raise InputError("entry", "--entry and --direction are required (or --site)")
        res = thickness_along(seg, _floats("entry", entry, 3), _floats("direction", direction, 3))
        if not res.bone_hit:
            raise InputError("direction", f"the path from {res.entry} along {res.direction} (LPS mm) "
                             "does not reach bone inside the image")
        if as_json:
            typer.echo(json.dumps(to_jsonable(res), indent=2))
            return
        from rich.console import Console
        from rich.table import Table

        tab = Table(title=f"Tissues from the skin to bone (frame {res.frame})")
        tab.add_column("tissue")
        tab.add_column("from, mm", justify="right")
        tab.add_column("to, mm", justify="right")
        tab.add_column("length, mm", justify="right")
        for s in res.segments:
            tab.add_row(s.tissue, f"{s.start_mm:.1f}", f"{s.end_mm:.1f}", f"{s.length_mm:.1f}")
        con = Console()
        con.print(tab)
        con.print(f"soft-tissue thickness: {res.soft_tissue_thickness_mm:.2f} mm; "
                  + ", ".join(f"{k} {v:.1f}" for k, v in res.thickness_by_tissue.items()))
