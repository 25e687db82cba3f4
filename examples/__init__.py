"""Examples of the user's own extensions, loaded with ``SRL_PLUGINS`` (docs/extending.md)."""
