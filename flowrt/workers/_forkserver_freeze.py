"""Imported last by the workers' forkserver, and only there: freeze what it has preloaded.

Workers are forked from the forkserver and share its pages (numpy, OpenCV, flowrt) copy-on-write.
A garbage collection in a worker writes to the header of every object it walks, which copies
each page it touches: ~8 MB per worker. Objects frozen before the fork are never walked, so the
pages stay shared (and a worker's full collection is microseconds instead of ~25 ms).
"""

import gc

gc.collect()
gc.freeze()
