"""`needletissue fe needle`: the parametric needle-tissue-bone FE model (two Schanz pins and a clamp)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from needletissue.commands import numbers, utilisation_line, warn_validity
from needletissue.errors import FORCE_RANGE_HELP


def register(app: typer.Typer, groups) -> None:
    from needletissue.geometry.needle import NeedleGeometry

    d = NeedleGeometry()

    @groups.fe.command("needle")
    def needle(
        ctx: typer.Context,
        force: Optional[List[float]] = typer.Option(None, "--force", help="Reduction force, N (repeat; "
                                                    "default 100 200 300), uniform over the gripper; "
                                                    f"{FORCE_RANGE_HELP}."),
        needles: int = typer.Option(d.needles, "--needles", help="Number of needles: 1 or 2."),
        diameter: float = typer.Option(d.diameter, "--diameter", help="Needle diameter d, mm (> 0)."),
        free_length: float = typer.Option(d.free_length, "--free-length",
                                          help="Needle length from the bone surface to its end, mm "
                                               "(> tissue thickness + grip length)."),
        spacing: float = typer.Option(d.spacing, "--spacing", help="Needle axis spacing s, mm (> diameter)."),
        depth: float = typer.Option(d.depth, "--depth", help="Insertion depth h in bone, mm (< bone thickness)."),
        mesh_size: float = typer.Option(d.mesh_size, "--mesh-size",
                                        help="Element size in tissue, bone and clamp near the needles, mm."),
        needle_mesh_size: float = typer.Option(d.needle_mesh_size, "--needle-mesh-size",
                                               help="Element size on the needles, mm (<= diameter)."),
        far_mesh_size: float = typer.Option(d.far_mesh_size, "--far-mesh-size",
                                            help="Element size at the far boundary, mm (>= mesh size)."),
        max_tetrahedra: int = typer.Option(d.max_tetrahedra, "--max-tetrahedra",
                                           help="Refuse, before meshing, a mesh estimated above this many "
                                                "tetrahedra (the estimate is within 2x of gmsh's count); "
                                                "raise it to run a finer mesh on purpose."),
        direction: str = typer.Option("0,1,0", "--direction",
                                      help="Force direction x,y,z (normalised; default y: lateral, "
                                           "perpendicular to the needles and their plane)."),
        load_offset: str = typer.Option("0,0,0", "--load-offset",
                                        help="Load point minus the gripper centre x,y,z, mm: the force acts "
                                             "there (applied as force + moment r x F at the centre)."),
        order: int = typer.Option(2, "--order", help="Element order: 2 (quadratic, default) or 1."),
        no_ritz: bool = typer.Option(False, "--no-ritz", help="Skip the Rayleigh-Ritz comparison."),
        out: Optional[Path] = typer.Option(None, "--out", help="Output folder: mesh, VTU per force, "
                                           "results.json, config.toml, versions.json, figures."),
        json_out: bool = typer.Option(False, "--json", help="Print the results JSON to stdout."),
        interfaces: str = typer.Option("bonded", "--interfaces", help="bonded (one conforming mesh) or "
                                       "paper (frictional contact: needle-muscle 0.3, muscle-bone 0.3, "
                                       "bone-needle 0.9; docs/contact.md)."),
        friction: Optional[List[str]] = typer.Option(None, "--friction", help="Per-pair friction "
                                                     "coefficient (>= 0, dimensionless), e.g. "
                                                     "needle-muscle=0.3; repeat; makes that pair a contact."),
        contact_dhat: Optional[float] = typer.Option(None, "--contact-dhat", help="Contact barrier distance, mm "
                                                     "(> 0; default 0.1): largest interpenetration; smaller is "
                                                     "stiffer and harder to converge (docs/contact.md)."),
        contact_eps_v: Optional[float] = typer.Option(None, "--contact-eps-v", help="Friction smoothing, mm of "
                                                      "slip per load increment (> 0; default 0.01) below which "
                                                      "an interface sticks (docs/contact.md)."),
        config_file: Optional[Path] = typer.Option(None, "--config", help="config.toml of an earlier `fe needle "
                                                   "--out` run (tables needle_model, contact; units mm, N): runs "
                                                   "it again; options given on the command line override it."),
    ):
        """Solve the needle-tissue-bone model at each force; report needle, clamp and tissue deformation
        and the Rayleigh-Ritz comparison. Units: mm, N, MPa."""
        from dataclasses import replace

        from needletissue.models.needle import NeedleModelConfig, run_needle_model

        if config_file is not None:
            base, contact = load_config(config_file)
            from needletissue.commands import from_command_line

            given = set(from_command_line(ctx))
        else:
            base, contact, given = NeedleModelConfig(), {}, set(ctx.params)
        p = ctx.params
        changes = {}
        if "direction" in given:
            changes["direction"] = numbers("--direction", direction)
        if "load_offset" in given:
            changes["load_offset"] = numbers("--load-offset", load_offset, unit="mm")
        geometry = replace(base.geometry, **{n: p[n] for n in _GEOMETRY_OPTIONS if n in given})
        if force:
            changes["forces"] = tuple(force)
        if "order" in given:
            changes["order"] = order
        if "no_ritz" in given:
            changes["ritz"] = not no_ritz
        cfg = replace(base, geometry=geometry, progress=not json_out, **changes)
        interfaces = interfaces if "interfaces" in given else contact.get("interfaces", "bonded")
        pairs = {**contact.get("friction", {}), **parse_friction(friction or [])}
        contact_dhat = contact_dhat if contact_dhat is not None else contact.get("dhat_mm")
        contact_eps_v = contact_eps_v if contact_eps_v is not None else contact.get("eps_v_mm")
        hooks = {}
        if interfaces != "bonded" or pairs:
            from needletissue.errors import check_number
            from needletissue.models.contact import NeedleContact, needle_settings

            given_settings = {k: check_number(f"--contact-{k.replace('_', '-')}", v, gt=0)
                              for k, v in (("dhat", contact_dhat), ("eps_v", contact_eps_v)) if v is not None}
            hooks = NeedleContact(interfaces, pairs, needle_settings(**given_settings)).hooks()
        if out is not None:  # a file or an unwritable place: one error line now, not after meshing
            from needletissue.runinfo import check_output_dir

            check_output_dir(out, "--out")
        result = run_needle_model(cfg, out, **hooks)
        warn_validity(result.results)
        if json_out:
            from needletissue.runinfo import to_jsonable

            print(json.dumps(to_jsonable(result.to_dict()), indent=2))
            return
        _table(result, out)


_GEOMETRY_OPTIONS = ("needles", "diameter", "free_length", "spacing", "depth", "mesh_size", "needle_mesh_size",
                     "far_mesh_size", "max_tetrahedra")
_CONTACT_KEYS = ("interfaces", "friction", "dhat_mm", "eps_v_mm")


def parse_friction(items):
    from needletissue.fem.contact import parse_friction as parse

    return parse(items)


def load_config(path):
    """A config.toml written by `fe needle --out` -> (NeedleModelConfig, contact table)."""
    from needletissue.errors import InputError
    from needletissue.models.needle import NeedleModelConfig
    from needletissue.runinfo import dataclass_from, read_toml

    data = read_toml(path)
    for key in data:
        if key not in ("needle_model", "contact"):
            raise InputError(f"{path}: {key}", "unknown table; allowed: [needle_model], [contact]")
    cfg = dataclass_from(NeedleModelConfig, data.get("needle_model", {}), f"{path}: needle_model")
    contact = data.get("contact", {})
    bad = sorted(set(contact) - set(_CONTACT_KEYS))
    if bad:
        raise InputError(f"{path}: contact.{bad[0]}", f"unknown field; allowed: {', '.join(_CONTACT_KEYS)}")
    return cfg, contact


def _table(result, out) -> None:
    from rich.console import Console
    from rich.table import Table

    m = result.mesh
    t = Table(title=f"Needle model: {m['tetrahedra']} tets, {m['quadratic_nodes']} nodes, "
                    f"{result.wall_time_s:.1f} s")
    for col in ("force N", "max needle mm", "clamp mm", "adipose mm", "muscle mm", "Ritz tip mm", "FE - Ritz mm"):
        t.add_column(col, justify="right")
    for r in result.results:
        f = (lambda v: "-" if v is None else f"{v:.3f}")
        t.add_row(f"{r.force_N:g}", f(r.max_needle_deformation_mm), f(r.clamp_displacement_mm),
                  f(r.max_deformation_mm.get("adipose")), f(r.max_deformation_mm.get("muscle")),
                  f(r.ritz_tip_deflection_mm), f(r.theory_fe_difference_mm))
    c = Console()
    c.print(t)
    for r in result.results:
        st = r.strength
        if st:
            c.print(utilisation_line(r.force_N, st))
    for row in result.extra.get("contact", {}).get("per_force", []):
        gaps = ", ".join(f"{k} {v:.3f}" for k, v in row["max_gap_opening_mm"].items())
        c.print(f"{row['force_N']:g} N contact: largest gap opening mm: {gaps}; "
                f"interpenetration {row['max_interpenetration_mm']:.4f} mm")
    if out is not None:
        c.print(f"wrote {out}/results.json, VTU and figures")
