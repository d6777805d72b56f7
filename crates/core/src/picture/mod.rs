//! Pictures for people: small JPEG thumbnails of reference images ([`thumbnail`]) and a
//! bounded, downsampled picture of a similarity matrix ([`matrix`]), the figure both papers
//! explain their results with.
//!
//! Both are sized independently of the data: a thumbnail is at most
//! [`thumbnail::MAX_WIDTH`] x [`thumbnail::MAX_HEIGHT`] pixels whatever the camera, and a
//! matrix picture at most [`matrix::MAX_SIDE`] pixels on each side whatever the number of
//! queries and references, so storing them with every image or localization costs a known,
//! small amount. Core layer: images in, bytes out; nothing here knows HTTP or the store.

pub mod matrix;
pub mod thumbnail;

pub use matrix::MatrixPicture;
pub use thumbnail::thumbnail_jpeg;
