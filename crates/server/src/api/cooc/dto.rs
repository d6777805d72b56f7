//! Wire types of co-occurrence maps: the `drive` part of `POST /v1/maps/{id}/drives`, its
//! answer, and the `method` parameter of a localization (also read by `localize`).

use serde::{Deserialize, Serialize};

use seasonloc_core::cooc::CoocMethod;

/// How a `cooc` map localizes a query sequence (`params.method`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CoocMethodDto {
    /// The co-occurrence scores (`s + 1`, column-normalised) as the flow graph's similarity
    /// matrix; the solver parameters apply (default).
    #[default]
    Flow,
    /// Single-image recognition: the best location per query, confidence = the size of its
    /// spatially consistent group; no hypotheses.
    Cooc,
    /// The paper's forward-only sequence matching (ds = 10); no hypotheses.
    CoocSeq,
}

impl From<CoocMethodDto> for CoocMethod {
    fn from(m: CoocMethodDto) -> Self {
        match m {
            CoocMethodDto::Flow => CoocMethod::Flow,
            CoocMethodDto::Cooc => CoocMethod::Single,
            CoocMethodDto::CoocSeq => CoocMethod::Sequence,
        }
    }
}

/// `drive` part of `POST /v1/maps/{id}/drives`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DriveDto {
    /// Location (reference image index) of each image, in part order.
    pub locations: Vec<u64>,
    /// Time key ordering the drives (e.g. the hour of day); only the order matters (default 0,
    /// the first drive's).
    #[serde(default)]
    pub time: Option<f64>,
}

/// Answer of `POST /v1/maps/{id}/drives`.
#[derive(Clone, Debug, Serialize)]
pub struct DriveResponse {
    /// Drives in the map now (the first mapping drive included).
    pub drives: usize,
    /// Images added by this drive.
    pub images: usize,
}
