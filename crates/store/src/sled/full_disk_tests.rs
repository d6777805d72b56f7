//! The embedded store on a full disk (issue 42, defect 5), on a real 16 MiB tmpfs (root only;
//! skipped with a message otherwise): writes fail with [`StoreError::StorageFull`] (507), never
//! an internal error; reads keep working; once space is freed, writes succeed again without
//! reopening the store by hand, and every acknowledged batch is there.

use super::*;
use seasonloc_app::model::DescriptorSettings;
use seasonloc_test_support::tmpfs::Tmpfs;

fn batch(map: u64, n: usize, base: f32) -> ImageBatch {
    let rows = Matrix::from_vec(n, 256, (0..n * 256).map(|k| base + k as f32).collect()).unwrap();
    ImageBatch::new(map, rows, vec![ImageMeta::default(); n]).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_refuses_writes_keeps_reads_and_recovers_by_itself() {
    let Some(fs) = tokio::task::spawn_blocking(|| Tmpfs::mount("full disk (sled)", 16))
        .await
        .unwrap()
    else {
        return;
    };
    let dir = fs.path().join("data");
    std::fs::create_dir_all(&dir).unwrap();
    let store: Arc<dyn Store> = Arc::new(SledStore::open(&dir).unwrap());
    let map = store
        .create_map(NewMap {
            id: crate::test_id(),
            name: "full".into(),
            descriptor: DescriptorSettings::Precomputed { dim: 256 },
            idempotency: None,
        })
        .await
        .unwrap();
    let mut acked = 0u32;
    for b in 0..4 {
        acked += store
            .append_images(batch(map.id, 16, b as f32))
            .await
            .unwrap()
            .len() as u32;
    }
    let filler = {
        let fs = &fs;
        fs.fill("filler")
    };
    let mut refused = Vec::new();
    for b in 0..200 {
        match store.append_images(batch(map.id, 16, b as f32)).await {
            Ok(r) => acked += r.len() as u32,
            Err(e) => refused.push(e),
        }
        if refused.len() >= 3 {
            break;
        }
    }
    assert!(
        !refused.is_empty(),
        "200 batches acknowledged on a full disk"
    );
    for e in &refused {
        assert!(
            matches!(e, StoreError::StorageFull(_)),
            "a write on a full disk failed with {e} ({}), want storage_full",
            e.code()
        );
        assert_eq!(e.code().status(), 507);
    }
    // Reads keep working on the full disk.
    let read = store.get_map(map.id).await;
    assert!(
        matches!(&read, Ok(m) if m.image_count == acked),
        "a read on a full disk: {read:?} (acknowledged {acked})"
    );
    std::fs::remove_file(filler).unwrap();
    let started = std::time::Instant::now();
    loop {
        match store.append_images(batch(map.id, 4, 7.0)).await {
            Ok(r) => {
                acked += r.len() as u32;
                break;
            }
            Err(e) if started.elapsed() < std::time::Duration::from_secs(10) => {
                eprintln!("after freeing space: {e}");
                tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            }
            Err(e) => panic!("writes still fail 10 s after space was freed: {e}"),
        }
    }
    let m = store.get_map(map.id).await.unwrap();
    assert_eq!(m.image_count, acked);
    assert_eq!(
        store.descriptors(map.id, 0..acked).await.unwrap().rows(),
        acked as usize
    );
    drop(store);
    // Everything acknowledged is there after a restart too, and the store passes its check.
    let store = SledStore::open(&dir).unwrap();
    assert_eq!(store.get_map(map.id).unwrap().image_count, acked);
}
