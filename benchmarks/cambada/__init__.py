"""The CAMBADA experiment (issue 6): a monolithic vision loop against the graph under flowrt.

    python -m benchmarks.cambada            # every configuration, then RESULTS.md and PNGs
    python -m benchmarks.cambada --quick    # a short smoke run

Modules: :mod:`.nodes` (the recording and paper-calibrated trackers), :mod:`.graph` (the
benchmark graph derived from graphs/cambada.yaml), :mod:`.monolithic` (the baseline loop),
:mod:`.modechange` (the paper's mode change in an embedded Runtime), :mod:`.analysis` (table
rows from activation records), :mod:`.report` (markdown and figures), :mod:`.run` (the driver).
"""
