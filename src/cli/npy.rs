//! Reading similarity matrices from NumPy `.npy` files (float32 or float64, 2-D, C or Fortran
//! order) with the `npyz` crate, which owns the header parsing and endianness.

use std::path::Path;

use anyhow::{bail, Context, Result};
use npyz::{DType, NpyFile, Order, TypeChar, WriterBuilder};

use seasonloc_core::Matrix;

/// Reads a 2-D float32/float64 `.npy` file into a [`Matrix`] (values converted to `f32`).
pub fn read_matrix(path: &Path) -> Result<Matrix> {
    // A regular file is checked against its header before anything is read; a pipe
    // (`/dev/stdin`) cannot be read twice and is read as it comes (a short stream fails the
    // read, a forged shape `Matrix::from_vec`).
    let mut file = std::fs::File::open(path).with_context(|| format!("{}", path.display()))?;
    let stored = if file.metadata().is_ok_and(|m| m.is_file()) {
        let stored = data_bytes(&mut file, path)?;
        std::io::Seek::rewind(&mut file).with_context(|| format!("{}", path.display()))?;
        Some(stored)
    } else {
        None
    };
    let npy = NpyFile::new(std::io::BufReader::new(file))
        .with_context(|| format!("{}: not a valid .npy file", path.display()))?;
    let shape = npy.shape().to_vec();
    let [rows, cols] = shape[..] else {
        bail!(
            "{}: expected a 2-D array (Q, D), got shape {shape:?}",
            path.display()
        );
    };
    let (rows, cols) = (rows as usize, cols as usize);
    if rows == 0 || cols == 0 {
        bail!(
            "{}: the matrix is empty (shape {rows}x{cols})",
            path.display()
        );
    }
    let elem = match npy.dtype() {
        DType::Plain(t) if t.type_char() == TypeChar::Float && matches!(t.size_field(), 4 | 8) => {
            t.size_field()
        }
        other => bail!(
            "{}: expected float32 or float64 data, got dtype {}",
            path.display(),
            other.descr()
        ),
    };
    // The header's shape must describe exactly the bytes that follow it, checked before any
    // allocation: a truncated or padded file, or a forged shape (whose product may not even fit
    // in memory or in 64 bits), is refused with both sizes instead of read.
    let wanted = (rows as u64)
        .checked_mul(cols as u64)
        .and_then(|n| n.checked_mul(elem));
    if let Some(stored) = stored.filter(|&stored| wanted != Some(stored)) {
        let wanted = wanted.map_or_else(|| "more than 2^64".to_string(), |n| n.to_string());
        bail!(
            "{}: the header's shape ({rows}, {cols}) of {elem}-byte values needs {wanted} bytes \
             of data, the file has {stored}",
            path.display()
        );
    }
    let order = npy.order();
    // `elem` is 4 or 8: the dtype was checked above.
    let data: Vec<f32> = if elem == 4 {
        npy.into_vec::<f32>()
            .with_context(|| format!("{}: reading float32 data", path.display()))?
    } else {
        npy.into_vec::<f64>()
            .with_context(|| format!("{}: reading float64 data", path.display()))?
            .into_iter()
            .map(|v| v as f32)
            .collect()
    };
    let data = match order {
        Order::C => data,
        Order::Fortran => {
            let mut c = vec![0.0; data.len()];
            for j in 0..cols {
                for i in 0..rows {
                    c[i * cols + j] = data[j * rows + i];
                }
            }
            c
        }
    };
    Ok(Matrix::from_vec(rows, cols, data)?)
}

/// Bytes after the `.npy` header: the file's length minus the preamble (magic, version, header
/// length: a `u16` in version 1, a `u32` in versions 2 and 3) and the header. Also refuses a
/// header whose shape has more than 2^64 values before `npyz` parses it (its product of the
/// shape overflows). Anything else wrong with the header is left to `npyz` to report. Reads
/// from the file's current position (its start); `path` names it in errors.
fn data_bytes(file: &mut std::fs::File, path: &Path) -> Result<u64> {
    use std::io::Read;
    let len = file
        .metadata()
        .with_context(|| format!("{}", path.display()))?
        .len();
    let mut pre = [0u8; 12];
    if file.read_exact(&mut pre).is_err() {
        return Ok(0); // too short for any header: `npyz` says what is missing
    }
    let (start, header_len) = match pre[6] {
        1 => (10, u64::from(u16::from_le_bytes([pre[8], pre[9]]))),
        _ => (
            12,
            u64::from(u32::from_le_bytes([pre[8], pre[9], pre[10], pre[11]])),
        ),
    };
    let mut header = Vec::new();
    std::io::Read::by_ref(file)
        .take(header_len.saturating_sub(12 - start))
        .read_to_end(&mut header)
        .with_context(|| format!("{}", path.display()))?;
    let header = String::from_utf8_lossy(&header);
    let dims: Option<Vec<u64>> = header
        .split_once("shape")
        .and_then(|(_, rest)| rest.split_once('('))
        .and_then(|(_, rest)| rest.split_once(')'))
        .and_then(|(tuple, _)| {
            let dims = tuple.split(',').map(str::trim).filter(|t| !t.is_empty());
            dims.map(|t| t.parse().ok()).collect()
        });
    if let Some(dims) = dims {
        if dims
            .iter()
            .try_fold(1u64, |a, &b| a.checked_mul(b))
            .is_none()
        {
            bail!(
                "{}: the header's shape {dims:?} has more than 2^64 values",
                path.display()
            );
        }
    }
    Ok(len.saturating_sub(start + header_len))
}

/// Writes `m` as a 2-D little-endian float32 `.npy` file (C order).
pub fn write_matrix(path: &Path, m: &Matrix) -> Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("{}", path.display()))?;
    let mut writer = npyz::WriteOptions::<f32>::new()
        .default_dtype()
        .shape(&[m.rows() as u64, m.cols() as u64])
        .writer(std::io::BufWriter::new(file))
        .begin_nd()
        .with_context(|| format!("{}: writing the .npy header", path.display()))?;
    writer
        .extend(m.as_slice().iter().copied())
        .with_context(|| format!("{}: writing data", path.display()))?;
    writer
        .finish()
        .with_context(|| format!("{}: finishing the file", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn write_npy(path: &Path, descr: &str, fortran: bool, shape: &[usize], body: &[u8]) {
        let shape_s = match shape {
            [n] => format!("({n},)"),
            _ => format!(
                "({})",
                shape
                    .iter()
                    .map(|s| s.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        let mut header = format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape_s}, }}",
            if fortran { "True" } else { "False" }
        );
        while (10 + header.len() + 1) % 64 != 0 {
            header.push(' ');
        }
        header.push('\n');
        let mut f = std::fs::File::create(path).unwrap();
        f.write_all(b"\x93NUMPY\x01\x00").unwrap();
        f.write_all(&(header.len() as u16).to_le_bytes()).unwrap();
        f.write_all(header.as_bytes()).unwrap();
        f.write_all(body).unwrap();
    }

    #[test]
    fn reads_f32_f64_and_fortran_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.npy");
        let vals = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0];
        let body: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        write_npy(&p, "<f4", false, &[2, 3], &body);
        let m = read_matrix(&p).unwrap();
        assert_eq!((m.rows(), m.cols()), (2, 3));
        assert_eq!(m.row(1), &[4.0, 5.0, 6.0]);

        let body: Vec<u8> = vals
            .iter()
            .flat_map(|v| f64::from(*v).to_le_bytes())
            .collect();
        write_npy(&p, "<f8", true, &[2, 3], &body);
        let m = read_matrix(&p).unwrap();
        // Fortran order: column-major data 1..6 -> rows [1,3,5], [2,4,6].
        assert_eq!(m.row(0), &[1.0, 3.0, 5.0]);
    }

    #[test]
    fn written_matrices_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("w.npy");
        let m = Matrix::from_vec(2, 3, vec![0.5, -1.0, 2.0, 3.0, 4.5, 0.0]).unwrap();
        write_matrix(&p, &m).unwrap();
        assert_eq!(read_matrix(&p).unwrap(), m);
    }

    #[test]
    fn rejects_wrong_rank_dtype_and_garbage() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.npy");
        write_npy(&p, "<f4", false, &[3], &[0u8; 12]);
        assert!(format!("{:#}", read_matrix(&p).unwrap_err()).contains("2-D"));
        write_npy(&p, "<i4", false, &[1, 1], &[0u8; 4]);
        assert!(format!("{:#}", read_matrix(&p).unwrap_err()).contains("float32 or float64"));
        std::fs::write(&p, b"not numpy").unwrap();
        assert!(format!("{:#}", read_matrix(&p).unwrap_err()).contains("not a valid .npy"));
        // The shape must describe exactly the bytes that follow the header.
        for (shape, body, needle) in [
            (
                &[3usize, 3][..],
                &[0u8; 8][..],
                "needs 36 bytes of data, the file has 8",
            ),
            (
                &[2, 2],
                &[0u8; 20],
                "needs 16 bytes of data, the file has 20",
            ),
            // Forged: far more than the file holds, and a product past 2^64.
            (&[100_000_000, 100_000_000], &[0u8; 16], "the file has 16"),
            (&[1 << 61, 4], &[0u8; 16], "needs more than 2^64 bytes"),
            (&[1 << 62, 8], &[0u8; 16], "has more than 2^64 values"),
        ] {
            write_npy(&p, "<f4", false, shape, body);
            let err = format!("{:#}", read_matrix(&p).unwrap_err());
            assert!(err.contains(needle), "{shape:?}: {err}");
        }
        let missing = dir.path().join("missing.npy");
        assert!(format!("{:#}", read_matrix(&missing).unwrap_err()).contains("missing.npy"));
    }
}
