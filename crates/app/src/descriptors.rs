//! Global-descriptor maps (HOG, CNN, precomputed): the one place that turns a map's descriptor
//! settings into an extractor for its images, shared by appends, localizations and trips.

use super::error::{AppError, AppResult};
use crate::model::{DescriptorSettings, MapRecord};
use seasonloc_core::features::cnn::CnnSpec;
use seasonloc_core::features::hog::{HogOptions, HogSpec};
use seasonloc_core::features::Extractor;

/// The extractor of a map's images (references and queries): `None` for precomputed maps.
///
/// For a CNN map the model at the recorded path is loaded (from the shared cache when its
/// content is unchanged) and checked against the identity recorded at creation: a model file
/// that changed, no longer loads or is gone is [`AppError::ModelMismatch`], never silently
/// used. A co-occurrence map has no global descriptors ([`AppError::MapKind`]). Blocking (it
/// hashes the model file): call it on the CPU pool.
pub fn map_extractor(map: &MapRecord) -> AppResult<Option<Box<dyn Extractor>>> {
    let id = map.id;
    match &map.descriptor {
        DescriptorSettings::Hog { cell_size, resize } => {
            Ok(Some(Box::new(HogSpec::new(HogOptions {
                cell_size: *cell_size,
                resize: *resize,
            })?)))
        }
        DescriptorSettings::Precomputed { .. } => Ok(None),
        DescriptorSettings::Cnn(c) => {
            let path = c.options.model.display();
            let spec = CnnSpec::new(c.options.clone()).map_err(|e| {
                AppError::ModelMismatch(format!(
                    "map `{id:016x}` was created with the model at {path} (sha256 {}), which no \
                     longer loads: {e}",
                    c.identity.sha256
                ))
            })?;
            if let Some(diff) = c.identity.mismatch(&spec.identity()) {
                return Err(AppError::ModelMismatch(format!(
                    "map `{id:016x}`: the model at {path} is not the one the map was created with \
                     ({diff}); restore that file or create a new map"
                )));
            }
            Ok(Some(Box::new(spec)))
        }
        DescriptorSettings::Cooc(_) => Err(AppError::MapKind(format!(
            "map `{id:016x}` is a co-occurrence map: it has no global descriptors (localize it \
             with POST /v1/maps/{id:016x}/localize, add drives with /drives)"
        ))),
    }
}
