//! One small little-endian byte codec for seasonloc's hand-written binary formats: the sled
//! engine's value encoding (`store::sled::codec`), the co-occurrence map blob
//! (`cooc::codec`) and the trip state (`trip::state`).
//!
//! Why not serde/bincode: each format is versioned and documented byte for byte (golden tests
//! pin them), floats must round-trip bit-exactly and a decoder must never panic or allocate
//! unboundedly on corrupt input. [`ByteWriter`] appends fixed-width little-endian integers and
//! IEEE floats; [`ByteReader`] reads them back with every read bounds-checked, returning a
//! [`DecodeError`] that each format wraps into its own error (naming the key, the blob or the
//! trip state). Lengths and counts are written as `u32` by [`ByteWriter::count`] (the sled
//! values' byte strings, the map blob's sections); magics, versions, tags and how a reader
//! bounds a count stay the formats' business.

use std::fmt;

/// Why a read failed; formats wrap it into their own error type and message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DecodeError {
    /// Fewer bytes remained than the read needs; `at` is the offset of the failed read.
    Truncated {
        /// Offset of the read that failed.
        at: usize,
    },
    /// A tag byte outside its range (`what` is "boolean" or "option tag").
    BadTag {
        /// What the byte encodes.
        what: &'static str,
        /// The byte read.
        tag: u8,
    },
}

impl fmt::Display for DecodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DecodeError::Truncated { at } => write!(f, "truncated at byte {at}"),
            DecodeError::BadTag { what, tag } => write!(f, "bad {what} {tag}"),
        }
    }
}

impl std::error::Error for DecodeError {}

/// Appends little-endian integers and bit-exact IEEE floats to a buffer.
#[derive(Clone, Debug, Default)]
pub struct ByteWriter(Vec<u8>);

impl ByteWriter {
    /// An empty buffer.
    pub fn new() -> Self {
        ByteWriter(Vec::new())
    }
    /// The bytes written.
    pub fn into_bytes(self) -> Vec<u8> {
        self.0
    }
    /// Raw bytes, as they are.
    pub fn raw(&mut self, v: &[u8]) {
        self.0.extend_from_slice(v);
    }
    /// A `u8`.
    pub fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    /// A boolean as one byte, 0 or 1.
    pub fn bool(&mut self, v: bool) {
        self.0.push(u8::from(v));
    }
    /// A `u16`.
    pub fn u16(&mut self, v: u16) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// A `u32`.
    pub fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// A `u64`.
    pub fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// A length or an item count as a `u32`, the width every format here gives them.
    ///
    /// Panics at `2^32` or more: callers count in-memory collections (a map's sections, a
    /// stored value's bytes) that are far below that.
    pub fn count(&mut self, n: usize) {
        self.u32(u32::try_from(n).expect("lengths and counts are below 2^32"));
    }
    /// An `f32`, bit-exact.
    pub fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// An `f64`, bit-exact.
    pub fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// An optional `f64`: tag byte 0 (none) or 1 followed by the value.
    pub fn opt_f64(&mut self, v: Option<f64>) {
        match v {
            None => self.u8(0),
            Some(x) => {
                self.u8(1);
                self.f64(x);
            }
        }
    }
    /// `f32`s without a length (the reader knows it).
    pub fn f32s(&mut self, v: &[f32]) {
        self.0.reserve(v.len() * 4);
        v.iter().for_each(|x| self.f32(*x));
    }
    /// `f64`s without a length (the reader knows it).
    pub fn f64s(&mut self, v: &[f64]) {
        self.0.reserve(v.len() * 8);
        v.iter().for_each(|x| self.f64(*x));
    }
}

/// Reads what [`ByteWriter`] wrote; every read is bounds-checked.
#[derive(Clone, Debug)]
pub struct ByteReader<'a> {
    buf: &'a [u8],
    at: usize,
}

impl<'a> ByteReader<'a> {
    /// A reader at the start of `buf`.
    pub fn new(buf: &'a [u8]) -> Self {
        ByteReader { buf, at: 0 }
    }
    /// Offset of the next read.
    pub fn position(&self) -> usize {
        self.at
    }
    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.buf.len() - self.at
    }
    /// The next `n` bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        let truncated = DecodeError::Truncated { at: self.at };
        let end = self.at.checked_add(n).ok_or(truncated)?;
        let head = self.buf.get(self.at..end).ok_or(truncated)?;
        self.at = end;
        Ok(head)
    }
    /// The next `N` bytes as an array.
    pub fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }
    /// A `u8`.
    pub fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.array::<1>()?[0])
    }
    /// A boolean (byte 0 or 1).
    pub fn bool(&mut self) -> Result<bool, DecodeError> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            tag => Err(DecodeError::BadTag {
                what: "boolean",
                tag,
            }),
        }
    }
    /// An option's tag byte: 0 is none, 1 is some.
    pub fn option_tag(&mut self) -> Result<bool, DecodeError> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            tag => Err(DecodeError::BadTag {
                what: "option tag",
                tag,
            }),
        }
    }
    /// A `u16`.
    pub fn u16(&mut self) -> Result<u16, DecodeError> {
        self.array().map(u16::from_le_bytes)
    }
    /// A `u32`.
    pub fn u32(&mut self) -> Result<u32, DecodeError> {
        self.array().map(u32::from_le_bytes)
    }
    /// A `u64`.
    pub fn u64(&mut self) -> Result<u64, DecodeError> {
        self.array().map(u64::from_le_bytes)
    }
    /// An `f32`.
    pub fn f32(&mut self) -> Result<f32, DecodeError> {
        self.array().map(f32::from_le_bytes)
    }
    /// An `f64`.
    pub fn f64(&mut self) -> Result<f64, DecodeError> {
        self.array().map(f64::from_le_bytes)
    }
    /// An optional `f64` written by [`ByteWriter::opt_f64`].
    pub fn opt_f64(&mut self) -> Result<Option<f64>, DecodeError> {
        if self.option_tag()? {
            self.f64().map(Some)
        } else {
            Ok(None)
        }
    }
    /// `n` `f32`s (fails before allocating when fewer bytes remain).
    pub fn f32s(&mut self, n: usize) -> Result<Vec<f32>, DecodeError> {
        let len = n
            .checked_mul(4)
            .ok_or(DecodeError::Truncated { at: self.at })?;
        Ok(self
            .take(len)?
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }
    /// `n` `f64`s (fails before allocating when fewer bytes remain).
    pub fn f64s(&mut self, n: usize) -> Result<Vec<f64>, DecodeError> {
        let len = n
            .checked_mul(8)
            .ok_or(DecodeError::Truncated { at: self.at })?;
        Ok(self
            .take(len)?
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_little_endian_and_reads_back_bit_exactly() {
        let mut w = ByteWriter::new();
        w.raw(b"MG");
        w.u8(7);
        w.bool(true);
        w.u16(0x0102);
        w.u32(0x0304_0506);
        w.u64(0x0708_090a_0b0c_0d0e);
        w.count(0x0a0b);
        w.f32(-0.0);
        w.f64(f64::from_bits(0x7ff8_0000_0000_0001));
        w.opt_f64(None);
        w.opt_f64(Some(1.5));
        w.f32s(&[1.0, f32::MIN_POSITIVE]);
        w.f64s(&[2.0]);
        let bytes = w.into_bytes();
        assert_eq!(
            &bytes[..17],
            &[
                b'M', b'G', 7, 1, 0x02, 0x01, 0x06, 0x05, 0x04, 0x03, 0x0e, 0x0d, 0x0c, 0x0b, 0x0a,
                0x09, 0x08
            ]
        );
        let mut r = ByteReader::new(&bytes);
        assert_eq!(r.take(2).unwrap(), b"MG");
        assert_eq!(r.u8().unwrap(), 7);
        assert!(r.bool().unwrap());
        assert_eq!(r.u16().unwrap(), 0x0102);
        assert_eq!(r.u32().unwrap(), 0x0304_0506);
        assert_eq!(r.u64().unwrap(), 0x0708_090a_0b0c_0d0e);
        assert_eq!(r.take(4).unwrap(), [0x0b, 0x0a, 0, 0]);
        assert_eq!(r.f32().unwrap().to_bits(), (-0.0f32).to_bits());
        assert_eq!(r.f64().unwrap().to_bits(), 0x7ff8_0000_0000_0001);
        assert_eq!(r.opt_f64().unwrap(), None);
        assert_eq!(r.opt_f64().unwrap(), Some(1.5));
        assert_eq!(r.f32s(2).unwrap(), vec![1.0, f32::MIN_POSITIVE]);
        assert_eq!(r.f64s(1).unwrap(), vec![2.0]);
        assert_eq!(r.remaining(), 0);
        assert_eq!(r.position(), bytes.len());
    }

    #[test]
    fn truncation_and_bad_tags_are_errors_not_panics() {
        let mut r = ByteReader::new(&[1, 2, 3]);
        assert_eq!(r.u32(), Err(DecodeError::Truncated { at: 0 }));
        assert_eq!(r.u16().unwrap(), 0x0201);
        assert_eq!(
            r.bool(),
            Err(DecodeError::BadTag {
                what: "boolean",
                tag: 3
            })
        );
        assert_eq!(r.u8(), Err(DecodeError::Truncated { at: 3 }));
        let mut r = ByteReader::new(&[2]);
        assert_eq!(
            r.opt_f64().unwrap_err().to_string(),
            "bad option tag 2".to_string()
        );
        let mut r = ByteReader::new(&[0; 8]);
        assert!(r.f64s(usize::MAX).is_err());
        assert!(r.f32s(3).is_err());
        assert_eq!(r.take(usize::MAX), Err(DecodeError::Truncated { at: 0 }));
    }
}
