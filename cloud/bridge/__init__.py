"""Bridge estimation core: per-pass data over a span, stiffness and weight posteriors, dynamics,
damage hypotheses, moving-reference influence lines (transport-free, pure numpy/scipy/numba)."""
