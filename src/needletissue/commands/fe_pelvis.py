"""`needletissue fe pelvis`: the anatomical pelvic reduction model (docs/pelvis_model.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from needletissue.commands import numbers, utilisation_line, warn_validity
from needletissue.errors import FORCE_RANGE_HELP


def register(app, groups) -> None:
    @groups.fe.command("pelvis")
    def pelvis(
        ctx: typer.Context,
        ct: Path = typer.Option(None, "--ct", help="CT volume (NIfTI, HU). Default: the example CT in the data folder."),
        labels: Path = typer.Option(None, "--labels", help="Label map on the CT grid (TotalSegmentator ids)."),
        segmentation: Path = typer.Option(None, "--segmentation", help="Folder written by `needletissue segment` "
                                          "(with --labels): mesh it with --mesher smooth instead of --ct/--labels."),
        ssm: bool = typer.Option(False, "--ssm", help="Use the mean SSM bone surfaces (soft tissue by offsetting)."),
        force: list[float] = typer.Option(None, "--force", help="Reduction force on the clamp, N (repeat; "
                                          f"{FORCE_RANGE_HELP})."),
        force_direction: str = typer.Option("0,0,-1", "--force-direction",
                                            help="Force direction x,y,z (patient RAS; made transverse to the needles)."),
        site: str = typer.Option("supra_acetabular", "--site", help="supra_acetabular or iliac_crest."),
        side: str = typer.Option("right", "--side", help="Hemipelvis with the needles: right or left."),
        mesh_size: float = typer.Option(None, "--mesh-size", help="Soft-tissue element size at the needles, mm "
                                         "(default 4.5 with --mesher smooth, 3 with box)."),
        needle_size: float = typer.Option(None, "--needle-size",
                                          help="Needle element size, mm (default 2/3 of --mesh-size)."),
        far_size: float = typer.Option(None, "--far-size",
                                       help="Element size 35 mm and more from the needles, mm (default 4x --mesh-size); "
                                            "with --mesher smooth, = --mesh-size meshes at one size."),
        mesher: str = typer.Option("smooth", "--mesher", help="smooth (the `segment` + `mesh` reconstruction of the "
                                   "CT's or the SSM's label map with the needles and clamp inserted exactly, graded "
                                   "to --far-size by CGAL's smooth interfaces; needs `apt-get install libcgal-dev`; "
                                   "--far-size = --mesh-size: one size, no CGAL) or box (gmsh box with exact needles "
                                   "and clamp, tissue by element centroid, graded)."),
        order: int = typer.Option(2, "--order", help="Element order: 2 (tetra10, curved needles) or 1 (linear "
                                                     "tets, the paper's; needs fine needles, see docs)."),
        needle_diameter: float = typer.Option(5.0, "--needle-diameter", help="Needle diameter, mm."),
        si_joint: str = typer.Option("fixed", "--si-joint", help="Sacroiliac joint: fixed (paper) or bonded."),
        out: Path = typer.Option(None, "--out", help="Folder for VTU, figures, config, versions and results."),
        json_out: bool = typer.Option(False, "--json", help="Print the results as JSON."),
        interfaces: str = typer.Option("bonded", "--interfaces", help="bonded (one conforming mesh) or paper "
                                       "(frictional contact: needle-muscle 0.3, muscle-bone 0.3, bone-needle "
                                       "0.9; docs/contact.md)."),
        friction: list[str] = typer.Option(None, "--friction", help="Per-pair friction coefficient (>= 0), "
                                           "e.g. needle-muscle=0.3; repeat; makes that pair a contact."),
        sliding_radius: float = typer.Option(None, "--sliding-radius",
                                             help="Muscle-bone contact within this distance of the needle axes, "
                                                  "mm; beyond it the muscles stay bonded to bone (their origins and "
                                                  "insertions; default 35; 1000: every face slides)."),
        contact_dhat: float = typer.Option(None, "--contact-dhat",
                                           help="Contact barrier distance, mm (> 0; default 0.1)."),
        contact_eps_v: float = typer.Option(None, "--contact-eps-v",
                                            help="Friction smoothing: slip per load increment below which an "
                                                 "interface sticks, mm (> 0; default 0.01, the needle model's)."),
        config_file: Path = typer.Option(None, "--config", help="config.toml of an earlier `fe pelvis --out` "
                                         "run (PelvisConfig fields; units mm, N): runs it again; options given "
                                         "on the command line override it."),
    ):
        """Hemipelvis from CT (or SSM) with two needles and a clamp; max needle and tissue deformation,
        ranking, thickness along the needles and the Ritz comparison. Units mm, N."""
        import json
        from dataclasses import asdict

        from needletissue.errors import InputError
        from needletissue.models.pelvis import PelvisConfig, run_pelvis_model
        from needletissue.models.pelvis.model import DEFAULT_MESH_SIZE

        kw, given = {}, set(ctx.params)
        if config_file is not None:
            from needletissue.commands import from_command_line
            from needletissue.runinfo import dataclass_from, read_toml

            written = read_toml(config_file)
            kw = asdict(dataclass_from(PelvisConfig, written, str(config_file)))
            if "mesher" not in written:   # written before the smooth mesher existed: it ran the box
                kw["mesher"] = "box"
            kw.pop("out"), kw.pop("progress")  # where to write and how to show it: this run's options
            given = set(from_command_line(ctx))
        if ssm and (ct is not None or labels is not None):
            raise InputError("--ssm", "give either --ssm or --ct/--labels, not both")
        if "force_direction" in given:
            kw["force_direction"] = list(numbers("--force-direction", force_direction))
        from needletissue.fem.contact import parse_friction

        cli = {"ssm": ("source", "ssm" if ssm else "ct"), "ct": ("ct", str(ct) if ct else None),
               "labels": ("labels", str(labels) if labels else None), "site": ("site", site),
               "segmentation": ("segmentation", str(segmentation) if segmentation else None),
               "side": ("side", side), "mesh_size": ("mesh_size", mesh_size),
               "needle_size": ("needle_size", needle_size), "far_size": ("far_size", far_size),
               "order": ("order", order), "mesher": ("mesher", mesher), "needle_diameter": ("needle_diameter", needle_diameter),
               "si_joint": ("si_joint", si_joint), "interfaces": ("interfaces", interfaces),
               "contact_dhat": ("contact_dhat", contact_dhat), "contact_eps_v": ("contact_eps_v", contact_eps_v),
               "sliding_radius": ("sliding_radius", sliding_radius)}
        if (config_file is not None and "mesher" in given and "mesh_size" not in given and mesher != kw["mesher"]
                and kw["mesh_size"] == DEFAULT_MESH_SIZE.get(kw["mesher"])):
            kw["mesh_size"] = None   # the file's size is its mesher's default: take the new mesher's
        kw.update(v for k, v in cli.items() if k in given)
        if ssm or ct is not None:  # a source given on the command line replaces the file's
            kw["source"] = "ssm" if ssm else "ct"
            if ssm:
                kw["ct"] = kw["labels"] = None
        if force:
            kw["forces"] = list(force)
        kw.setdefault("forces", [100.0, 200.0, 300.0])
        kw["friction"] = {**kw.get("friction", {}), **parse_friction(friction or [])}
        if segmentation is not None:
            if not (segmentation / "tissues.nii.gz").is_file():
                raise InputError("--segmentation", f"{segmentation}: no tissues.nii.gz (run `needletissue segment` first)")
        if kw.get("source", "ct") == "ct" and (kw.get("ct") is None) != (kw.get("labels") is None):
            raise InputError("--ct/--labels", "give both --ct and --labels (or neither for the example CT)")
        if out is not None:  # a file or an unwritable place: one error line now, not a traceback after the solve
            from needletissue.runinfo import check_output_dir

            check_output_dir(out, "--out")
        config = PelvisConfig(**kw, out=str(out) if out else None, progress=not json_out)
        res = run_pelvis_model(config)
        d = res.to_dict()
        warn_validity(d["results"])
        if json_out:
            keep = ("mesh", "wall_time_s", "results", "ranking", "thickness", "comparison", "contact")
            print(json.dumps({k: d[k] for k in keep if d.get(k) is not None}, indent=2))
            return
        from rich.console import Console
        from rich.table import Table

        con = Console()
        t = Table(title=f"pelvis model: {d['mesh']['tetrahedra']} tets, {d['mesh']['nodes']} nodes, "
                        f"{d['wall_time_s']:.0f} s")
        for c in ("force N", "max needle mm", "clamp mm", "Ritz mm", "|Ritz-FE| mm"):
            t.add_column(c, justify="right")
        for r in d["results"]:
            t.add_row(f"{r['force_N']:.0f}", f"{r['max_needle_deformation_mm']:.3f}",
                      f"{r['clamp_displacement_mm']:.3f}", f"{r['ritz_tip_deflection_mm']:.3f}",
                      f"{r['theory_fe_difference_mm']:.3f}")
        con.print(t)
        last = d["results"][-1]["max_deformation_mm"]
        con.print("ranking (largest first): " + " > ".join(f"{n} {last[n]:.2f} mm" for n in d["ranking"]))
        for r in d["results"]:
            if r.get("strength"):
                con.print(utilisation_line(r["force_N"], r["strength"]))
        if d.get("contact"):
            _print_contact(con, d["contact"])
        for th in d["thickness"]:
            con.print(f"{th['needle']}: muscle {th['muscle_mm']:.1f} mm, adipose {th['adipose_mm']:.1f} mm, "
                      f"total {th['total_mm']:.1f} mm")
        if out:
            con.print(f"written: {out}/")


def _print_contact(con, contact: dict) -> None:
    """Per force and interface: gap, slip, contact pressure, interpenetration; equilibrium."""
    from rich.table import Table

    a = contact.get("attachments", {})
    if a:
        con.print(f"muscle-bone: {a['muscle_bone_area_sliding_mm2']:.0f} mm2 sliding within "
                  f"{a['sliding_radius_mm']:g} mm of the needles, {a['muscle_bone_area_bonded_mm2']:.0f} mm2 "
                  "bonded (muscle attachments)")
    t = Table(title="contact interfaces (friction: " + ", ".join(f"{k} {v:g}" for k, v in contact["interfaces"].items())
              + ")")
    for c in ("force N", "interface", "gap mm", "slip mm", "p max / mean MPa", "overlap mm", "equilibrium"):
        t.add_column(c, justify="right")
    for x in contact["per_force"]:
        for name, s in x.get("interfaces", {}).items():
            t.add_row(f"{x['force_N']:.0f}", name, f"{s['max_gap_opening_mm']:.3f}", f"{s['max_slip_mm']:.3f}",
                      f"{s['max_pressure_MPa']:.3g} / {s['mean_pressure_MPa']:.3g}",
                      f"{s['max_interpenetration_mm']:.3f}", f"{100 * x.get('equilibrium_error', float('nan')):.2f} %")
    con.print(t)
