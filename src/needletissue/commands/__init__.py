"""CLI commands, one module per concern; each defines register(app, groups). Heavy imports stay inside commands."""


def from_command_line(ctx) -> list[str]:
    """The options typed on the command line (not defaults): those override a --config file."""
    # by name: Typer may bring its own copy of click, whose ParameterSource is a different enum
    return [n for n in ctx.params if getattr(ctx.get_parameter_source(n), "name", "") == "COMMANDLINE"]


def numbers(option: str, text: str | None, n: int = 3, unit: str = "") -> tuple[float, ...] | None:
    """`--option X,Y,Z` -> n floats (None stays None); anything else is one InputError naming the option."""
    from needletissue.errors import InputError

    if text is None:
        return None
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) != n:
        raise InputError(option, f"expected {n} comma-separated numbers{f' ({unit})' if unit else ''}, got {text!r}")
    return v


def utilisation_line(force_N: float, strength: dict) -> str:
    """One result's needle and bone utilisation (models.strength), for the fe commands' tables."""
    return (f"{force_N:g} N: needle yield utilisation {strength['needle_yield_utilisation']:.2f}, bone strength "
            f"utilisation {strength['bone_strength_utilisation']:.2f} (max von Mises / strength)")


def warn_validity(results) -> None:
    """Each result's validity warnings (a stress past its material's strength, models.strength) on stderr, one
    line each, whether the results go to stdout as JSON (which keeps them, `strength.validity_warnings`) or as a
    table."""
    import typer

    for r in results:
        st = (r.get("strength") if isinstance(r, dict) else r.strength) or {}
        force = r["force_N"] if isinstance(r, dict) else r.force_N
        for w in st.get("validity_warnings", []):
            typer.echo(f"warning: {force:g} N: {w}", err=True)
