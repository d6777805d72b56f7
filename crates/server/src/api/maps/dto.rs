//! Wire types of `/v1/maps` (create, list, read, append images or descriptors) and their
//! conversions from the use cases' types. Only the API knows the wire format: store records
//! and core types can change without changing it, and the reverse.

use serde::{Deserialize, Serialize};

use crate::api::error::ApiError;
use crate::api::wire::format_id;
use seasonloc_app::model::{DescriptorSettings, ImageMeta, MapRecord};
use seasonloc_core::features::cnn::CnnResize;

/// Longest accepted map name, in characters (as the OpenAPI `maxLength` counts).
pub const MAX_NAME_CHARS: usize = 200;
/// Largest integer `timestamp` (Unix milliseconds): 9999-12-31T23:59:59.999Z.
const MAX_UNIX_MS: i64 = 253_402_300_799_999;

/// Longest accepted metadata string (timestamp, label), in characters.
pub const MAX_META_CHARS: usize = 256;
/// Largest accepted precomputed descriptor length.
pub const MAX_DESCRIPTOR_DIM: u32 = 1 << 20;

fn default_cell_size() -> u32 {
    32
}

/// Descriptor settings of a map, as sent and returned.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum DescriptorDto {
    /// HOG (`cell_size` pixels per cell side, optional `resize: [width, height]`).
    Hog {
        /// Cell side in pixels (default 32).
        #[serde(default = "default_cell_size")]
        cell_size: u32,
        /// Resize to `[width, height]` before extraction.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        resize: Option<[u32; 2]>,
    },
    /// One layer of an ONNX model on the server (`docs/cnn.md`). Unset preprocessing fields
    /// take the shipped EfficientNet-Lite0 README's values (224x224, short side 256 + centre
    /// crop, `(x - 127) / 128`); in answers every field is set and `identity` is added.
    Cnn {
        /// Model path on the server (default: the server's `--cnn-model`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        model: Option<String>,
        /// Output (or node) name used as descriptor, e.g. `block10`.
        layer: String,
        /// Network input `[width, height]` (default `[224, 224]`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        input_size: Option<[u32; 2]>,
        /// `crop` (scale the short side to `short_side`, cut the centre; default) or `stretch`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        resize: Option<CnnResizeDto>,
        /// Short side before the centre crop (default 256/224 of the larger input side).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        short_side: Option<u32>,
        /// Per-channel R, G, B mean subtracted from 0..255 pixels (default 127 each).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mean: Option<[f32; 3]>,
        /// Per-channel R, G, B divisor after the mean (default 128 each).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        scale: Option<[f32; 3]>,
        /// What the model was at creation (set by the server; rejected in requests).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        identity: Option<ModelIdentityDto>,
    },
    /// A feature co-occurrence map (`docs/cooc.md`): built from the first batch of reference
    /// images, further drives added with `POST /v1/maps/{id}/drives`. Unset fields keep the
    /// library defaults; answers set every field.
    Cooc {
        /// Branching factor of the vocabulary tree (default 32).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        vocabulary_branching: Option<usize>,
        /// Depth of the vocabulary tree (default 2: 1,024 words).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        vocabulary_depth: Option<usize>,
        /// Upsampling before corner detection (default 2).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        upsample: Option<u32>,
        /// Keypoints kept per image (default 300).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        max_keypoints: Option<usize>,
        /// Spatial grid `[columns, rows]` (default `[12, 8]`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        grid: Option<[u16; 2]>,
        /// Tolerated grid-offset difference in cells (default 1).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        spatial_tolerance: Option<u16>,
        /// Merge drives adjacent in time (default false).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        merge_adjacent_drives: Option<bool>,
        /// Seed of the vocabulary's k-means.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seed: Option<u64>,
    },
    /// Descriptors computed by the client, of length `dim`.
    Precomputed {
        /// Descriptor length.
        dim: u32,
    },
}

/// How a CNN map brings images to the network's input size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CnnResizeDto {
    /// Scale the whole image to the input size.
    Stretch,
    /// Scale the short side, then cut the centred input-size window.
    Crop,
}

/// The model a CNN map was created with.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ModelIdentityDto {
    /// Lower-case hex sha256 of the ONNX file.
    pub sha256: String,
    /// The layer used as descriptor.
    pub layer: String,
    /// One-line summary of the preprocessing.
    pub preprocessing: String,
}

impl Default for DescriptorDto {
    fn default() -> Self {
        DescriptorDto::Hog {
            cell_size: default_cell_size(),
            resize: None,
        }
    }
}

impl From<DescriptorSettings> for DescriptorDto {
    fn from(d: DescriptorSettings) -> Self {
        match d {
            DescriptorSettings::Hog { cell_size, resize } => DescriptorDto::Hog {
                cell_size,
                resize: resize.map(|(w, h)| [w, h]),
            },
            DescriptorSettings::Precomputed { dim } => DescriptorDto::Precomputed { dim },
            DescriptorSettings::Cooc(p) => DescriptorDto::Cooc {
                vocabulary_branching: Some(p.vocabulary_branching),
                vocabulary_depth: Some(p.vocabulary_depth),
                upsample: Some(p.keypoints.upsample),
                max_keypoints: Some(p.keypoints.max_keypoints),
                grid: Some([p.grid_cols, p.grid_rows]),
                spatial_tolerance: Some(p.spatial_tolerance),
                merge_adjacent_drives: Some(p.merge_adjacent_drives),
                seed: Some(p.seed),
            },
            DescriptorSettings::Cnn(c) => {
                let o = c.options;
                let (resize, short_side) = match o.resize {
                    CnnResize::Stretch => (CnnResizeDto::Stretch, None),
                    CnnResize::ShortSideCrop { short_side } => {
                        (CnnResizeDto::Crop, Some(short_side))
                    }
                };
                DescriptorDto::Cnn {
                    model: Some(o.model.to_string_lossy().into_owned()),
                    layer: o.layer,
                    input_size: Some([o.input_size.0, o.input_size.1]),
                    resize: Some(resize),
                    short_side,
                    mean: Some(o.mean),
                    scale: Some(o.scale),
                    identity: Some(ModelIdentityDto {
                        sha256: c.identity.sha256,
                        layer: c.identity.layer,
                        preprocessing: c.identity.preprocessing,
                    }),
                }
            }
        }
    }
}

/// `POST /v1/maps` body.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateMapRequest {
    /// Name, 1..=200 bytes.
    pub name: String,
    /// Descriptor settings (default HOG with 32-pixel cells).
    #[serde(default)]
    pub descriptor: DescriptorDto,
}

/// A map as returned by the API.
#[derive(Clone, Debug, Serialize)]
pub struct MapResponse {
    /// Map id.
    pub id: String,
    /// Name.
    pub name: String,
    /// Descriptor settings.
    pub descriptor: DescriptorDto,
    /// Descriptor length, known after the first batch (or at creation for precomputed).
    pub descriptor_dim: Option<u32>,
    /// Number of reference images.
    pub image_count: u32,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: u64,
}

impl From<MapRecord> for MapResponse {
    fn from(m: MapRecord) -> Self {
        MapResponse {
            id: format_id(m.id),
            name: m.name,
            descriptor: m.descriptor.into(),
            descriptor_dim: m.dim,
            image_count: m.image_count,
            created_at_ms: m.created_ms,
        }
    }
}

/// `GET /v1/maps` body.
#[derive(Clone, Debug, Serialize)]
pub struct MapListResponse {
    /// All maps, oldest first.
    pub maps: Vec<MapResponse>,
}

/// Optional metadata of one reference image.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageMetaDto {
    /// Capture time: a string (free-form, e.g. RFC 3339, at most 256 characters) or an integer
    /// of Unix milliseconds (stored as RFC 3339 in UTC).
    pub timestamp: Option<serde_json::Value>,
    /// Latitude in degrees, -90..=90.
    pub latitude: Option<f64>,
    /// Longitude in degrees, -180..=180.
    pub longitude: Option<f64>,
    /// Free-form label, at most 256 bytes.
    pub label: Option<String>,
}

impl ImageMetaDto {
    /// Validates entry `index` of a batch's metadata.
    pub fn validate(self, index: usize) -> Result<ImageMeta, ApiError> {
        let name = |f: &str| format!("metadata[{index}].{f}");
        let timestamp = match self.timestamp {
            None | Some(serde_json::Value::Null) => None,
            Some(serde_json::Value::String(s)) => Some(s),
            Some(serde_json::Value::Number(n)) => match n.as_i64() {
                Some(ms) if (0..=MAX_UNIX_MS).contains(&ms) => {
                    Some(seasonloc_core::time::format_unix_ms(ms))
                }
                _ => {
                    return Err(ApiError::param(
                        name("timestamp"),
                        format!(
                            "an integer timestamp is Unix milliseconds, from 0 to {MAX_UNIX_MS} \
                             (year 9999), got {n}"
                        ),
                    ))
                }
            },
            Some(_) => {
                return Err(ApiError::param(
                    name("timestamp"),
                    "must be a string (e.g. RFC 3339) or an integer of Unix milliseconds",
                ))
            }
        };
        for (field, v) in [("timestamp", &timestamp), ("label", &self.label)] {
            if v.as_ref()
                .is_some_and(|s| s.chars().count() > MAX_META_CHARS)
            {
                return Err(ApiError::param(
                    name(field),
                    format!("must be at most {MAX_META_CHARS} characters"),
                ));
            }
        }
        if let Some(lat) = self.latitude {
            if !(-90.0..=90.0).contains(&lat) {
                return Err(ApiError::param(
                    name("latitude"),
                    format!("must be within [-90, 90], got {lat}"),
                ));
            }
        }
        if let Some(lon) = self.longitude {
            if !(-180.0..=180.0).contains(&lon) {
                return Err(ApiError::param(
                    name("longitude"),
                    format!("must be within [-180, 180], got {lon}"),
                ));
            }
        }
        Ok(ImageMeta {
            timestamp,
            latitude: self.latitude,
            longitude: self.longitude,
            label: self.label,
        })
    }
}

/// `POST /v1/maps/{id}/descriptors` JSON body.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AppendDescriptorsRequest {
    /// One descriptor per reference image, in route order.
    pub descriptors: Vec<Vec<f64>>,
    /// Optional metadata, one entry per descriptor.
    #[serde(default)]
    pub metadata: Option<Vec<ImageMetaDto>>,
}

/// Answer of an append: the indices given to the new images.
#[derive(Clone, Debug, Serialize)]
pub struct AppendResponse {
    /// Route indices of the appended images, in order.
    pub indices: Vec<u32>,
    /// The map's image count after the append.
    pub image_count: u32,
}

/// Query of the raw-float form of `/descriptors`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawQuery {
    /// Descriptor length (the map's when absent).
    pub dim: Option<u32>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn descriptor_defaults_to_hog_32() {
        let r: CreateMapRequest = serde_json::from_str(r#"{"name": "a"}"#).unwrap();
        assert_eq!(
            r.descriptor,
            DescriptorDto::Hog {
                cell_size: 32,
                resize: None
            }
        );
        let r: CreateMapRequest =
            serde_json::from_str(r#"{"name": "a", "descriptor": {"kind": "hog", "cell_size": 8}}"#)
                .unwrap();
        assert_eq!(
            r.descriptor,
            DescriptorDto::Hog {
                cell_size: 8,
                resize: None
            }
        );
        let err = serde_json::from_str::<CreateMapRequest>(
            r#"{"name": "a", "descriptor": {"kind": "hog", "cel_size": 8}}"#,
        )
        .unwrap_err();
        assert!(err.to_string().contains("cel_size"), "{err}");
    }

    #[test]
    fn metadata_ranges_name_the_entry() {
        let m = ImageMetaDto {
            latitude: Some(91.0),
            ..ImageMetaDto::default()
        };
        let err = m.validate(3).unwrap_err();
        assert!(err.to_string().contains("metadata[3].latitude"), "{err}");
    }
}
