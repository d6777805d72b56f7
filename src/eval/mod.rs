//! Evaluation protocol of `spec.md` §4.

/// One method's answer for one query: at most one per query, higher confidence = more certain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prediction {
    /// Query index `i`.
    pub query: usize,
    /// Predicted reference index `j`.
    pub reference: usize,
    /// Higher = more certain. Finite.
    pub confidence: f64,
}
