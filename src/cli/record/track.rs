//! GPS tracks: GPX (`<trkpt lat lon><time>`), NMEA 0183 (`$GPRMC` / `$GPGGA`, checksums
//! checked, bad sentences skipped and counted) and CSV (`timestamp,latitude,longitude[,heading]`),
//! read into one time-ordered list of fixes; positions and distances along it by time.
//!
//! Times are milliseconds since the Unix epoch (UTC). Distances are haversine on a sphere of
//! the mean Earth radius (6,371,008.8 m), summed fix to fix: at 2 m spacing the error against
//! the WGS-84 ellipsoid is far below a GPS fix's own.

use std::path::Path;

use anyhow::{bail, Context, Result};

/// Mean Earth radius in metres (IUGG).
pub const EARTH_RADIUS_M: f64 = 6_371_008.8;

/// One GPS fix.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fix {
    /// Milliseconds since the Unix epoch.
    pub t_ms: i64,
    /// Degrees north.
    pub lat: f64,
    /// Degrees east.
    pub lon: f64,
}

/// A time-ordered track with the distance travelled at each fix.
#[derive(Clone, Debug)]
pub struct Track {
    fixes: Vec<Fix>,
    /// Metres from the first fix, along the track.
    along: Vec<f64>,
    /// Sentences or rows skipped (bad NMEA checksums, NMEA without a fix).
    pub skipped: usize,
}

/// Great-circle distance in metres between two positions in degrees.
pub fn haversine_m(lat1: f64, lon1: f64, lat2: f64, lon2: f64) -> f64 {
    let (p1, p2) = (lat1.to_radians(), lat2.to_radians());
    let dp = p2 - p1;
    let dl = (lon2 - lon1).to_radians();
    let a = (dp / 2.0).sin().powi(2) + p1.cos() * p2.cos() * (dl / 2.0).sin().powi(2);
    2.0 * EARTH_RADIUS_M * a.sqrt().min(1.0).asin()
}

impl Track {
    /// A track from fixes (sorted by time here; fixes at the same time keep the first).
    pub fn new(mut fixes: Vec<Fix>, skipped: usize) -> Result<Track> {
        for f in &fixes {
            if !(f.lat.is_finite() && f.lon.is_finite())
                || f.lat.abs() > 90.0
                || f.lon.abs() > 180.0
            {
                bail!(
                    "a fix at {} ms has no valid position ({}, {})",
                    f.t_ms,
                    f.lat,
                    f.lon
                );
            }
        }
        fixes.sort_by_key(|f| f.t_ms);
        fixes.dedup_by_key(|f| f.t_ms);
        if fixes.is_empty() {
            bail!("the track has no points");
        }
        let mut along = Vec::with_capacity(fixes.len());
        let mut d = 0.0;
        for (i, f) in fixes.iter().enumerate() {
            if i > 0 {
                let p = fixes[i - 1];
                d += haversine_m(p.lat, p.lon, f.lat, f.lon);
            }
            along.push(d);
        }
        Ok(Track {
            fixes,
            along,
            skipped,
        })
    }

    /// Reads a track file; the format comes from the extension (`.gpx`, `.nmea` / `.nmea0183`
    /// / `.log`, `.csv`).
    pub fn read(path: &Path) -> Result<Track> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the track {}", path.display()))?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        let parsed = match ext.as_str() {
            "gpx" => parse_gpx(&text),
            "nmea" | "nmea0183" | "log" | "txt" => parse_nmea(&text),
            "csv" => parse_csv(&text),
            other => bail!(
                "the track {} has extension `{other}`: expected .gpx, .nmea or .csv",
                path.display()
            ),
        };
        parsed.with_context(|| format!("the track {}", path.display()))
    }

    /// First and last fix times.
    pub fn span_ms(&self) -> (i64, i64) {
        (self.fixes[0].t_ms, self.fixes[self.fixes.len() - 1].t_ms)
    }

    /// The fixes.
    #[cfg(test)]
    pub fn fixes(&self) -> &[Fix] {
        &self.fixes
    }

    /// Position and distance along the track at time `t_ms`, linearly interpolated between
    /// the fixes around it; `None` outside the track's time span.
    pub fn at(&self, t_ms: i64) -> Option<(f64, f64, f64)> {
        let (first, last) = self.span_ms();
        if t_ms < first || t_ms > last {
            return None;
        }
        let i = self.fixes.partition_point(|f| f.t_ms <= t_ms);
        // fixes[i - 1].t_ms <= t_ms < fixes[i].t_ms (or i == len at the last fix).
        let a = i - 1;
        if a + 1 >= self.fixes.len() {
            let f = self.fixes[a];
            return Some((f.lat, f.lon, self.along[a]));
        }
        let (fa, fb) = (self.fixes[a], self.fixes[a + 1]);
        let w = (t_ms - fa.t_ms) as f64 / (fb.t_ms - fa.t_ms) as f64;
        Some((
            fa.lat + w * (fb.lat - fa.lat),
            fa.lon + w * (fb.lon - fa.lon),
            self.along[a] + w * (self.along[a + 1] - self.along[a]),
        ))
    }
}

// ---- time ----------------------------------------------------------------------------------

/// Days from 1970-01-01 to a proleptic Gregorian date (Howard Hinnant's `days_from_civil`).
fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// Milliseconds since the epoch of a UTC date and time of day.
fn epoch_ms(y: i64, mo: i64, d: i64, h: i64, mi: i64, s: f64) -> Result<i64> {
    if !(1..=12).contains(&mo)
        || !(1..=31).contains(&d)
        || h > 23
        || mi > 59
        || !(0.0..61.0).contains(&s)
    {
        bail!("not a valid date and time: {y:04}-{mo:02}-{d:02} {h:02}:{mi:02}:{s}");
    }
    let days = days_from_civil(y, mo, d);
    Ok(((days * 86_400 + h * 3_600 + mi * 60) as f64 * 1000.0 + s * 1000.0).round() as i64)
}

/// An RFC 3339 / ISO 8601 time (`2026-05-01T10:20:30.5Z`, `... +02:00`, or without a zone,
/// read as UTC), an integer of Unix milliseconds (13 digits or more) or seconds, as Unix
/// milliseconds.
pub fn parse_time(text: &str) -> Result<i64> {
    let t = text.trim();
    if let Ok(n) = t.parse::<i64>() {
        return Ok(if n.abs() >= 100_000_000_000 {
            n
        } else {
            n * 1000
        });
    }
    if let Ok(x) = t.parse::<f64>() {
        if x.is_finite() {
            return Ok((x * 1000.0).round() as i64);
        }
    }
    let bad = || anyhow::anyhow!("`{t}` is not a time (RFC 3339, or Unix seconds or milliseconds)");
    let (date, rest) = t.split_once(['T', 't', ' ']).ok_or_else(bad)?;
    let mut dp = date.split('-');
    let (Some(y), Some(mo), Some(d), None) = (dp.next(), dp.next(), dp.next(), dp.next()) else {
        return Err(bad());
    };
    let (clock, offset_min) = if let Some(c) = rest.strip_suffix(['Z', 'z']) {
        (c, 0)
    } else if let Some(i) = rest.rfind(['+', '-']).filter(|&i| i >= 5) {
        let (c, z) = rest.split_at(i);
        let sign = if z.starts_with('-') { -1 } else { 1 };
        let z = &z[1..];
        let (zh, zm) = z
            .split_once(':')
            .unwrap_or((z.get(..2).unwrap_or(z), z.get(2..).unwrap_or("0")));
        let zh: i64 = zh.parse().map_err(|_| bad())?;
        let zm: i64 = if zm.is_empty() {
            0
        } else {
            zm.parse().map_err(|_| bad())?
        };
        (c, sign * (zh * 60 + zm))
    } else {
        (rest, 0)
    };
    let mut cp = clock.split(':');
    let (Some(h), Some(mi), Some(s)) = (cp.next(), cp.next(), cp.next()) else {
        return Err(bad());
    };
    let num = |v: &str| v.parse::<i64>().map_err(|_| bad());
    let ms = epoch_ms(
        num(y)?,
        num(mo)?,
        num(d)?,
        num(h)?,
        num(mi)?,
        s.parse::<f64>().map_err(|_| bad())?,
    )?;
    Ok(ms - offset_min * 60_000)
}

/// Unix milliseconds as RFC 3339 UTC with milliseconds (`2026-05-01T10:20:30.500Z`).
pub fn format_time(ms: i64) -> String {
    seasonloc_core::time::format_unix_ms(ms)
}

// ---- formats -------------------------------------------------------------------------------

/// The value of attribute `name` in an XML start tag's text.
fn attr(tag: &str, name: &str) -> Option<String> {
    for quote in ['"', '\''] {
        let key = format!("{name}={quote}");
        if let Some(i) = tag.find(&key) {
            let rest = &tag[i + key.len()..];
            return rest.split(quote).next().map(str::to_string);
        }
    }
    None
}

/// GPX 1.0/1.1: every `<trkpt>` (and `<rtept>`/`<wpt>` when there is no `<trkpt>`) with a
/// `<time>`.
pub fn parse_gpx(text: &str) -> Result<Track> {
    let mut fixes = Vec::new();
    for tag_name in ["trkpt", "rtept", "wpt"] {
        let open = format!("<{tag_name}");
        let close = format!("</{tag_name}>");
        let mut rest = text;
        while let Some(i) = rest.find(&open) {
            let after = &rest[i..];
            let end = after
                .find('>')
                .ok_or_else(|| anyhow::anyhow!("an unterminated <{tag_name}> tag"))?;
            let tag = &after[..end];
            let body_end = after.find(&close).unwrap_or(end);
            let body = &after[end..body_end.max(end)];
            let lat = attr(tag, "lat").and_then(|v| v.trim().parse::<f64>().ok());
            let lon = attr(tag, "lon").and_then(|v| v.trim().parse::<f64>().ok());
            let time = body
                .split_once("<time>")
                .and_then(|(_, t)| t.split_once("</time>"))
                .map(|(t, _)| t.trim().to_string());
            match (lat, lon, time) {
                (Some(lat), Some(lon), Some(time)) => fixes.push(Fix {
                    t_ms: parse_time(&time)?,
                    lat,
                    lon,
                }),
                (Some(_), Some(_), None) => {
                    bail!("a <{tag_name}> has no <time>: a track must say when each point was")
                }
                _ => bail!("a <{tag_name}> without numeric lat and lon attributes"),
            }
            rest = &after[end..];
        }
        if !fixes.is_empty() {
            break;
        }
    }
    if fixes.is_empty() {
        bail!("the GPX file has no points (no <trkpt>, <rtept> or <wpt>)");
    }
    Track::new(fixes, 0)
}

/// The NMEA checksum of a sentence's body (between `$` and `*`).
fn nmea_checksum_ok(line: &str) -> bool {
    let Some(body) = line.strip_prefix('$') else {
        return false;
    };
    let Some((data, sum)) = body.split_once('*') else {
        return false;
    };
    let Ok(sum) = u8::from_str_radix(sum.trim(), 16) else {
        return false;
    };
    data.bytes().fold(0u8, |a, b| a ^ b) == sum
}

/// `ddmm.mmmm` with its hemisphere, in degrees.
fn nmea_degrees(v: &str, hemi: &str, deg_digits: usize) -> Option<f64> {
    if v.len() < deg_digits + 2 {
        return None;
    }
    let d: f64 = v[..deg_digits].parse().ok()?;
    let m: f64 = v[deg_digits..].parse().ok()?;
    let x = d + m / 60.0;
    match hemi {
        "N" | "E" => Some(x),
        "S" | "W" => Some(-x),
        _ => None,
    }
}

/// NMEA 0183: `$..RMC` gives date, time and position; `$..GGA` (time and position, no date)
/// takes the date of the last RMC. Sentences with a bad checksum, no fix or before any date are
/// skipped and counted ([`Track::skipped`]).
pub fn parse_nmea(text: &str) -> Result<Track> {
    let mut fixes = Vec::new();
    let mut skipped = 0;
    let mut date: Option<(i64, i64, i64)> = None;
    for line in text.lines().map(str::trim).filter(|l| l.starts_with('$')) {
        if !nmea_checksum_ok(line) {
            skipped += 1;
            continue;
        }
        let data = line[1..].split('*').next().unwrap_or("");
        let f: Vec<&str> = data.split(',').collect();
        let kind = f[0].get(2..).unwrap_or("");
        let clock = |s: &str| -> Option<(i64, i64, f64)> {
            Some((
                s.get(..2)?.parse().ok()?,
                s.get(2..4)?.parse().ok()?,
                s.get(4..)?.parse().ok()?,
            ))
        };
        let fix = match kind {
            "RMC" if f.len() >= 10 => {
                let d = f[9];
                if let (Some(dd), Some(mm), Some(yy)) = (d.get(..2), d.get(2..4), d.get(4..6)) {
                    if let (Ok(dd), Ok(mm), Ok(yy)) = (dd.parse(), mm.parse(), yy.parse::<i64>()) {
                        date = Some((2000 + yy, mm, dd));
                    }
                }
                if f[2] != "A" {
                    None
                } else {
                    Some((
                        f[1],
                        nmea_degrees(f[3], f[4], 2),
                        nmea_degrees(f[5], f[6], 3),
                    ))
                }
            }
            "GGA" if f.len() >= 7 => {
                if f[6] == "0" {
                    None
                } else {
                    Some((
                        f[1],
                        nmea_degrees(f[2], f[3], 2),
                        nmea_degrees(f[4], f[5], 3),
                    ))
                }
            }
            _ => continue,
        };
        let Some((time, Some(lat), Some(lon))) = fix else {
            skipped += 1;
            continue;
        };
        let (Some((y, mo, d)), Some((h, mi, s))) = (date, clock(time)) else {
            skipped += 1;
            continue;
        };
        fixes.push(Fix {
            t_ms: epoch_ms(y, mo, d, h, mi, s)?,
            lat,
            lon,
        });
    }
    if fixes.is_empty() {
        bail!("the NMEA log has no fix with a date ({skipped} sentences skipped)");
    }
    Track::new(fixes, skipped)
}

/// CSV with a header naming `timestamp`, `latitude`, `longitude` (and optionally `heading`)
/// in any order; `timestamp` as for [`parse_time`].
pub fn parse_csv(text: &str) -> Result<Track> {
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let header: Vec<String> = lines
        .next()
        .ok_or_else(|| anyhow::anyhow!("the CSV track is empty"))?
        .split(',')
        .map(|h| h.trim().to_ascii_lowercase())
        .collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| h == name)
            .ok_or_else(|| anyhow::anyhow!("the CSV track has no `{name}` column (header: timestamp,latitude,longitude[,heading])"))
    };
    let (ct, clat, clon) = (col("timestamp")?, col("latitude")?, col("longitude")?);
    let mut fixes = Vec::new();
    for (n, line) in lines.enumerate() {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let get = |i: usize| {
            f.get(i)
                .copied()
                .ok_or_else(|| anyhow::anyhow!("row {} has too few fields", n + 2))
        };
        let num = |i: usize| -> Result<f64> {
            get(i)?
                .parse()
                .map_err(|_| anyhow::anyhow!("row {}: `{}` is not a number", n + 2, f[i]))
        };
        fixes.push(Fix {
            t_ms: parse_time(get(ct)?).with_context(|| format!("row {}", n + 2))?,
            lat: num(clat)?,
            lon: num(clon)?,
        });
    }
    if fixes.is_empty() {
        bail!("the CSV track has no rows");
    }
    Track::new(fixes, 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_parse_in_every_form_and_round_trip() {
        let t = parse_time("2026-05-01T10:20:30.5Z").unwrap();
        assert_eq!(format_time(t), "2026-05-01T10:20:30.500Z");
        assert_eq!(parse_time("2026-05-01T12:20:30.5+02:00").unwrap(), t);
        assert_eq!(parse_time("1777630830500").unwrap(), t);
        assert_eq!(parse_time("1777630830.5").unwrap(), t);
        assert_eq!(parse_time("1970-01-01T00:00:00Z").unwrap(), 0);
        assert!(parse_time("yesterday").is_err());
        assert!(parse_time("2026-13-01T00:00:00Z").is_err());
    }

    #[test]
    fn haversine_matches_a_hand_computation() {
        // One degree of latitude: pi * R / 180.
        let d = haversine_m(0.0, 0.0, 1.0, 0.0);
        assert!((d - std::f64::consts::PI * EARTH_RADIUS_M / 180.0).abs() < 1e-6);
    }

    #[test]
    fn nmea_checksums_are_checked_and_bad_sentences_counted() {
        let good = "$GPRMC,102030.00,A,5230.0000,N,01320.0000,E,0.0,0.0,010526,,,A*";
        let sum = good[1..good.len() - 1].bytes().fold(0u8, |a, b| a ^ b);
        let good = format!("{good}{sum:02X}");
        let text =
            format!("{good}\n$GPRMC,102031.00,A,5230.0000,N,01320.0000,E,0.0,0.0,010526,,,A*00\n");
        let track = parse_nmea(&text).unwrap();
        assert_eq!(track.fixes().len(), 1);
        assert_eq!(track.skipped, 1);
        let f = track.fixes()[0];
        assert!((f.lat - 52.5).abs() < 1e-9 && (f.lon - 13.333_333_333).abs() < 1e-6);
        assert_eq!(format_time(f.t_ms), "2026-05-01T10:20:30.000Z");
        assert!(parse_nmea("$GPRMC,bad*00\n").is_err());
    }

    #[test]
    fn positions_are_interpolated_by_time() {
        let gpx = r#"<gpx><trk><trkseg>
            <trkpt lat="0" lon="0"><time>2026-05-01T00:00:00Z</time></trkpt>
            <trkpt lat="0.001" lon="0"><time>2026-05-01T00:00:10Z</time></trkpt>
            </trkseg></trk></gpx>"#;
        let t = parse_gpx(gpx).unwrap();
        let t0 = parse_time("2026-05-01T00:00:00Z").unwrap();
        let (lat, lon, d) = t.at(t0 + 2_500).unwrap();
        assert!((lat - 0.00025).abs() < 1e-12 && lon == 0.0);
        assert!((d - haversine_m(0.0, 0.0, 0.001, 0.0) / 4.0).abs() < 1e-6);
        assert!(t.at(t0 - 1).is_none() && t.at(t0 + 10_001).is_none());
        assert!(parse_gpx("<gpx></gpx>").is_err());
        let csv = parse_csv("timestamp,latitude,longitude\n1777630830000,1.5,2.5\n").unwrap();
        assert_eq!(csv.fixes()[0].lat, 1.5);
        assert!(parse_csv("time,lat\n").is_err());
    }
}
