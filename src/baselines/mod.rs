//! Baselines evaluated on the same matrices as the flow method.
