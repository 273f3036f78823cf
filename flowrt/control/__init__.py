"""The control endpoint of a running graph: server, wire format and client."""
