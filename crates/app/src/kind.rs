//! The one dispatch on a map's kind. A map either holds one global descriptor per image (HOG,
//! a CNN layer, or client-computed) and is localized by the flow graph
//! (`app/descriptors.rs`, `app/localize.rs`), or it is a feature co-occurrence map built
//! from its images (`app/cooc.rs`). Use cases branch on [`kind`] and nowhere else.
//!
//! Adding a kind: a variant of `store::DescriptorSettings` (with its stored encoding), an arm
//! here, and one module beside `cooc.rs` implementing its appends and localization.

use crate::model::{DescriptorSettings, MapRecord};
use seasonloc_core::cooc::CoocParams;

/// What a map is, for the use cases.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind<'a> {
    /// Global descriptors (HOG, CNN, precomputed) in the flow graph.
    Descriptors(&'a DescriptorSettings),
    /// A feature co-occurrence map with these parameters.
    Cooc(&'a CoocParams),
}

/// The kind of `map`.
pub fn kind(map: &MapRecord) -> Kind<'_> {
    match &map.descriptor {
        DescriptorSettings::Cooc(p) => Kind::Cooc(p),
        d @ (DescriptorSettings::Hog { .. }
        | DescriptorSettings::Precomputed { .. }
        | DescriptorSettings::Cnn(_)) => Kind::Descriptors(d),
    }
}
