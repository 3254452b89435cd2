"""CLI commands, one module per concern; each defines register(app, groups). Heavy imports stay inside commands."""
