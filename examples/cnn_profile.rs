//! Where one CNN inference spends its time: per-operator and per-node wall time of the loaded
//! plan (the one `CnnSpec` extracts with), for finding what to speed up next. Timings of record
//! live in `benches/cnn.rs`.
//!
//! `cargo run --release --example cnn_profile -- [model.onnx] [layer] [image] [runs]`
//! (defaults: the shipped EfficientNet-Lite0, `block10`, Nordland winter frame 10, 20 runs;
//! stretch to 224x224 as in `benches/cnn.rs`).

use std::collections::HashMap;
use std::time::Duration;

use seasonloc_core::features::cnn::{CnnOptions, CnnResize, CnnSpec};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, default: &str| args.get(i).cloned().unwrap_or_else(|| default.into());
    let shared = |rel: &str| {
        seasonloc_test_support::datasets::resolve(rel)
            .map(|p| p.display().to_string())
            .unwrap_or_else(|| rel.to_string())
    };
    let model = args
        .first()
        .cloned()
        .unwrap_or_else(|| shared("models/efficientnet-lite0-224.onnx"));
    let layer = arg(1, "block10");
    let image = args
        .get(2)
        .cloned()
        .unwrap_or_else(|| shared("data/nordland_64x32/winter/images-00010.png"));
    let runs: usize = arg(3, "20").parse()?;

    let mut options = CnnOptions::efficientnet_lite0(&model);
    options.layer = layer.clone();
    options.resize = CnnResize::Stretch;
    let spec = CnnSpec::new(options)?;
    let times = spec.node_times(&image::open(&image)?, runs)?;
    let ms = |d: Duration| d.as_secs_f64() * 1e3 / runs as f64;
    let total: Duration = times.iter().map(|t| t.total).sum();
    println!(
        "{model} -> {layer}, {image}, {runs} runs: {:.2} ms/image in nodes",
        ms(total)
    );

    let mut by_op: HashMap<&str, (Duration, usize)> = HashMap::new();
    for t in &times {
        let e = by_op.entry(&t.op).or_default();
        e.0 += t.total;
        e.1 += 1;
    }
    let mut by_op: Vec<_> = by_op.into_iter().collect();
    by_op.sort_by_key(|(_, (d, _))| std::cmp::Reverse(*d));
    println!("\nby operator (ms/image, nodes):");
    for (op, (d, n)) in by_op {
        println!("  {:>7.3}  {n:>3}  {op}", ms(d));
    }
    println!("\nslowest nodes (ms/image):");
    for t in times.iter().take(30) {
        println!("  {:>7.3}  {} {} -> {}", ms(t.total), t.op, t.name, t.shape);
    }
    Ok(())
}
