//! seasonloc's algorithms: visual localization on a previously driven route, across seasons.
//!
//! The core of the workspace (see `ARCHITECTURE.md`): pure algorithms on images, descriptor
//! matrices and similarity matrices, with no HTTP, JSON, async runtime or database; failures
//! are [`Error`]. [`features`] (HOG; a CNN layer on tract behind the `cnn` feature),
//! [`similarity`] (Eq. 1 and 2), [`solver`] (the flow graph), [`confidence`] and [`localize`]
//! (from descriptors to hypotheses and predictions), [`trip`] (the online solver of a vehicle
//! that posts frames as it drives), [`cooc`] (feature co-occurrence maps), [`baselines`],
//! [`picture`] (what people look at) and [`eval`] (the evaluation protocol). The `serde` feature
//! gives the results other layers store and send their serde forms.
//!
//! The method is Naseer, Burgard & Stachniss, *Robust Visual Localization Across Seasons*:
//! global descriptors -> cosine similarity matrix (Eq. 1) -> column normalisation (Eq. 2)
//! -> min-cost flow on a DAG of matching and hidden nodes.
#![warn(missing_docs)]

pub mod baselines;
pub mod calibration;
pub mod codec;
pub mod confidence;
pub mod cooc;
pub mod error;
pub mod eval;
pub mod features;
pub mod localize;
pub mod matrix;
pub mod picture;
pub mod prediction;
pub mod similarity;
pub mod solver;
pub mod time;
pub mod trip;
pub mod window;

pub use error::{Error, Result};
pub use matrix::Matrix;
