"""flowrt against dora-rs on the same payloads and nodes: ``python -m benchmarks.peers``."""
