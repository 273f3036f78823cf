"""A graph's description: models, YAML loading, resolution, diagnostics, kinds."""
