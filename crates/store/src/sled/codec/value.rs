//! The value format's two halves: [`Writer`] (a format byte, then fields with the crate's one
//! byte codec) and [`Reader`] (bounds-checked reads whose errors name the record's key, and a
//! `finish` that rejects trailing bytes). Every record encoding in the sibling modules goes
//! through them, so corruption is reported the same way for every record kind.

use seasonloc_app::store::StoreError;
use seasonloc_core::codec::{ByteReader, ByteWriter, DecodeError};

const FORMAT_V1: u8 = 1;

/// Appends values in the store's binary format: the format byte, then fields written with
/// the crate's one byte codec (dereferences to [`ByteWriter`] for the fixed-width fields).
pub(super) struct Writer(ByteWriter);

impl std::ops::Deref for Writer {
    type Target = ByteWriter;
    fn deref(&self) -> &ByteWriter {
        &self.0
    }
}

impl std::ops::DerefMut for Writer {
    fn deref_mut(&mut self) -> &mut ByteWriter {
        &mut self.0
    }
}

impl Writer {
    pub(super) fn new() -> Self {
        let mut w = ByteWriter::new();
        w.u8(FORMAT_V1);
        Writer(w)
    }
    pub(super) fn into_bytes(self) -> Vec<u8> {
        self.0.into_bytes()
    }
    pub(super) fn bytes(&mut self, v: &[u8]) {
        self.count(v.len());
        self.raw(v);
    }
    pub(super) fn str(&mut self, v: &str) {
        self.bytes(v.as_bytes());
    }
    pub(super) fn opt_str(&mut self, v: Option<&str>) {
        match v {
            None => self.u8(0),
            Some(s) => {
                self.u8(1);
                self.str(s);
            }
        }
    }
}

/// Reads values written by [`Writer`]; every error names the key.
pub(super) struct Reader<'a> {
    pub(super) key: &'a [u8],
    buf: ByteReader<'a>,
}

impl<'a> Reader<'a> {
    pub(super) fn new(key: &'a [u8], buf: &'a [u8]) -> Result<Self, StoreError> {
        let mut r = Reader {
            key,
            buf: ByteReader::new(buf),
        };
        let format = r.u8()?;
        if format != FORMAT_V1 {
            return Err(StoreError::corrupt(
                key,
                format!("unknown value format {format}"),
            ));
        }
        Ok(r)
    }
    /// The store error for a failed read of the byte codec.
    pub(super) fn check<T>(&self, read: Result<T, DecodeError>) -> Result<T, StoreError> {
        read.map_err(|e| match e {
            DecodeError::Truncated { .. } => StoreError::corrupt(self.key, "value is truncated"),
            DecodeError::BadTag { tag, .. } => {
                StoreError::corrupt(self.key, format!("bad option tag {tag}"))
            }
        })
    }
    pub(super) fn take(&mut self, n: usize) -> Result<&'a [u8], StoreError> {
        let read = self.buf.take(n);
        self.check(read)
    }
    pub(super) fn u8(&mut self) -> Result<u8, StoreError> {
        let read = self.buf.u8();
        self.check(read)
    }
    pub(super) fn u32(&mut self) -> Result<u32, StoreError> {
        let read = self.buf.u32();
        self.check(read)
    }
    pub(super) fn u64(&mut self) -> Result<u64, StoreError> {
        let read = self.buf.u64();
        self.check(read)
    }
    pub(super) fn f64(&mut self) -> Result<f64, StoreError> {
        let read = self.buf.f64();
        self.check(read)
    }
    pub(super) fn bytes(&mut self) -> Result<&'a [u8], StoreError> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    pub(super) fn str(&mut self) -> Result<String, StoreError> {
        let b = self.bytes()?;
        String::from_utf8(b.to_vec()).map_err(|_| StoreError::corrupt(self.key, "invalid UTF-8"))
    }
    pub(super) fn opt_str(&mut self) -> Result<Option<String>, StoreError> {
        let tag = self.buf.option_tag();
        if self.check(tag)? {
            self.str().map(Some)
        } else {
            Ok(None)
        }
    }
    pub(super) fn opt_f64(&mut self) -> Result<Option<f64>, StoreError> {
        let read = self.buf.opt_f64();
        self.check(read)
    }
    /// Bytes not read yet (a value that grew a field in a later layout ends earlier when
    /// written by an earlier one).
    pub(super) fn remaining(&self) -> usize {
        self.buf.remaining()
    }
    pub(super) fn finish(self) -> Result<(), StoreError> {
        if self.buf.remaining() == 0 {
            Ok(())
        } else {
            Err(StoreError::corrupt(self.key, "trailing bytes in value"))
        }
    }
}
