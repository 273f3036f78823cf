"""One run of a graph: the embedding API and what a run owns."""
