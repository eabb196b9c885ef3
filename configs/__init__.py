"""Packaged cell configurations (TOML). ``sim.toml`` is the default cell."""
