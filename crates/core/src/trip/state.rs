//! The exact byte encoding of online solver and trip state: little-endian integers, bit-exact
//! IEEE floats ([`crate::codec`]), no serde (the core layer owns its state format; the store keeps it as opaque
//! bytes). Invariant: every read is bounds-checked, so truncated or corrupt bytes are an
//! [`Error::Format`] naming the trip state, never a panic.

use crate::codec::{ByteReader, ByteWriter, DecodeError};
use crate::{Error, Result};

/// Version byte of the state encoding written by [`StateWriter`].
pub const STATE_FORMAT: u8 = 2;

pub(super) fn corrupt(reason: impl Into<String>) -> Error {
    Error::Format {
        path: "trip state".into(),
        reason: reason.into(),
    }
}

/// Writes the exact byte encoding of solver and trip state: little-endian integers and IEEE
/// floats (bit-exact, so a restored state continues bit-identically), with the crate's one
/// byte codec. No serde: the core layer owns its state format and the store keeps it as
/// opaque bytes.
pub type StateWriter = ByteWriter;

/// Reads what [`StateWriter`] wrote; truncation, bad tags and impossible values are
/// [`Error::Format`] naming the trip state.
pub struct StateReader<'a>(ByteReader<'a>);

/// The corrupt-state error for a failed read of the byte codec.
fn decode(e: DecodeError) -> Error {
    match e {
        DecodeError::Truncated { .. } => corrupt("state is truncated"),
        DecodeError::BadTag { what, tag } => corrupt(format!("bad {what} {tag}")),
    }
}

impl<'a> StateReader<'a> {
    /// A reader over `buf`.
    pub fn new(buf: &'a [u8]) -> Self {
        StateReader(ByteReader::new(buf))
    }
    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.0.remaining()
    }
    /// Fails unless every byte was read.
    pub fn finish(self) -> Result<()> {
        match self.0.remaining() {
            0 => Ok(()),
            n => Err(corrupt(format!("{n} trailing bytes"))),
        }
    }
    /// `n` raw bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        self.0.take(n).map_err(decode)
    }
    /// A `u8`.
    pub fn u8(&mut self) -> Result<u8> {
        self.0.u8().map_err(decode)
    }
    /// A boolean (byte 0 or 1).
    pub fn bool(&mut self) -> Result<bool> {
        self.0.bool().map_err(decode)
    }
    /// A `u32`.
    pub fn u32(&mut self) -> Result<u32> {
        self.0.u32().map_err(decode)
    }
    /// A `u64`.
    pub fn u64(&mut self) -> Result<u64> {
        self.0.u64().map_err(decode)
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
        self.0.f64().map_err(decode)
    }
    /// An optional `f64`.
    pub fn opt_f64(&mut self) -> Result<Option<f64>> {
        self.0.opt_f64().map_err(decode)
    }
    /// `n` `f64`s.
    pub fn f64s(&mut self, n: usize) -> Result<Vec<f64>> {
        self.0.f64s(n).map_err(decode)
    }
    /// `n` `f32`s.
    pub fn f32s(&mut self, n: usize) -> Result<Vec<f32>> {
        self.0.f32s(n).map_err(decode)
    }
}

/// Wraps a reason as the corrupt-state error (for [`crate::trip`]).
pub(crate) fn corrupt_state(reason: impl Into<String>) -> Error {
    corrupt(reason)
}
