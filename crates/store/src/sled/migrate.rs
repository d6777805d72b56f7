//! Layout versions of the store and the steps between them (see `migrations/README.md`).
//!
//! Invariant: a step's changes and its new `schema_version` are applied in one atomic
//! `sled::Batch` and flushed, so a crash between steps leaves a consistent older version that
//! the next start upgrades.

use super::{codec, StoreError, StoreResult};
use crate::OrStore;

/// One layout upgrade.
pub struct Migration {
    /// The version this step produces.
    pub version: u32,
    /// File name in `migrations/`.
    pub file: &'static str,
    /// The file's text (the step's documentation).
    pub doc: &'static str,
    /// Adds this step's changes to the batch (the version key is added by the runner).
    pub apply: fn(&sled::Db, &mut sled::Batch) -> StoreResult<()>,
}

/// One [`Migration`] whose documentation is `migrations/<file>`, so the name and the text cannot
/// drift apart.
macro_rules! step {
    ($version:literal, $file:literal, $apply:expr) => {
        Migration {
            version: $version,
            file: $file,
            doc: include_str!(concat!("../../../../migrations/", $file)),
            apply: $apply,
        }
    };
}

/// Every step, in order.
pub const MIGRATIONS: &[Migration] = &[
    step!(1, "0001_initial.md", nothing_to_convert),
    step!(2, "0002_localizations_by_map.md", localizations_by_map),
    // Version 3 adds descriptor kinds (CNN, co-occurrence) and `C` keys; every version-2
    // record is already valid.
    step!(3, "0003_cnn_and_cooc_maps.md", nothing_to_convert),
    // Layouts before 4 have no trip keys.
    step!(4, "0004_trips.md", nothing_to_convert),
    // Layouts before 5 have no thumbnails or pictures: old maps and results simply have none.
    step!(5, "0005_thumbnails_and_pictures.md", nothing_to_convert),
    // Layout 6 stores a trip's state in parts (`b`, `s`, `r`); the `S` blobs of layouts 4-5
    // stay readable and each is replaced by parts at its trip's next batch.
    step!(6, "0006_trip_state_parts.md", nothing_to_convert),
    // A frame value grew `p_correct` and a status; shorter (older) values are read as such.
    step!(7, "0007_frame_trust.md", nothing_to_convert),
    // A trip record may end with its owner (the key that opened it); older records have none.
    step!(8, "0008_trip_owner.md", nothing_to_convert),
];

/// The layout this build writes.
pub const CURRENT_VERSION: u32 = 8;

/// The stored layout version, if any.
pub fn read_version(db: &sled::Db) -> StoreResult<Option<u32>> {
    match db.get(codec::SCHEMA_VERSION_KEY).or_store()? {
        None => Ok(None),
        Some(v) => {
            let bytes: [u8; 4] = v
                .as_ref()
                .try_into()
                .map_err(|_| StoreError::corrupt(codec::SCHEMA_VERSION_KEY, "expected 4 bytes"))?;
            Ok(Some(u32::from_be_bytes(bytes)))
        }
    }
}

/// Brings `db` to [`CURRENT_VERSION`]; returns the version found (0 for a new store).
pub fn migrate(db: &sled::Db) -> StoreResult<u32> {
    let found = match read_version(db)? {
        Some(v) => v,
        None => {
            if let Some(kv) = db.iter().next() {
                let (k, _) = kv.or_store()?;
                return Err(StoreError::corrupt(
                    &k,
                    "the store holds data but no schema_version; refusing to guess its layout",
                ));
            }
            0
        }
    };
    if found > CURRENT_VERSION {
        return Err(StoreError::UnsupportedSchema {
            found,
            supported: CURRENT_VERSION,
        });
    }
    for step in MIGRATIONS.iter().filter(|m| m.version > found) {
        let mut batch = sled::Batch::default();
        (step.apply)(db, &mut batch)?;
        batch.insert(codec::SCHEMA_VERSION_KEY, &step.version.to_be_bytes());
        db.apply_batch(batch).or_store()?;
        db.flush().or_store()?;
        tracing::info!(
            version = step.version,
            file = step.file,
            "store layout upgraded"
        );
    }
    Ok(found)
}

/// A step that only raises the version: every record of the older layout is valid in the new
/// one (each use in [`MIGRATIONS`] says why).
fn nothing_to_convert(_db: &sled::Db, _batch: &mut sled::Batch) -> StoreResult<()> {
    Ok(())
}

fn localizations_by_map(db: &sled::Db, batch: &mut sled::Batch) -> StoreResult<()> {
    for kv in db.scan_prefix([codec::LOCALIZATION_PREFIX]) {
        let (k, v) = kv.or_store()?;
        let (id, map_id) = codec::decode_localization_ids(&k, &v)?;
        batch.insert(&codec::by_map_key(map_id, id), &[] as &[u8]);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sled::SledStore;
    use seasonloc_app::model::{DescriptorSettings, ImageMeta, LocalizationRecord, MapRecord};
    use seasonloc_app::model::{LocalizationParams, LocalizationResult, LocalizationTimings};
    use seasonloc_app::store::{NewTrip, PageRequest};

    #[test]
    fn steps_are_consecutive_and_documented() {
        for (k, m) in MIGRATIONS.iter().enumerate() {
            assert_eq!(m.version as usize, k + 1);
            assert!(m.file.starts_with(&format!("{:04}_", m.version)));
            assert!(
                m.doc.starts_with(&format!("# {:04}", m.version)),
                "{}",
                m.file
            );
        }
        assert_eq!(MIGRATIONS.last().map(|m| m.version), Some(CURRENT_VERSION));
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../migrations");
        let mut files: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .filter(|n| n != "README.md" && n.ends_with(".md"))
            .collect();
        files.sort();
        let steps: Vec<&str> = MIGRATIONS.iter().map(|m| m.file).collect();
        assert_eq!(files, steps);
    }

    /// Writes a store exactly as layout version 1 did (no by-map index) and opens it.
    #[test]
    fn opens_a_store_written_by_layout_1() {
        let dir = tempfile::tempdir().unwrap();
        let (map_id, locs) = {
            let db = sled::open(dir.path()).unwrap();
            db.insert(codec::SCHEMA_VERSION_KEY, &1u32.to_be_bytes())
                .unwrap();
            let map = MapRecord {
                id: 5,
                name: "old".into(),
                descriptor: DescriptorSettings::Precomputed { dim: 2 },
                dim: Some(2),
                image_count: 2,
                created_ms: 1,
            };
            db.insert(codec::map_key(5), codec::encode_map(&map))
                .unwrap();
            for i in 0..2u32 {
                let v = codec::encode_image(&[i as f32, 1.0], &ImageMeta::default());
                db.insert(codec::image_key(5, i), v).unwrap();
            }
            let mut locs = Vec::new();
            for id in [10u64, 11, 12] {
                let result = LocalizationResult {
                    query_count: 1,
                    reference_count: 2,
                    params: LocalizationParams::new(&Default::default(), 1.0, None),
                    total_cost: 1.0,
                    hypotheses: Vec::new(),
                    predictions: Vec::new(),
                    timings: LocalizationTimings::default(),
                    picture: None,
                };
                let rec = LocalizationRecord {
                    id,
                    map_id: 5,
                    created_ms: id,
                    result,
                };
                db.insert(
                    codec::localization_key(id),
                    codec::encode_localization(&rec).unwrap(),
                )
                .unwrap();
                locs.push(id);
            }
            db.flush().unwrap();
            (map.id, locs)
        };
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.schema_version().unwrap(), CURRENT_VERSION);
        let page = store
            .list_localizations(
                Some(map_id),
                PageRequest {
                    before: None,
                    limit: 10,
                },
            )
            .unwrap();
        let ids: Vec<u64> = page.items.iter().map(|r| r.id).collect();
        assert_eq!(ids, locs.iter().rev().copied().collect::<Vec<_>>());
        assert_eq!(store.references(map_id).unwrap().1.row(1), &[1.0, 1.0]);
        // The upgraded store holds the newer descriptor kinds next to the old maps (layout 3).
        let cnn = DescriptorSettings::Cnn(Box::new(seasonloc_app::model::CnnSettings {
            options: seasonloc_core::features::cnn::CnnOptions::efficientnet_lite0("m.onnx"),
            identity: seasonloc_core::features::cnn::ModelIdentity {
                sha256: "00".repeat(32),
                layer: "block10".into(),
                preprocessing: "224x224".into(),
            },
        }));
        let created = store
            .create_map(seasonloc_app::store::NewMap {
                id: 0x1000,
                name: "cnn".into(),
                descriptor: cnn.clone(),
                idempotency: None,
            })
            .unwrap();
        assert_eq!(store.get_map(created.id).unwrap().descriptor, cnn);
        assert_eq!(store.get_map(map_id).unwrap().name, "old");
        // Trips work on an upgraded store, and deleting the map still removes everything.
        let trip = store
            .create_trip(NewTrip {
                id: 0x1001,
                map_id,
                reference_count: 2,
                params: seasonloc_core::trip::TripParams::default(),
                owner: None,
                base: vec![7],
                snapshot: vec![8],
                idempotency: None,
            })
            .unwrap();
        let page = PageRequest {
            before: None,
            limit: 5,
        };
        assert_eq!(store.list_trips(map_id, page).unwrap().items, vec![trip]);
        // Opening again is a no-op: the upgrade does not run twice.
        drop(store);
        let store = SledStore::open(dir.path()).unwrap();
        assert_eq!(store.schema_version().unwrap(), CURRENT_VERSION);
    }

    #[test]
    fn refuses_newer_layouts_and_unversioned_data() {
        let dir = tempfile::tempdir().unwrap();
        {
            let db = sled::open(dir.path()).unwrap();
            db.insert(codec::SCHEMA_VERSION_KEY, &99u32.to_be_bytes())
                .unwrap();
            db.flush().unwrap();
        }
        assert!(matches!(
            SledStore::open(dir.path()),
            Err(StoreError::UnsupportedSchema { found: 99, .. })
        ));
        let dir = tempfile::tempdir().unwrap();
        {
            let db = sled::open(dir.path()).unwrap();
            db.insert(codec::map_key(1), b"x".to_vec()).unwrap();
            db.flush().unwrap();
        }
        let err = SledStore::open(dir.path()).err().unwrap();
        assert!(err.to_string().contains("no schema_version"), "{err}");
    }
}
