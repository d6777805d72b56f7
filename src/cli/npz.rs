//! Reading one array's `.npy` bytes out of a NumPy `.npz` archive (a ZIP file: `np.savez`
//! stores, `np.savez_compressed` deflates), by its central directory. Enough ZIP for NumPy's
//! archives (no ZIP64, no encryption); `flate2` inflates.

use std::io::Read;

use anyhow::{bail, Context, Result};

fn u16_at(b: &[u8], at: usize) -> Option<usize> {
    b.get(at..at + 2)
        .map(|s| usize::from(u16::from_le_bytes([s[0], s[1]])))
}

fn u32_at(b: &[u8], at: usize) -> Option<usize> {
    b.get(at..at + 4)
        .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as usize)
}

/// The names of the arrays in the archive `zip` (file names without `.npy`) and, for the one
/// called `name`, its `.npy` bytes (`None` when absent).
pub fn array(zip: &[u8], name: &str) -> Result<(Vec<String>, Option<Vec<u8>>)> {
    let bad = || anyhow::anyhow!("not a ZIP archive of .npy files (a broken or ZIP64 .npz)");
    // The end-of-central-directory record: the last signature in the final 64 KiB + 22 bytes.
    let from = zip.len().saturating_sub(22 + 65_535);
    let eocd = (from..zip.len().saturating_sub(21))
        .rev()
        .find(|&i| zip[i..i + 4] == [0x50, 0x4b, 0x05, 0x06])
        .ok_or_else(bad)?;
    let entries = u16_at(zip, eocd + 10).ok_or_else(bad)?;
    let mut at = u32_at(zip, eocd + 16).ok_or_else(bad)?;
    let (mut names, mut found) = (Vec::new(), None);
    for _ in 0..entries {
        if zip.get(at..at + 4) != Some(&[0x50, 0x4b, 0x01, 0x02][..]) {
            return Err(bad());
        }
        let method = u16_at(zip, at + 10).ok_or_else(bad)?;
        let size = u32_at(zip, at + 20).ok_or_else(bad)?;
        let (n, e, c) = (
            u16_at(zip, at + 28).ok_or_else(bad)?,
            u16_at(zip, at + 30).ok_or_else(bad)?,
            u16_at(zip, at + 32).ok_or_else(bad)?,
        );
        let local = u32_at(zip, at + 42).ok_or_else(bad)?;
        let file = String::from_utf8_lossy(zip.get(at + 46..at + 46 + n).ok_or_else(bad)?);
        let array = file.strip_suffix(".npy").unwrap_or(&file).to_string();
        if array == name {
            let ln = u16_at(zip, local + 26).ok_or_else(bad)?;
            let le = u16_at(zip, local + 28).ok_or_else(bad)?;
            let start = local + 30 + ln + le;
            let data = zip.get(start..start + size).ok_or_else(bad)?;
            found = Some(match method {
                0 => data.to_vec(),
                8 => {
                    let mut out = Vec::new();
                    flate2::read::DeflateDecoder::new(data)
                        .read_to_end(&mut out)
                        .context("inflating the array")?;
                    out
                }
                m => bail!("array `{name}` is stored with ZIP method {m} (expected 0 or 8)"),
            });
        }
        names.push(array);
        at += 46 + n + e + c;
    }
    Ok((names, found))
}
