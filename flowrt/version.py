"""flowrt's version, in a module of its own: what records a recording's provenance (the MCAP
writer, a session's metadata) reads it without importing the whole package."""

__version__ = "0.1.0"
