//! `seasonloc import` and `seasonloc drive` (issue 46) against a real server: frames chosen by
//! distance along a GPX track with varying speed and a stop (checked against a hand
//! computation), interpolated positions, an interrupted import run again, a drive equal to
//! posting the same frames, a video through `ffmpeg`, and bad input refused before any map.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

use crate::common::{Route, Server};
use crate::http::{Client, Part};

/// Metres per degree of latitude on the sphere the import uses.
const M_PER_DEG: f64 = std::f64::consts::PI * 6_371_008.8 / 180.0;
/// 2026-05-01T10:00:00Z in Unix milliseconds.
const T0: i64 = 1_777_629_600_000;

/// The route's speed profile: 5 m/s for 2 s, stopped for 1 s, 10 m/s for 3 s (fixes each second).
fn along_at(t_s: f64) -> f64 {
    if t_s <= 2.0 {
        5.0 * t_s
    } else if t_s <= 3.0 {
        10.0
    } else {
        10.0 + 10.0 * (t_s - 3.0)
    }
}

fn write_gpx(path: &Path) {
    let mut pts = String::new();
    for s in 0..=6 {
        let lat = along_at(f64::from(s)) / M_PER_DEG;
        let secs = s;
        pts.push_str(&format!(
            "<trkpt lat=\"{lat:.9}\" lon=\"0.000000000\"><time>2026-05-01T10:00:0{secs}Z</time></trkpt>\n"
        ));
    }
    std::fs::write(
        path,
        format!("<?xml version=\"1.0\"?><gpx version=\"1.1\"><trk><trkseg>\n{pts}</trkseg></trk></gpx>\n"),
    )
    .unwrap();
}

/// 60 frames of `route` (references or queries) as PNG files `f000.png` .. in `dir`.
fn write_frames(dir: &Path, route: &Route, query: bool) {
    std::fs::create_dir_all(dir).unwrap();
    for i in 0..60 {
        let png = if query {
            route.query_png(i)
        } else {
            route.reference_png(i)
        };
        std::fs::write(dir.join(format!("f{i:03}.png")), png).unwrap();
    }
}

/// The frames `--every 2m` keeps, computed by hand: frame i is at 0.1 i s; a frame is kept
/// when it is at least 2 m beyond the last kept one.
fn hand_selection() -> Vec<usize> {
    let mut kept = vec![0];
    let mut last = 0.0;
    for i in 1..60 {
        let d = along_at(i as f64 * 0.1);
        if d - last >= 2.0 - 1e-9 {
            kept.push(i);
            last = d;
        }
    }
    kept
}

fn seasonloc(args: &[&str], server: &str) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(args)
        .env("SEASONLOC_SERVER", server)
        .env_remove("SEASONLOC_API_KEY")
        .output()
        .unwrap()
}

fn ok(out: &std::process::Output) -> Value {
    assert!(
        out.status.success(),
        "exit {:?}: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn images(c: &Client, map: &str) -> Vec<Value> {
    c.get(&format!("/v1/maps/{map}/images?limit=1000")).json()["items"]
        .as_array()
        .unwrap()
        .clone()
}

#[test]
fn import_keeps_the_frames_the_distance_rule_selects_at_their_positions_once() {
    let server = Server::start();
    let url = format!("http://{}", server.client.addr);
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    write_frames(&frames, &Route::new(60, 11), false);
    let gpx = dir.path().join("drive.gpx");
    write_gpx(&gpx);
    // Frame 36 (a selected one) is damaged: the first run stops there, the batches before it stored.
    let good = std::fs::read(frames.join("f036.png")).unwrap();
    std::fs::write(frames.join("f036.png"), b"not a png").unwrap();
    let start = T0.to_string();
    let args = [
        "import",
        frames.to_str().unwrap(),
        "--name",
        "gpx-route",
        "--track",
        gpx.to_str().unwrap(),
        "--start",
        &start,
        "--fps",
        "10",
        "--every",
        "2m",
        "--batch",
        "3",
    ];
    let out = seasonloc(&args, &url);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("422 invalid_image") && err.contains("f036.png"),
        "{err}"
    );
    let maps = server.client.get("/v1/maps").json();
    let map = maps["maps"][0]["id"].as_str().unwrap().to_string();
    let before = images(&server.client, &map).len();
    let expected = hand_selection();
    assert!(
        before > 0 && before < expected.len(),
        "{before} of {}",
        expected.len()
    );

    // Run again, repaired: the same map, every selected frame exactly once, in order.
    std::fs::write(frames.join("f036.png"), good).unwrap();
    let summary = ok(&seasonloc(&args, &url));
    assert_eq!(summary["map_id"], map.as_str());
    assert_eq!(
        server.client.get("/v1/maps").json()["maps"]
            .as_array()
            .unwrap()
            .len(),
        1
    );
    let stored = images(&server.client, &map);
    let labels: Vec<String> = stored
        .iter()
        .map(|i| i["label"].as_str().unwrap().to_string())
        .collect();
    let want: Vec<String> = expected.iter().map(|i| format!("f{i:03}.png")).collect();
    assert_eq!(labels, want, "the distance rule's frames, once each");
    for (img, &i) in stored.iter().zip(&expected) {
        let d = along_at(i as f64 * 0.1);
        let lat = img["latitude"].as_f64().unwrap();
        assert!(
            (lat * M_PER_DEG - d).abs() < 0.5,
            "frame {i}: {} m along, expected {d}",
            lat * M_PER_DEG
        );
        assert_eq!(img["longitude"].as_f64(), Some(0.0));
        assert!(img["timestamp"]
            .as_str()
            .unwrap()
            .starts_with("2026-05-01T10:00:0"));
    }
}

#[test]
fn a_drive_gives_the_estimates_that_posting_its_frames_gives() {
    let server = Server::start();
    let c = &server.client;
    let url = format!("http://{}", c.addr);
    let dir = tempfile::tempdir().unwrap();
    let route = Route::new(60, 5);
    let refs = dir.path().join("refs");
    let queries = dir.path().join("queries");
    write_frames(&refs, &route, false);
    write_frames(&queries, &route, true);
    let summary = ok(&seasonloc(
        &[
            "import",
            refs.to_str().unwrap(),
            "--name",
            "drive-route",
            "--batch",
            "25",
        ],
        &url,
    ));
    let map = summary["map_id"].as_str().unwrap().to_string();
    assert_eq!(summary["image_count"], 60);
    let out_file = dir.path().join("estimates.jsonl");
    let gt = dir.path().join("gt.csv");
    let mut rows = String::from("query_index,query_file,ref_index,ref_file\n");
    for i in 0..60 {
        rows.push_str(&format!("{i},queries/f{i:03}.png,{i},refs/f{i:03}.png\n"));
    }
    std::fs::write(&gt, rows).unwrap();
    let drive = seasonloc(
        &[
            "drive",
            queries.to_str().unwrap(),
            "--map",
            &map,
            "--batch",
            "10",
            "--out",
            out_file.to_str().unwrap(),
            "--ground-truth",
            gt.to_str().unwrap(),
        ],
        &url,
    );
    let summary = ok(&drive);
    assert_eq!(summary["frames"], 60);
    let driven: Vec<Value> = std::fs::read_to_string(&out_file)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(driven.len(), 60);
    // The metrics count what the estimates say (tolerance 0: the true reference of frame i is i).
    let with_ref = driven.iter().filter(|d| !d["ref"].is_null()).count();
    let right = driven.iter().filter(|d| d["ref"] == d["frame"]).count();
    assert_eq!(summary["metrics"]["predicted"], with_ref);
    assert_eq!(summary["metrics"]["correct"], right);
    assert_eq!(summary["metrics"]["positives"], 60);
    assert!(right > 40, "the drive localized only {right} of 60 frames");

    // The same frames posted by hand to a second trip.
    let trip = c.request("POST", &format!("/v1/maps/{map}/trips"), None, &[]);
    let trip = trip.json()["id"].as_str().unwrap().to_string();
    let mut by_hand = Vec::new();
    for start in (0..60).step_by(10) {
        let parts: Vec<Part> = (start..start + 10)
            .map(|i| {
                Part::image(
                    &format!("q{i}.png"),
                    std::fs::read(queries.join(format!("f{i:03}.png"))).unwrap(),
                )
            })
            .collect();
        let r = c.post_multipart(&format!("/v1/trips/{trip}/frames"), &parts);
        assert_eq!(r.status, 200);
        by_hand.extend(r.json()["estimates"].as_array().unwrap().clone());
    }
    for (d, h) in driven.iter().zip(&by_hand) {
        assert_eq!(d["frame"], h["frame"]);
        assert_eq!(d["ref"], h["ref"]);
        assert_eq!(d["status"], h["status"]);
        assert_eq!(d["confidence"], h["confidence"]);
    }
    // The trip the drive opened is closed, with all its frames.
    let trips = c.get(&format!("/v1/maps/{map}/trips")).json();
    let driven_trip = trips["items"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["id"] != trip.as_str())
        .unwrap()
        .clone();
    assert_eq!(driven_trip["frame_count"], 60);
    assert!(!driven_trip["closed_at_ms"].is_null());
}

#[test]
fn an_import_killed_midway_and_run_again_stores_every_frame_once() {
    let server = Server::start();
    let url = format!("http://{}", server.client.addr);
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    write_frames(&frames, &Route::new(60, 4), false);
    let args = [
        "import",
        frames.to_str().unwrap(),
        "--name",
        "killed",
        "--batch",
        "1",
    ];
    let mut child = Command::new(env!("CARGO_BIN_EXE_seasonloc"))
        .args(args)
        .env("SEASONLOC_SERVER", &url)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // SIGKILL once some images are in (a batch may be in flight: the service applies it
    // whole or not at all, and the retry's key finds it).
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    loop {
        let maps = server.client.get("/v1/maps").json();
        let count = maps["maps"][0]["image_count"].as_u64().unwrap_or(0);
        if count >= 5 || matches!(child.try_wait(), Ok(Some(_))) {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the import made no progress"
        );
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    child.kill().unwrap();
    let _ = child.wait();
    let summary = ok(&seasonloc(&args, &url));
    assert_eq!(summary["image_count"], 60, "{summary}");
    let map = summary["map_id"].as_str().unwrap();
    let labels: Vec<String> = images(&server.client, map)
        .iter()
        .map(|i| i["label"].as_str().unwrap().to_string())
        .collect();
    let want: Vec<String> = (0..60).map(|i| format!("f{i:03}.png")).collect();
    assert_eq!(labels, want);
    assert_eq!(
        server.client.get("/v1/maps").json()["maps"]
            .as_array()
            .unwrap()
            .len(),
        1
    );
}

#[test]
fn bad_recordings_are_refused_before_any_map_is_made() {
    let server = Server::start();
    let url = format!("http://{}", server.client.addr);
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    write_frames(&frames, &Route::new(60, 2), false);
    let f = frames.to_str().unwrap();
    let gpx = dir.path().join("drive.gpx");
    write_gpx(&gpx);
    let g = gpx.to_str().unwrap();
    let refuse = |args: &[&str], needle: &str| {
        let out = seasonloc(args, &url);
        assert!(!out.status.success(), "{args:?} was accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(
            !err.contains('\n') || err.trim_end().lines().count() == 1,
            "{err}"
        );
    };
    refuse(&["import", f, "--name", "x", "--every", "2km"], "--every");
    // A day later than the track: no overlap in time.
    let late = (T0 + 86_400_000).to_string();
    refuse(
        &[
            "import", f, "--name", "x", "--track", g, "--start", &late, "--every", "2m",
        ],
        "does not overlap the track",
    );
    let empty = dir.path().join("empty.gpx");
    std::fs::write(&empty, "<gpx version=\"1.1\"><trk></trk></gpx>").unwrap();
    let e = empty.to_str().unwrap();
    refuse(
        &["import", f, "--name", "x", "--track", e, "--start", "0"],
        "no points",
    );
    refuse(
        &["import", f, "--name", "x", "--every", "2m"],
        "needs a GPS track",
    );
    let video = dir.path().join("broken.mp4");
    std::fs::write(&video, b"\x00\x00\x00\x18ftypmp42 truncated").unwrap();
    refuse(
        &[
            "import",
            video.to_str().unwrap(),
            "--name",
            "x",
            "--start",
            "0",
        ],
        "ffmpeg",
    );
    assert!(
        server.client.get("/v1/maps").json()["maps"]
            .as_array()
            .unwrap()
            .is_empty(),
        "a refused import left a map"
    );
}

/// Whether the `ffmpeg` program runs; under CI=true it must (`.ci/run` installs it).
fn ffmpeg() -> bool {
    let found = Command::new("ffmpeg")
        .arg("-version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !found {
        assert!(
            std::env::var("CI").map_or(true, |v| v != "true"),
            "ffmpeg is required when CI=true (apt-get install ffmpeg)"
        );
        eprintln!("SKIPPED the video import test: no ffmpeg program (apt-get install ffmpeg)");
    }
    found
}

#[test]
fn a_video_is_imported_through_ffmpeg_frame_for_frame() {
    if !ffmpeg() {
        return;
    }
    let server = Server::start();
    let url = format!("http://{}", server.client.addr);
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    write_frames(&frames, &Route::new(60, 9), false);
    for (name, codec) in [("route.mp4", "libx264"), ("route.mkv", "libx264")] {
        let video = dir.path().join(name);
        let made = Command::new("ffmpeg")
            .args(["-nostdin", "-v", "error", "-y", "-framerate", "10", "-i"])
            .arg(frames.join("f%03d.png"))
            .args(["-c:v", codec, "-pix_fmt", "yuv420p", "-vf", "scale=64:32"])
            .arg(&video)
            .status()
            .unwrap();
        assert!(made.success(), "ffmpeg could not make {name}");
        let summary = ok(&seasonloc(
            &[
                "import",
                video.to_str().unwrap(),
                "--name",
                name,
                "--start",
                "2026-05-01T10:00:00Z",
                "--fps",
                "10",
                "--every",
                "0.5s",
            ],
            &url,
        ));
        // 6 s of video at 10 fps, one frame per 0.5 s.
        assert_eq!(summary["frames"], 60, "{summary}");
        assert_eq!(summary["image_count"], 12, "{summary}");
        let map = summary["map_id"].as_str().unwrap();
        let stored = images(&server.client, map);
        assert_eq!(stored[1]["timestamp"], "2026-05-01T10:00:00.500Z");
    }
}

#[test]
fn an_integer_timestamp_is_unix_milliseconds_and_other_types_are_refused_by_name() {
    let server = Server::start();
    let c = &server.client;
    let map = crate::common::create_hog_map(c, "typed-metadata", 8);
    let route = Route::new(4, 1);
    let post = |meta: serde_json::Value| {
        let parts = vec![
            Part::image("a.png", route.reference_png(0)),
            Part::json("metadata", &meta),
        ];
        c.post_multipart(&format!("/v1/maps/{map}/images"), &parts)
    };
    let r = post(serde_json::json!([{"timestamp": T0 + 500, "label": "a"}]));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let r = post(serde_json::json!([{"timestamp": "dawn"}]));
    assert_eq!(r.status, 200, "a free-form string stays accepted");
    let stored = images(c, &map);
    assert_eq!(stored[0]["timestamp"], "2026-05-01T10:00:00.500Z");
    assert_eq!(stored[1]["timestamp"], "dawn");
    for bad in [
        serde_json::json!([{"timestamp": 1.5}]),
        serde_json::json!([{"timestamp": -1}]),
        serde_json::json!([{"timestamp": true}]),
    ] {
        let r = post(bad.clone());
        assert_eq!(r.status, 400, "{bad}");
        assert_eq!(r.code(), "invalid_parameter");
        assert!(
            r.message().contains("metadata[0].timestamp"),
            "{}",
            r.message()
        );
    }
    assert_eq!(images(c, &map).len(), 2, "a refused batch stored nothing");
}

/// A JPEG of `img` whose EXIF says it was taken at `when` ("YYYY:MM:DD HH:MM:SS", offset
/// +02:00) at latitude `lat` N, longitude `lon` E (built byte by byte: no EXIF writer needed).
fn jpeg_with_exif(img: &image::GrayImage, when: &str, lat: f64, lon: f64) -> Vec<u8> {
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
        .encode_image(img)
        .unwrap();
    let mut t: Vec<u8> = b"II\x2a\x00\x08\x00\x00\x00".to_vec();
    let entry = |t: &mut Vec<u8>, tag: u16, kind: u16, count: u32, value: u32| {
        t.extend(tag.to_le_bytes());
        t.extend(kind.to_le_bytes());
        t.extend(count.to_le_bytes());
        t.extend(value.to_le_bytes());
    };
    let (exif_ifd, gps_ifd) = (38u32, 96u32);
    t.extend(2u16.to_le_bytes());
    entry(&mut t, 0x8769, 4, 1, exif_ifd);
    entry(&mut t, 0x8825, 4, 1, gps_ifd);
    t.extend(0u32.to_le_bytes());
    assert_eq!(t.len(), 38);
    t.extend(2u16.to_le_bytes());
    entry(&mut t, 0x9003, 2, 20, 68);
    entry(&mut t, 0x9011, 2, 7, 88);
    t.extend(0u32.to_le_bytes());
    t.extend(when.as_bytes());
    t.push(0);
    t.extend(b"+02:00\0\0");
    assert_eq!(t.len(), 96);
    t.extend(4u16.to_le_bytes());
    entry(&mut t, 1, 2, 2, u32::from_le_bytes(*b"N\0\0\0"));
    entry(&mut t, 2, 5, 3, 150);
    entry(&mut t, 3, 2, 2, u32::from_le_bytes(*b"E\0\0\0"));
    entry(&mut t, 4, 5, 3, 174);
    t.extend(0u32.to_le_bytes());
    assert_eq!(t.len(), 150);
    for v in [lat, lon] {
        let d = v.trunc();
        let m = ((v - d) * 60.0).trunc();
        let s = ((v - d) * 60.0 - m) * 60.0;
        for (num, den) in [
            (d as u32, 1u32),
            (m as u32, 1),
            ((s * 1e6).round() as u32, 1_000_000),
        ] {
            t.extend(num.to_le_bytes());
            t.extend(den.to_le_bytes());
        }
    }
    let mut app1 = vec![0xff, 0xe1];
    app1.extend(((2 + 6 + t.len()) as u16).to_be_bytes());
    app1.extend(b"Exif\0\0");
    app1.extend(t);
    let mut out = jpeg[..2].to_vec();
    out.extend(app1);
    out.extend(&jpeg[2..]);
    out
}

#[test]
fn camera_jpegs_give_their_exif_time_and_position() {
    let server = Server::start();
    let url = format!("http://{}", server.client.addr);
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("camera");
    std::fs::create_dir_all(&frames).unwrap();
    let route = Route::new(12, 6);
    // 3 m north each second, from 48.1 N 11.5 E, at 10:00 local time (+02:00).
    let lat = |i: usize| 48.1 + 3.0 * i as f64 / M_PER_DEG;
    for i in 0..12 {
        let png = route.reference_png(i as u32);
        let img = image::load_from_memory(&png).unwrap().to_luma8();
        let when = format!("2026:05:01 10:00:{i:02}");
        std::fs::write(
            frames.join(format!("IMG_{i:04}.jpg")),
            jpeg_with_exif(&img, &when, lat(i), 11.5),
        )
        .unwrap();
    }
    let summary = ok(&seasonloc(
        &[
            "import",
            frames.to_str().unwrap(),
            "--name",
            "camera",
            "--every",
            "5m",
        ],
        &url,
    ));
    let map = summary["map_id"].as_str().unwrap();
    let stored = images(&server.client, map);
    // 0, 6, 12, ... m along: every other frame is 5 m or more beyond the last kept one.
    let kept: Vec<usize> = (0..12).step_by(2).collect();
    assert_eq!(stored.len(), kept.len(), "{summary}");
    for (img, i) in stored.iter().zip(kept) {
        assert_eq!(img["label"], format!("IMG_{i:04}.jpg"));
        assert_eq!(img["timestamp"], format!("2026-05-01T08:00:{i:02}.000Z"));
        let dlat = (img["latitude"].as_f64().unwrap() - lat(i)) * M_PER_DEG;
        assert!(dlat.abs() < 0.5, "frame {i}: {dlat} m off");
        assert!((img["longitude"].as_f64().unwrap() - 11.5).abs() < 1e-6);
    }
}
