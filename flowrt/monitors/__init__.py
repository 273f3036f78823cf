"""Monitors of a run: users of the runtime's narrow interface, never imported by it."""
