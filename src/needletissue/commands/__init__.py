"""CLI commands, one module per concern; each defines register(app, groups). Heavy imports stay inside commands."""


def from_command_line(ctx) -> list[str]:
    """The options typed on the command line (not defaults): those override a --config file."""
    # by name: Typer may bring its own copy of click, whose ParameterSource is a different enum
    return [n for n in ctx.params if getattr(ctx.get_parameter_source(n), "name", "") == "COMMANDLINE"]
