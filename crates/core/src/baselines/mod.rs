//! Baselines evaluated on the same similarity matrices as the flow method, so that the
//! comparison isolates the data-association step:
//!
//! * [`best_match()`] — single-image matching: per query the most similar reference.
//! * [`seqslam()`] — SeqSLAM (Milford & Wyeth 2012) as in OpenSeqSLAM: local contrast
//!   enhancement of the difference matrix plus a straight-line trajectory search.
//!
//! Both reduce their result to at most one [`Prediction`](crate::localize::Prediction) per query,
//! in increasing query order, with a documented confidence (higher = more certain).

mod best_match;
mod seqslam;

pub use best_match::best_match;
pub use seqslam::{enhance_contrast, seqslam, SeqSlamParams};
