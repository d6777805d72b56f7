//! A damaged embedded store (issue 42, defect 4): its file truncated, bytes flipped, a page
//! zeroed. Every trial either refuses to open with [`StoreError::Damaged`] (never a panic) or
//! opens with every acknowledged record intact; an untouched copy opens with everything.

use super::*;
use seasonloc_app::model::DescriptorSettings;

/// Maps and their descriptor rows, as acknowledged.
type Truth = Vec<(u64, Matrix)>;

fn fill(store: &SledStore) -> Truth {
    let mut truth = Vec::new();
    for m in 0..6u32 {
        let map = store
            .create_map(NewMap {
                id: crate::test_id(),
                name: format!("m{m}"),
                descriptor: DescriptorSettings::Precomputed { dim: 64 },
                idempotency: None,
            })
            .unwrap();
        let mut all = Vec::new();
        for b in 0..8u32 {
            let n = 16;
            let data: Vec<f32> = (0..n * 64)
                .map(|k| (m * 1000 + b * 100) as f32 + k as f32 * 0.5)
                .collect();
            all.extend_from_slice(&data);
            let rows = Matrix::from_vec(n, 64, data).unwrap();
            let metas = vec![ImageMeta::default(); n];
            store
                .append_images(&ImageBatch::new(map.id, rows, metas).unwrap())
                .unwrap();
        }
        truth.push((map.id, Matrix::from_vec(all.len() / 64, 64, all).unwrap()));
    }
    truth
}

/// What is missing or different from `truth` (empty: everything is there).
fn missing(store: &SledStore, truth: &Truth) -> Vec<String> {
    let mut out = Vec::new();
    for (id, rows) in truth {
        match store.get_map(*id) {
            Ok(m) if m.image_count as usize == rows.rows() => {}
            Ok(m) => out.push(format!("map {id:x}: {} images", m.image_count)),
            Err(e) => out.push(format!("map {id:x}: {e}")),
        }
        match store.descriptors(*id, 0..rows.rows() as u32) {
            Ok(got) if got == *rows => {}
            Ok(_) => out.push(format!("map {id:x}: other descriptors")),
            Err(e) => out.push(format!("map {id:x} descriptors: {e}")),
        }
    }
    out
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// A small deterministic generator for the flipped offsets.
fn offsets(seed: u64, below: u64, n: usize) -> Vec<u64> {
    let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x % below
        })
        .collect()
}

type Damage = Box<dyn Fn(&Path, u64)>;

fn truncate(frac: f64) -> Damage {
    Box::new(move |f, size| {
        let file = std::fs::OpenOptions::new().write(true).open(f).unwrap();
        file.set_len((size as f64 * frac) as u64).unwrap();
    })
}

fn flip(seed: u64) -> Damage {
    Box::new(move |f, size| {
        let mut bytes = std::fs::read(f).unwrap();
        for off in offsets(seed, size, 16) {
            bytes[off as usize] ^= 0xff;
        }
        std::fs::write(f, bytes).unwrap();
    })
}

fn zero_page_at_half() -> Damage {
    Box::new(|f, size| {
        let mut bytes = std::fs::read(f).unwrap();
        let at = (size / 2 / 4096 * 4096) as usize;
        let end = (at + 4096).min(bytes.len());
        bytes[at..end].fill(0);
        std::fs::write(f, bytes).unwrap();
    })
}

#[test]
fn a_damaged_store_is_refused_or_intact_never_silently_short() {
    let gold = tempfile::tempdir().unwrap();
    let truth = {
        let store = SledStore::open(gold.path()).unwrap();
        let truth = fill(&store);
        store.flush().unwrap();
        truth
    };
    let db = gold.path().join("db");
    let size = std::fs::metadata(&db).unwrap().len();
    assert!(
        size > 64 * 1024,
        "a store file of {size} B is too small to damage"
    );
    let trials: Vec<(&str, Option<Damage>)> = vec![
        ("untouched", None),
        ("truncated to 1/4", Some(truncate(0.25))),
        ("truncated to 1/2", Some(truncate(0.5))),
        ("truncated to 3/4", Some(truncate(0.75))),
        ("16 bytes flipped, seed 1", Some(flip(1))),
        ("16 bytes flipped, seed 2", Some(flip(2))),
        ("16 bytes flipped, seed 3", Some(flip(3))),
        ("the page at 1/2 zeroed", Some(zero_page_at_half())),
    ];
    let mut fails = Vec::new();
    for (what, damage) in &trials {
        let dir = tempfile::tempdir().unwrap();
        copy_dir(gold.path(), dir.path());
        if let Some(d) = damage {
            d(&dir.path().join("db"), size);
        }
        let opened = std::panic::catch_unwind(|| SledStore::open(dir.path()));
        match opened {
            Err(_) => fails.push(format!("{what}: panicked")),
            Ok(Ok(store)) => {
                let miss = missing(&store, &truth);
                if !miss.is_empty() {
                    fails.push(format!("{what}: opened with {}", miss.join("; ")));
                }
            }
            Ok(Err(StoreError::Damaged { reason, .. })) if damage.is_some() => {
                eprintln!("{what}: refused: {reason}");
            }
            Ok(Err(e)) => fails.push(format!("{what}: {e}")),
        }
    }
    assert!(fails.is_empty(), "{}", fails.join("\n"));
}

/// A store written before the ledger existed (no `meta/generation`, no ledger file) opens
/// with everything, and starts its ledger.
#[test]
fn a_store_without_a_ledger_opens_and_starts_one() {
    let dir = tempfile::tempdir().unwrap();
    let truth = {
        let store = SledStore::open(dir.path()).unwrap();
        fill(&store)
    };
    std::fs::remove_file(dir.path().join(ledger::FILE_NAME)).unwrap();
    let store = SledStore::open(dir.path()).unwrap();
    assert!(missing(&store, &truth).is_empty());
    assert!(matches!(
        ledger::read(dir.path()).unwrap(),
        ledger::Found::Generation(g) if g > 0
    ));
}

/// A store rolled back to an older copy of itself (a consistent store, older than what was
/// acknowledged) is refused, and accepted once its ledger is removed (the documented repair).
#[test]
fn a_store_older_than_its_ledger_is_refused_until_the_ledger_is_removed() {
    let dir = tempfile::tempdir().unwrap();
    let old = tempfile::tempdir().unwrap();
    {
        let store = SledStore::open(dir.path()).unwrap();
        fill(&store);
    }
    copy_dir(dir.path(), old.path());
    {
        let store = SledStore::open(dir.path()).unwrap();
        fill(&store);
    }
    // The old files, the new ledger.
    for f in ["db", "conf"] {
        std::fs::copy(old.path().join(f), dir.path().join(f)).unwrap();
    }
    for e in std::fs::read_dir(dir.path()).unwrap() {
        let name = e.unwrap().file_name();
        if name.to_string_lossy().starts_with("snap.") {
            std::fs::remove_file(dir.path().join(name)).unwrap();
        }
    }
    for e in std::fs::read_dir(old.path()).unwrap() {
        let name = e.unwrap().file_name();
        if name.to_string_lossy().starts_with("snap.") {
            std::fs::copy(old.path().join(&name), dir.path().join(&name)).unwrap();
        }
    }
    match SledStore::open(dir.path()) {
        Err(StoreError::Damaged { reason, .. }) => {
            assert!(reason.contains("acknowledged"), "{reason}")
        }
        Err(e) => panic!("expected Damaged, got {e}"),
        Ok(_) => panic!("a rolled-back store was opened"),
    }
    std::fs::remove_file(dir.path().join(ledger::FILE_NAME)).unwrap();
    SledStore::open(dir.path()).unwrap();
}
