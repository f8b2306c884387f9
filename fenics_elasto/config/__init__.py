"""Every input's schema: problem.toml, scene specs, ``--set`` overrides."""
