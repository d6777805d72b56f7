//! The exact byte encoding of online solver and trip state: little-endian integers, bit-exact
//! IEEE floats, no serde (the core layer owns its state format; the store keeps it as opaque
//! bytes). Invariant: every read is bounds-checked, so truncated or corrupt bytes are an
//! [`Error::Format`] naming the trip state, never a panic.

use crate::{Error, Result};

/// Version byte of the state encoding written by [`StateWriter`].
pub const STATE_FORMAT: u8 = 1;

pub(super) fn corrupt(reason: impl Into<String>) -> Error {
    Error::Format {
        path: "trip state".into(),
        reason: reason.into(),
    }
}

/// Writes the exact byte encoding of solver and trip state: little-endian integers and IEEE
/// floats (bit-exact, so a restored state continues bit-identically). No serde: the core
/// layer owns its state format and the store keeps it as opaque bytes.
#[derive(Debug, Default)]
pub struct StateWriter(Vec<u8>);

impl StateWriter {
    /// An empty buffer.
    pub fn new() -> Self {
        StateWriter(Vec::new())
    }
    /// The bytes written.
    pub fn into_bytes(self) -> Vec<u8> {
        self.0
    }
    /// Raw bytes.
    pub fn raw(&mut self, v: &[u8]) {
        self.0.extend_from_slice(v);
    }
    /// A `u8`.
    pub fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    /// A boolean as one byte.
    pub fn bool(&mut self, v: bool) {
        self.0.push(u8::from(v));
    }
    /// A `u32`.
    pub fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// A `u64`.
    pub fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// An `f64`, bit-exact.
    pub fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// An optional `f64` (tag byte 0/1).
    pub fn opt_f64(&mut self, v: Option<f64>) {
        match v {
            None => self.u8(0),
            Some(x) => {
                self.u8(1);
                self.f64(x);
            }
        }
    }
    /// `f64`s without a length (the reader knows it).
    pub fn f64s(&mut self, v: &[f64]) {
        v.iter().for_each(|x| self.f64(*x));
    }
    /// `f32`s without a length (the reader knows it).
    pub fn f32s(&mut self, v: &[f32]) {
        v.iter()
            .for_each(|x| self.0.extend_from_slice(&x.to_le_bytes()));
    }
}

/// Reads what [`StateWriter`] wrote; truncation, bad tags and impossible values are
/// [`Error::Format`] naming the trip state.
pub struct StateReader<'a> {
    buf: &'a [u8],
}

impl<'a> StateReader<'a> {
    /// A reader over `buf`.
    pub fn new(buf: &'a [u8]) -> Self {
        StateReader { buf }
    }
    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.buf.len()
    }
    /// Fails unless every byte was read.
    pub fn finish(self) -> Result<()> {
        if self.buf.is_empty() {
            Ok(())
        } else {
            Err(corrupt(format!("{} trailing bytes", self.buf.len())))
        }
    }
    /// `n` raw bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if self.buf.len() < n {
            return Err(corrupt("state is truncated"));
        }
        let (head, tail) = self.buf.split_at(n);
        self.buf = tail;
        Ok(head)
    }
    /// A `u8`.
    pub fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    /// A boolean (byte 0 or 1).
    pub fn bool(&mut self) -> Result<bool> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            t => Err(corrupt(format!("bad boolean {t}"))),
        }
    }
    /// A `u32`.
    pub fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("took 4 bytes"),
        ))
    }
    /// A `u64`.
    pub fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("took 8 bytes"),
        ))
    }
    /// A `u64` that must fit `usize` and stay below 2^40 (no state holds more elements).
    pub fn usize(&mut self) -> Result<usize> {
        let v = self.u64()?;
        if v >= 1 << 40 {
            return Err(corrupt(format!("implausible count {v}")));
        }
        usize::try_from(v).map_err(|_| corrupt(format!("count {v} does not fit")))
    }
    /// An `f64`.
    pub fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(
            self.take(8)?.try_into().expect("took 8 bytes"),
        ))
    }
    /// An optional `f64`.
    pub fn opt_f64(&mut self) -> Result<Option<f64>> {
        match self.u8()? {
            0 => Ok(None),
            1 => self.f64().map(Some),
            t => Err(corrupt(format!("bad option tag {t}"))),
        }
    }
    /// `n` `f64`s.
    pub fn f64s(&mut self, n: usize) -> Result<Vec<f64>> {
        let bytes = self.take(n.checked_mul(8).ok_or_else(|| corrupt("length overflow"))?)?;
        Ok(bytes
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("chunks of 8")))
            .collect())
    }
    /// `n` `f32`s.
    pub fn f32s(&mut self, n: usize) -> Result<Vec<f32>> {
        let bytes = self.take(n.checked_mul(4).ok_or_else(|| corrupt("length overflow"))?)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("chunks of 4")))
            .collect())
    }
}

/// Wraps a reason as the corrupt-state error (for [`crate::trip`]).
pub(crate) fn corrupt_state(reason: impl Into<String>) -> Error {
    corrupt(reason)
}
