//! A camera's own record in a JPEG's EXIF block (kamadak-exif): when it was taken
//! (`DateTimeOriginal`, with `OffsetTimeOriginal` when the camera wrote it, otherwise read as
//! UTC) and where (`GPSLatitude`/`GPSLongitude` with their `Ref`s). Used for a folder of
//! images given without `--start` and `--track`.

use std::path::Path;

use exif::{In, Tag, Value};

/// What a JPEG's EXIF says about its frame: Unix milliseconds, and latitude/longitude.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Taken {
    /// `DateTimeOriginal` (and its offset), as Unix milliseconds.
    pub t_ms: Option<i64>,
    /// Degrees north and east.
    pub position: Option<(f64, f64)>,
}

fn ascii(exif: &exif::Exif, tag: Tag) -> Option<String> {
    match &exif.get_field(tag, In::PRIMARY)?.value {
        Value::Ascii(v) => v
            .first()
            .map(|b| String::from_utf8_lossy(b).trim().to_string()),
        _ => None,
    }
}

fn degrees(exif: &exif::Exif, tag: Tag, reference: Tag, negative: &str) -> Option<f64> {
    let Value::Rational(parts) = &exif.get_field(tag, In::PRIMARY)?.value else {
        return None;
    };
    if parts.len() < 3 || parts.iter().any(|r| r.denom == 0) {
        return None;
    }
    let d = parts[0].to_f64() + parts[1].to_f64() / 60.0 + parts[2].to_f64() / 3600.0;
    let sign = match ascii(exif, reference) {
        Some(r) if r.eq_ignore_ascii_case(negative) => -1.0,
        _ => 1.0,
    };
    Some(sign * d)
}

/// The EXIF record of `path` (an empty one when the file has none or is not a JPEG).
pub fn read(path: &Path) -> Taken {
    let Ok(file) = std::fs::File::open(path) else {
        return Taken::default();
    };
    let Ok(exif) = exif::Reader::new().read_from_container(&mut std::io::BufReader::new(file))
    else {
        return Taken::default();
    };
    // "2026:05:01 10:00:00" (+ "+02:00").
    let t_ms = ascii(&exif, Tag::DateTimeOriginal).and_then(|t| {
        let (date, clock) = t.split_once(' ')?;
        let offset = ascii(&exif, Tag::OffsetTimeOriginal).unwrap_or_else(|| "Z".into());
        super::track::parse_time(&format!("{}T{clock}{offset}", date.replace(':', "-"))).ok()
    });
    let position = degrees(&exif, Tag::GPSLatitude, Tag::GPSLatitudeRef, "S").zip(degrees(
        &exif,
        Tag::GPSLongitude,
        Tag::GPSLongitudeRef,
        "W",
    ));
    Taken { t_ms, position }
}
