//! Where a recording's frames come from, and which of them a map or a drive keeps.
//!
//! * **A folder of images** (sorted by name): frame `i` was taken at `start + i / fps`.
//! * **A video file** (whatever FFmpeg reads: MP4/H.264, MKV, ...): the `ffmpeg` program, run
//!   as a child process, samples it at `--fps` into JPEG files in a temporary folder; frame `i`
//!   is at `start + i / fps`, `start` the video's `creation_time` (from `ffprobe`) unless
//!   `--start` is given. No FFmpeg library is linked: the binary builds and runs without it,
//!   and a video given without the program is a clear error naming it.
//!
//! [`Every`] then keeps frames by distance travelled along a GPS track (`2m`), by time
//! (`0.5s`) or by frame step (`3`).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

use super::track::Track;

/// One frame of a recording.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Position in the recording (0-based, before selection).
    pub index: usize,
    /// When it was taken, milliseconds since the Unix epoch (`None`: no time known).
    pub t_ms: Option<i64>,
    /// The image file.
    pub path: PathBuf,
}

/// A recording's frames, and the temporary folder holding decoded video frames.
pub struct Recording {
    /// The frames, in order.
    pub frames: Vec<Frame>,
    _decoded: Option<tempfile::TempDir>,
}

/// Where a frame was taken: latitude and longitude in degrees, metres along the track.
pub type Place = (f64, f64, f64);

/// A chosen frame and its place (when there is a track).
pub type Chosen = (Frame, Option<Place>);

/// How frames are chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Every {
    /// Every `n`-th frame (`n` >= 1).
    Frames(usize),
    /// One frame per this many seconds.
    Seconds(f64),
    /// One frame per this many metres along the track.
    Metres(f64),
}

impl std::str::FromStr for Every {
    type Err = String;

    fn from_str(s: &str) -> Result<Every, String> {
        let s = s.trim();
        let positive = |v: &str, unit: &str| -> Result<f64, String> {
            match v.trim().parse::<f64>() {
                Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
                _ => Err(format!("`{s}`: the number before `{unit}` must be > 0")),
            }
        };
        if let Some(v) = s.strip_suffix("ms") {
            return Ok(Every::Seconds(positive(v, "ms")? / 1000.0));
        }
        if let Some(v) = s.strip_suffix('m') {
            return Ok(Every::Metres(positive(v, "m")?));
        }
        if let Some(v) = s.strip_suffix('s') {
            return Ok(Every::Seconds(positive(v, "s")?));
        }
        match s.parse::<usize>() {
            Ok(n) if n >= 1 => Ok(Every::Frames(n)),
            _ => Err(format!(
                "`{s}` is not a frame step (a whole number >= 1), a distance (`2m`) or a time \
                 (`0.5s`, `500ms`)"
            )),
        }
    }
}

/// Whether `path` is read as a video (by extension).
pub fn is_video(path: &Path) -> bool {
    path.is_file()
        && path.extension().and_then(|e| e.to_str()).is_some_and(|e| {
            ["mp4", "mkv", "mov", "avi", "webm", "m4v", "ts", "mts"]
                .iter()
                .any(|v| e.eq_ignore_ascii_case(v))
        })
}

/// Opens a folder of images or a video. `start_ms` is when frame 0 was taken (`None`: the
/// video's creation time, or no times for a folder); frames are `1/fps` s apart.
pub fn open(source: &Path, fps: f64, start_ms: Option<i64>) -> Result<Recording> {
    if !(fps.is_finite() && fps > 0.0) {
        bail!("--fps must be > 0, got {fps}");
    }
    let step_ms = 1000.0 / fps;
    let time =
        |start: Option<i64>, i: usize| start.map(|s| s + (i as f64 * step_ms).round() as i64);
    if source.is_dir() {
        let files = seasonloc_core::features::list_images(source)?;
        if files.is_empty() {
            bail!("{} holds no images (PNG or JPEG)", source.display());
        }
        let frames = files
            .into_iter()
            .enumerate()
            .map(|(i, path)| Frame {
                index: i,
                t_ms: time(start_ms, i),
                path,
            })
            .collect();
        return Ok(Recording {
            frames,
            _decoded: None,
        });
    }
    if !source.exists() {
        bail!("{} does not exist", source.display());
    }
    if !is_video(source) {
        bail!(
            "{} is neither a folder of images nor a video (.mp4, .mkv, .mov, .avi, .webm)",
            source.display()
        );
    }
    let start = match start_ms {
        Some(s) => Some(s),
        None => creation_time(source)?,
    };
    let dir = tempfile::tempdir().context("a temporary folder for the decoded frames")?;
    let out = Command::new("ffmpeg")
        .args(["-nostdin", "-v", "error", "-i"])
        .arg(source)
        .args(["-vf", &format!("fps={fps}"), "-q:v", "2"])
        .arg(dir.path().join("%09d.jpg"))
        .output();
    let out = match out {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "reading the video {} needs the `ffmpeg` program, which is not on PATH (Debian: \
             apt-get install ffmpeg); a folder of images needs nothing",
            source.display()
        ),
        Err(e) => return Err(e).context("running ffmpeg"),
    };
    if !out.status.success() {
        bail!(
            "ffmpeg cannot read {}: {}",
            source.display(),
            one_line(&out.stderr)
        );
    }
    let files = seasonloc_core::features::list_images(dir.path())?;
    if files.is_empty() {
        bail!("{}: ffmpeg decoded no frame", source.display());
    }
    // A truncated file decodes its readable part without an error; ffmpeg still reports it.
    let stderr = String::from_utf8_lossy(&out.stderr);
    if stderr.contains("Invalid data") || stderr.contains("moov atom not found") {
        bail!(
            "ffmpeg cannot read {}: {}",
            source.display(),
            one_line(stderr.as_bytes())
        );
    }
    let frames = files
        .into_iter()
        .enumerate()
        .map(|(i, path)| Frame {
            index: i,
            t_ms: time(start, i),
            path,
        })
        .collect();
    Ok(Recording {
        frames,
        _decoded: Some(dir),
    })
}

/// A program's stderr as one line.
fn one_line(stderr: &[u8]) -> String {
    String::from_utf8_lossy(stderr)
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join("; ")
}

/// The video's `creation_time` tag, if it has one (`ffprobe`; none when it is absent).
fn creation_time(video: &Path) -> Result<Option<i64>> {
    let out = match Command::new("ffprobe")
        .args([
            "-v",
            "error",
            "-show_entries",
            "format_tags=creation_time",
            "-of",
            "default=nw=1:nk=1",
        ])
        .arg(video)
        .output()
    {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => bail!(
            "reading the video {} needs the `ffprobe` program (part of FFmpeg), which is not on \
             PATH (Debian: apt-get install ffmpeg)",
            video.display()
        ),
        Err(e) => return Err(e).context("running ffprobe"),
    };
    if !out.status.success() {
        bail!(
            "ffprobe cannot read {}: {}",
            video.display(),
            one_line(&out.stderr)
        );
    }
    let text = String::from_utf8_lossy(&out.stdout);
    match text.lines().map(str::trim).find(|l| !l.is_empty()) {
        Some(t) => Ok(Some(super::track::parse_time(t)?)),
        None => Ok(None),
    }
}

/// The frames `every` keeps, each with its position on `track` when there is one (`(lat, lon,
/// metres along the track)`). Frames outside the track's time span are dropped; a recording
/// that does not overlap the track at all is an error.
pub fn select(frames: &[Frame], every: Every, track: Option<&Track>) -> Result<Vec<Chosen>> {
    let placed: Vec<Chosen> = match track {
        None => frames.iter().map(|f| (f.clone(), None)).collect(),
        Some(track) => {
            if frames.iter().any(|f| f.t_ms.is_none()) {
                bail!(
                    "a GPS track is aligned by time, and these frames have none: give --start \
                     (when frame 0 was taken) and --fps"
                );
            }
            let placed: Vec<_> = frames
                .iter()
                .filter_map(|f| Some((f.clone(), Some(track.at(f.t_ms?)?))))
                .collect();
            if placed.is_empty() {
                let (a, b) = track.span_ms();
                bail!(
                    "the recording ({} .. {}) does not overlap the track ({} .. {}) in time: \
                     check --start and --offset",
                    frames[0].t_ms.map_or("?".into(), super::track::format_time),
                    frames[frames.len() - 1]
                        .t_ms
                        .map_or("?".into(), super::track::format_time),
                    super::track::format_time(a),
                    super::track::format_time(b)
                );
            }
            placed
        }
    };
    let mut kept = Vec::new();
    let mut last: Option<(i64, f64, usize)> = None;
    for (i, (frame, at)) in placed.iter().enumerate() {
        let keep = match (every, last) {
            (_, None) => true,
            (Every::Frames(n), Some((_, _, li))) => i - li >= n,
            (Every::Seconds(s), Some((lt, _, _))) => {
                let t = frame.t_ms.ok_or_else(|| {
                    anyhow::anyhow!("--every {s}s needs frame times: give --start and --fps")
                })?;
                (t - lt) as f64 >= s * 1000.0 - 0.5
            }
            (Every::Metres(m), Some((_, ld, _))) => {
                let Some((_, _, d)) = at else {
                    bail!("--every {m}m needs a GPS track (--track)");
                };
                // To a micrometre: positions read from text round their last digit.
                d - ld >= m - 1e-6
            }
        };
        if keep {
            last = Some((frame.t_ms.unwrap_or(0), at.map_or(0.0, |a| a.2), i));
            kept.push((frame.clone(), *at));
        }
    }
    if let (Every::Metres(m), None) = (every, track) {
        bail!("--every {m}m needs a GPS track (--track)");
    }
    Ok(kept)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_parses_units_and_refuses_the_rest() {
        assert_eq!("2m".parse::<Every>().unwrap(), Every::Metres(2.0));
        assert_eq!("0.5s".parse::<Every>().unwrap(), Every::Seconds(0.5));
        assert_eq!("250ms".parse::<Every>().unwrap(), Every::Seconds(0.25));
        assert_eq!("3".parse::<Every>().unwrap(), Every::Frames(3));
        for bad in ["2km", "0m", "-1s", "x", "0"] {
            assert!(bad.parse::<Every>().is_err(), "{bad}");
        }
    }
}
