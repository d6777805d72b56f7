//! Cosine similarity matrix (flow paper Eq. 1) and column normalisation (Eq. 2).
