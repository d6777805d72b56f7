//! `eval --ground-truth` in the field's forms, read from their files and handed to the core's
//! one `GroundTruth` (`seasonloc_core::eval`, whose `forms` module says what each means): the
//! CSV, VPR-Bench's `ground_truth_new.npy` (a pickled object array), VPR_Tutorial's `GThard` /
//! `GTsoft` bool matrices (`.npy`, or `.npz` holding them).

use std::path::Path;

use anyhow::{bail, Context, Result};
use npyz::{DType, NpyFile, Order, TypeChar};

use seasonloc_core::eval::GroundTruth;

/// The form of a ground-truth file, by its extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Form {
    /// seasonloc's CSV (`query_index`, `ref_index`).
    Csv,
    /// A `.npy`: VPR-Bench's object rows or a references x queries matrix.
    Npy,
    /// A `.npz` holding `GThard` (or `GTsoft`).
    Npz,
}

impl Form {
    /// The form of `path`: `.npy`, `.npz`, otherwise the CSV.
    pub fn of(path: &Path) -> Form {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("npy") => Form::Npy,
            Some("npz") => Form::Npz,
            _ => Form::Csv,
        }
    }
}

/// Reads the ground truth at `path` in its form (`soft`: an `.npz`'s `GTsoft` instead of
/// `GThard`). Errors name the file.
pub fn load(path: &Path, soft: bool) -> Result<GroundTruth> {
    let form = Form::of(path);
    if form == Form::Csv {
        return Ok(GroundTruth::from_csv(path)?);
    }
    let bytes = std::fs::read(path).with_context(|| format!("{}", path.display()))?;
    let gt = if form == Form::Npz {
        let key = if soft { "GTsoft" } else { "GThard" };
        let (names, array) = super::npz::array(&bytes, key)?;
        let Some(array) = array else {
            bail!("no `{key}` array (found: {})", names.join(", "));
        };
        from_npy(&array)
    } else {
        from_npy(&bytes)
    };
    gt.with_context(|| format!("{}", path.display()))
}

/// A `.npy` file's bytes as a ground truth: a pickled object array (VPR-Bench's rows) or a 2-D
/// bool (or 0/1 integer) references x queries matrix (VPR_Tutorial's).
fn from_npy(bytes: &[u8]) -> Result<GroundTruth> {
    let (header, data) = split_header(bytes)?;
    if header.contains("'|O'") || header.contains("\"|O\"") {
        let rows = super::pickle::object_rows(data)
            .context("reading VPR-Bench's rows [query index, [reference indices]]")?;
        return Ok(GroundTruth::from_query_lists(&rows)?);
    }
    let npy = NpyFile::new(bytes).context("not a valid .npy file")?;
    let shape = npy.shape().to_vec();
    let [refs, queries] = shape[..] else {
        bail!("expected a references x queries matrix, got shape {shape:?}");
    };
    let (refs, queries) = (refs as usize, queries as usize);
    let order = npy.order();
    let values: Vec<bool> = match npy.dtype() {
        DType::Plain(t) if t.type_char() == TypeChar::Bool => npy.into_vec::<bool>()?,
        DType::Plain(t) if t.type_char() == TypeChar::Uint && t.size_field() == 1 => {
            zero_one(npy.into_vec::<u8>()?.into_iter().map(i64::from))?
        }
        DType::Plain(t) if t.type_char() == TypeChar::Int && t.size_field() == 8 => {
            zero_one(npy.into_vec::<i64>()?)?
        }
        other => bail!(
            "expected a bool references x queries matrix or VPR-Bench's object rows, got dtype {}",
            other.descr()
        ),
    };
    let values = match order {
        Order::C => values,
        Order::Fortran => {
            let mut c = vec![false; values.len()];
            for j in 0..queries {
                for i in 0..refs {
                    c[i * queries + j] = values[j * refs + i];
                }
            }
            c
        }
    };
    Ok(GroundTruth::from_match_matrix(refs, queries, &values)?)
}

fn zero_one(values: impl IntoIterator<Item = i64>) -> Result<Vec<bool>> {
    values
        .into_iter()
        .map(|v| match v {
            0 => Ok(false),
            1 => Ok(true),
            v => bail!("a ground-truth matrix holds 0 and 1 only, found {v}"),
        })
        .collect()
}

/// The header text of a `.npy` and the bytes after it.
fn split_header(bytes: &[u8]) -> Result<(String, &[u8])> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        bail!("not a valid .npy file");
    }
    let (start, len) = match bytes[6] {
        1 => (10, usize::from(u16::from_le_bytes([bytes[8], bytes[9]]))),
        _ if bytes.len() >= 12 => (
            12,
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
        ),
        _ => bail!("not a valid .npy file"),
    };
    let header = bytes
        .get(start..start + len)
        .context("the .npy header is cut short")?;
    Ok((
        String::from_utf8_lossy(header).into_owned(),
        &bytes[start + len..],
    ))
}
