"""Configuration files shipped with the package (default.toml: `needletissue reproduce`)."""
