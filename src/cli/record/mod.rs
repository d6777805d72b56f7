//! `seasonloc import` and `seasonloc drive`: a vehicle's recording (a video or a folder of
//! images, with an optional GPS track) against a running service.
//!
//! * `import` builds a map: it creates the map (or appends to `--map`), chooses frames by
//!   distance along the track, by time or by step ([`source::Every`]), gives each image its
//!   time, interpolated position and a label, and uploads batches, each under an
//!   `Idempotency-Key` derived from the map, the batch's place and its files: run again after an
//!   interruption, it re-sends only what the service does not hold (a created map is found
//!   again by the same key), so every selected frame ends in the map exactly once.
//! * `drive` replays a recording as a trip (the same frame selection), in batches, as fast as
//!   the service answers or at the recording's pace, and writes every estimate as JSON lines or
//!   CSV with the matched image's position.
//!
//! Code: [`track`] (GPX, NMEA, CSV tracks; time; haversine), [`source`] (folders, videos
//! through the `ffmpeg` program, selection), [`camera`] (a JPEG's own time and GPS position),
//! [`client`] (the HTTP calls).

pub mod camera;
pub mod client;
pub mod source;
pub mod track;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};

use client::{Client, Part};
use source::Every;
use track::Track;

/// Where the recording is and how its frames are read and chosen (shared by both commands).
#[derive(Debug, Clone, Args)]
pub struct RecordingArgs {
    /// A video file (MP4, MKV, ...: whatever `ffmpeg` reads) or a folder of images.
    pub source: PathBuf,
    /// The service (`http://host:port`).
    #[arg(
        long,
        env = "SEASONLOC_SERVER",
        default_value = "http://127.0.0.1:8080"
    )]
    pub server: String,
    /// API key (sent as a bearer token).
    #[arg(long, env = "SEASONLOC_API_KEY", hide_env_values = true)]
    pub key: Option<String>,
    /// GPS track of the recording: GPX, NMEA 0183 (`.nmea`) or CSV
    /// (`timestamp,latitude,longitude[,heading]`), aligned by time.
    #[arg(long)]
    pub track: Option<PathBuf>,
    /// When frame 0 was taken (RFC 3339 or Unix seconds/ms); default: the video's creation
    /// time.
    #[arg(long, value_parser = track::parse_time)]
    pub start: Option<i64>,
    /// Seconds added to every frame's time (a camera clock ahead of the GPS: negative).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub offset: f64,
    /// Frames per second: a video is sampled at this rate; a folder's images are this far
    /// apart in time.
    #[arg(long, default_value_t = 10.0)]
    pub fps: f64,
    /// Which frames to keep: `2m` (distance along the track), `0.5s` (time) or `3` (every
    /// third frame).
    #[arg(long, default_value = "1")]
    pub every: Every,
    /// Images per request.
    #[arg(long, default_value_t = 20)]
    pub batch: usize,
}

/// `seasonloc import`: a recording to a map.
#[derive(Debug, Clone, Args)]
pub struct ImportArgs {
    #[command(flatten)]
    pub recording: RecordingArgs,
    /// Append to this map instead of creating one.
    #[arg(long, conflicts_with = "name")]
    pub map: Option<String>,
    /// Name of the map to create.
    #[arg(long, required_unless_present = "map")]
    pub name: Option<String>,
    /// Descriptor of a new map.
    #[arg(long, value_enum, default_value = "hog")]
    pub descriptor: DescriptorKind,
    /// HOG cell size in pixels (new HOG maps).
    #[arg(long, default_value_t = 8)]
    pub cell_size: u32,
    /// CNN layer (new CNN maps), e.g. `block10`.
    #[arg(long, default_value = "block10")]
    pub layer: String,
    /// CNN model on the server (new CNN maps; default: the server's `--cnn-model`).
    #[arg(long)]
    pub model: Option<String>,
}

/// Descriptor kinds `import` can create.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum DescriptorKind {
    /// HOG on a dense cell grid.
    Hog,
    /// A layer of an ONNX CNN.
    Cnn,
}

/// `seasonloc drive`: a recording replayed as a trip.
#[derive(Debug, Clone, Args)]
pub struct DriveArgs {
    #[command(flatten)]
    pub recording: RecordingArgs,
    /// The map to drive on.
    #[arg(long)]
    pub map: String,
    /// Post each batch when the recording reached its last frame (the recording's pace)
    /// instead of as fast as the service answers.
    #[arg(long, conflicts_with = "fast")]
    pub realtime: bool,
    /// As fast as the service answers (the default).
    #[arg(long)]
    pub fast: bool,
    /// Write the estimates here (`.csv` for CSV, anything else JSON lines); default stdout.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Ground truth of the recording's frames (the CSV `eval` reads: `query_index` is the
    /// frame's place in the recording): the summary then holds `eval`'s metrics of the
    /// estimates, ranked by their confidence.
    #[arg(long)]
    pub ground_truth: Option<PathBuf>,
    /// With `--ground-truth`: a reference within this many frames of the true one is correct.
    #[arg(long, default_value_t = 0)]
    pub tolerance: usize,
    /// With `--ground-truth`: recording frames left out of the metrics, e.g. `0-16`.
    #[arg(long, value_parser = seasonloc_core::eval::Exclusions::parse)]
    pub exclude: Option<seasonloc_core::eval::Exclusions>,
}

fn digest(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    h.finalize()[..16]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The frames of a recording the arguments choose, with their positions.
fn chosen(args: &RecordingArgs) -> Result<(source::Recording, Vec<source::Chosen>, usize)> {
    if args.batch == 0 {
        bail!("--batch must be at least 1");
    }
    if !args.offset.is_finite() {
        bail!("--offset must be a number of seconds");
    }
    let mut track = args.track.as_deref().map(Track::read).transpose()?;
    let mut recording = source::open(&args.source, args.fps, args.start)?;
    // A folder of camera JPEGs given without --start and --track: their EXIF times, and their
    // EXIF positions as the track.
    if args.start.is_none() && args.track.is_none() && args.source.is_dir() {
        let taken: Vec<camera::Taken> = recording
            .frames
            .iter()
            .map(|f| camera::read(&f.path))
            .collect();
        if taken.iter().all(|t| t.t_ms.is_some()) {
            for (f, t) in recording.frames.iter_mut().zip(&taken) {
                f.t_ms = t.t_ms;
            }
            if taken.iter().all(|t| t.position.is_some()) {
                let fixes = taken
                    .iter()
                    .filter_map(|t| {
                        let (lat, lon) = t.position?;
                        Some(track::Fix {
                            t_ms: t.t_ms?,
                            lat,
                            lon,
                        })
                    })
                    .collect();
                track = Some(Track::new(fixes, 0)?);
            }
        }
    }
    let shift = (args.offset * 1000.0).round() as i64;
    for f in &mut recording.frames {
        f.t_ms = f.t_ms.map(|t| t + shift);
    }
    let kept = source::select(&recording.frames, args.every, track.as_ref())?;
    Ok((recording, kept, track.map_or(0, |t| t.skipped)))
}

fn progress(len: usize, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} ({eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_string());
    bar
}

/// Runs `import`; answers `{"map_id", "selected", "uploaded", "already_stored", ...}`.
pub fn import(args: &ImportArgs) -> Result<Value> {
    let r = &args.recording;
    let client = Client::new(&r.server, r.key.clone())?;
    let (_recording, kept, skipped) = chosen(r)?;
    let source_id = std::fs::canonicalize(&r.source)
        .unwrap_or_else(|_| r.source.clone())
        .to_string_lossy()
        .into_owned();
    let (map_id, created) = match (&args.map, &args.name) {
        (Some(id), _) => (id.clone(), false),
        (None, Some(name)) => {
            let descriptor = match args.descriptor {
                DescriptorKind::Hog => json!({"kind": "hog", "cell_size": args.cell_size}),
                DescriptorKind::Cnn => {
                    let mut d = json!({"kind": "cnn", "layer": args.layer});
                    if let Some(m) = &args.model {
                        d["model"] = json!(m);
                    }
                    d
                }
            };
            let body = json!({"name": name, "descriptor": descriptor});
            // The same import (name, descriptor, source) finds its map again.
            let key = format!(
                "import-map-{}",
                digest(&[body.to_string().as_bytes(), source_id.as_bytes()])
            );
            let map = client.post_json("/v1/maps", Some(&body), Some(&key))?;
            let id = map["id"]
                .as_str()
                .ok_or_else(|| anyhow::anyhow!("the created map has no id: {map}"))?
                .to_string();
            (id, true)
        }
        (None, None) => bail!("give --name (a new map) or --map (append)"),
    };
    let map = client.get(&format!("/v1/maps/{map_id}"))?;
    let stored = map["image_count"].as_u64().unwrap_or(0) as usize;
    let label_of = |f: &source::Frame| {
        f.path.file_name().map_or_else(
            || format!("frame {}", f.index),
            |n| n.to_string_lossy().into_owned(),
        )
    };
    let bar = progress(kept.len(), "uploading");
    let (mut uploaded, mut already) = (0usize, 0usize);
    for (b, chunk) in kept.chunks(r.batch).enumerate() {
        let first = b * r.batch;
        // A map this import created holds its batches in order: those below its count are in.
        if created && first + chunk.len() <= stored {
            already += chunk.len();
            bar.inc(chunk.len() as u64);
            continue;
        }
        let files: Vec<Vec<u8>> = chunk
            .iter()
            .map(|(f, _)| {
                std::fs::read(&f.path).with_context(|| format!("reading {}", f.path.display()))
            })
            .collect::<Result<_>>()?;
        let names: Vec<String> = chunk.iter().map(|(f, _)| label_of(f)).collect();
        let metadata: Vec<Value> = chunk
            .iter()
            .zip(&names)
            .map(|((f, at), name)| {
                json!({
                    "timestamp": f.t_ms.map(track::format_time),
                    "latitude": at.map(|a| a.0),
                    "longitude": at.map(|a| a.1),
                    "label": name,
                })
            })
            .collect();
        let metadata = Value::Array(metadata);
        let mut hashed: Vec<&[u8]> = vec![map_id.as_bytes()];
        let place = first.to_le_bytes();
        hashed.push(&place);
        let meta_bytes = metadata.to_string();
        hashed.push(meta_bytes.as_bytes());
        for f in &files {
            hashed.push(f);
        }
        let key = format!("import-{}", digest(&hashed));
        let mut parts: Vec<Part<'_>> = files
            .iter()
            .zip(&names)
            .map(|(bytes, name)| Part::Image { name, bytes })
            .collect();
        parts.push(Part::Json {
            name: "metadata",
            value: &metadata,
        });
        client.post_multipart(&format!("/v1/maps/{map_id}/images"), &parts, &key)?;
        uploaded += chunk.len();
        bar.inc(chunk.len() as u64);
    }
    bar.finish_and_clear();
    let map = client.get(&format!("/v1/maps/{map_id}"))?;
    Ok(json!({
        "map_id": map_id,
        "created": created,
        "frames": _recording.frames.len(),
        "selected": kept.len(),
        "uploaded": uploaded,
        "already_stored": already,
        "image_count": map["image_count"],
        "track_sentences_skipped": skipped,
    }))
}

/// The map's image metadata by index (for the positions of estimates).
fn map_places(client: &Client, map: &str) -> Result<Vec<Value>> {
    let mut out = Vec::new();
    let mut from = 0u64;
    loop {
        let page = client.get(&format!("/v1/maps/{map}/images?from={from}&limit=1000"))?;
        out.extend(page["items"].as_array().cloned().unwrap_or_default());
        match page["next"].as_u64() {
            Some(n) if n > from => from = n,
            _ => return Ok(out),
        }
    }
}

/// Runs `drive`; writes one line per estimate, answers a summary.
pub fn drive(args: &DriveArgs) -> Result<Value> {
    let r = &args.recording;
    let client = Client::new(&r.server, r.key.clone())?;
    let ground_truth = args
        .ground_truth
        .as_deref()
        .map(seasonloc_core::eval::GroundTruth::from_csv)
        .transpose()?;
    let (recording, kept, _) = chosen(r)?;
    let places = map_places(&client, &args.map)?;
    let mut predictions = Vec::new();
    let csv = args
        .out
        .as_deref()
        .and_then(Path::extension)
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
    let mut out: Box<dyn Write> = match &args.out {
        Some(p) => Box::new(std::io::BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("cannot write {}", p.display()))?,
        )),
        None => Box::new(std::io::stdout().lock()),
    };
    if csv {
        writeln!(
            out,
            "frame,source_index,time,ref,status,confidence,p_correct,latitude,longitude,label"
        )?;
    }
    let trip = client.post_json(&format!("/v1/maps/{}/trips", args.map), None, None)?;
    let trip_id = trip["id"]
        .as_str()
        .ok_or_else(|| anyhow::anyhow!("the opened trip has no id: {trip}"))?
        .to_string();
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let started = Instant::now();
    let t0 = kept.first().and_then(|(f, _)| f.t_ms);
    let mut sent = 0usize;
    let mut counts = std::collections::BTreeMap::<String, usize>::new();
    for chunk in kept.chunks(r.batch) {
        if args.realtime {
            if let (Some(t0), Some(t)) = (t0, chunk.last().and_then(|(f, _)| f.t_ms)) {
                let due = Duration::from_millis((t - t0).max(0) as u64);
                if let Some(wait) = due.checked_sub(started.elapsed()) {
                    std::thread::sleep(wait);
                }
            }
        }
        let files: Vec<Vec<u8>> = chunk
            .iter()
            .map(|(f, _)| {
                std::fs::read(&f.path).with_context(|| format!("reading {}", f.path.display()))
            })
            .collect::<Result<_>>()?;
        let names: Vec<String> = chunk
            .iter()
            .map(|(f, _)| format!("frame-{}.img", f.index))
            .collect();
        let parts: Vec<Part<'_>> = files
            .iter()
            .zip(&names)
            .map(|(bytes, name)| Part::Image { name, bytes })
            .collect();
        let key = format!("drive-{trip_id}-{sent}");
        let answer = client.post_multipart(&format!("/v1/trips/{trip_id}/frames"), &parts, &key)?;
        let estimates = answer["estimates"].as_array().cloned().unwrap_or_default();
        for e in &estimates {
            let frame = e["frame"].as_u64().unwrap_or(0) as usize;
            let (src, _) = kept.get(frame).map_or((None, None), |(f, a)| (Some(f), *a));
            let reference = e["ref"].as_u64();
            let place = reference.and_then(|i| places.get(i as usize));
            let status = e["status"].as_str().unwrap_or("");
            *counts.entry(status.to_string()).or_default() += 1;
            if let (Some(f), Some(reference), Some(confidence)) =
                (src, reference, e["confidence"].as_f64())
            {
                predictions.push(seasonloc_core::eval::Prediction {
                    query: f.index,
                    reference: reference as usize,
                    confidence,
                    p_correct: e["p_correct"].as_f64(),
                });
            }
            let row = json!({
                "frame": frame,
                "source_index": src.map(|f| f.index),
                "time": src.and_then(|f| f.t_ms).map(track::format_time),
                "ref": reference,
                "status": status,
                "confidence": e["confidence"],
                "p_correct": e["p_correct"],
                "latitude": place.map_or(Value::Null, |p| p["latitude"].clone()),
                "longitude": place.map_or(Value::Null, |p| p["longitude"].clone()),
                "label": place.map_or(Value::Null, |p| p["label"].clone()),
            });
            if csv {
                let cell = |v: &Value| match v {
                    Value::Null => String::new(),
                    Value::String(s) => format!("\"{}\"", s.replace('"', "\"\"")),
                    other => other.to_string(),
                };
                let cols = [
                    "frame",
                    "source_index",
                    "time",
                    "ref",
                    "status",
                    "confidence",
                    "p_correct",
                    "latitude",
                    "longitude",
                    "label",
                ];
                let line: Vec<String> = cols.iter().map(|c| cell(&row[*c])).collect();
                writeln!(out, "{}", line.join(","))?;
            } else {
                writeln!(out, "{row}")?;
            }
        }
        sent += chunk.len();
        if terminal {
            let last = estimates.last();
            eprint!(
                "\rframe {sent}/{}  ref {}  {}   ",
                kept.len(),
                last.and_then(|e| e["ref"].as_u64())
                    .map_or("-".into(), |v| v.to_string()),
                answer["status"].as_str().unwrap_or("")
            );
        }
    }
    if terminal {
        eprintln!();
    }
    out.flush()?;
    client.post_json(&format!("/v1/trips/{trip_id}/close"), None, None)?;
    let mut summary = json!({"trip_id": trip_id, "frames": sent, "statuses": counts});
    if let Some(gt) = &ground_truth {
        let none = seasonloc_core::eval::Exclusions::none();
        let m = seasonloc_core::eval::evaluate(
            &predictions,
            gt,
            recording.frames.len(),
            args.tolerance,
            args.exclude.as_ref().unwrap_or(&none),
        )?;
        summary["metrics"] = super::eval::metrics_json(&m);
    }
    Ok(summary)
}
