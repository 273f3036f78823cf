"""The example graphs, installed as ``flowrt.examples`` (``flowrt examples --copy .``)."""
