"""Physics-informed surrogate of ANM6-Easy (paper §4.2): KKT-NNs → aggregation → power balance → next state."""
