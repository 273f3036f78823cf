"""Graphs across machines over Zenoh: exports, imports, clocks and the wire."""
