//! Reading the pickle inside a NumPy object-array `.npy` (what `np.save` writes for an array of
//! Python objects, e.g. VPR-Bench's `ground_truth_new.npy`): a small pickle machine for the
//! opcodes `pickle` protocols 2-5 use for numbers, strings, bytes, lists, tuples, dicts and
//! NumPy's own reconstructors, executing no code. Globals (`numpy...._reconstruct`,
//! `numpy.dtype`, `numpy...scalar`) are kept as names and their calls as [`Value::Call`]; the
//! NumPy meaning of those is decoded by [`object_rows`] only.
//!
//! Why our own: the one pickle crate would need the same NumPy decoding on top, and a reader
//! that never imports or calls anything is what an untrusted file needs.

use anyhow::{bail, Context, Result};

/// A value on the pickle machine's stack. Lists and dicts are nodes of the arena, so that an
/// `APPEND` after a `MEMOIZE` changes the memoised object too (as Python's pickle does).
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// A boolean.
    Bool(bool),
    /// An integer (Python's are unbounded; beyond 64 bits is an error).
    Int(i64),
    /// A float.
    Float(f64),
    /// A str.
    Str(String),
    /// bytes.
    Bytes(Vec<u8>),
    /// A list or tuple: arena node indices.
    List(Vec<usize>),
    /// A dict: arena node index pairs.
    Dict(Vec<(usize, usize)>),
    /// A global `module.name`, never resolved.
    Global(String, String),
    /// `callable(*args)` (REDUCE, NEWOBJ) with its BUILD state, if any.
    Call {
        /// The global called.
        callable: usize,
        /// Its arguments (a tuple node).
        args: usize,
        /// The state BUILD gave it.
        state: Option<usize>,
    },
}

/// The decoded pickle: every value and the index of the one the stream returns.
pub struct Pickle {
    nodes: Vec<Value>,
    root: usize,
}

impl Pickle {
    /// The value of node `i`.
    pub fn node(&self, i: usize) -> &Value {
        &self.nodes[i]
    }

    /// The value the stream returns.
    pub fn root(&self) -> usize {
        self.root
    }
}

struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len());
        let end = end.context("the pickle ends in the middle of a value")?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    fn le(&mut self, n: usize) -> Result<u64> {
        let b = self.take(n)?;
        Ok(b.iter().rev().fold(0u64, |a, &x| (a << 8) | u64::from(x)))
    }
    fn line(&mut self) -> Result<String> {
        let rest = &self.data[self.pos..];
        let n = rest
            .iter()
            .position(|&c| c == b'\n')
            .context("the pickle ends in the middle of a line")?;
        let s = String::from_utf8_lossy(&rest[..n]).into_owned();
        self.pos += n + 1;
        Ok(s)
    }
}

/// Runs the pickle in `data` (without executing anything) and returns its values.
pub fn read(data: &[u8]) -> Result<Pickle> {
    let mut nodes: Vec<Value> = Vec::new();
    let mut stack: Vec<usize> = Vec::new();
    let mut marks: Vec<usize> = Vec::new();
    let mut memo: std::collections::HashMap<u64, usize> = std::collections::HashMap::new();
    let mut r = Reader { data, pos: 0 };
    let push = |nodes: &mut Vec<Value>, stack: &mut Vec<usize>, v: Value| {
        nodes.push(v);
        stack.push(nodes.len() - 1);
    };
    loop {
        let op = r.u8()?;
        macro_rules! pop {
            () => {
                stack.pop().context("the pickle pops an empty stack")?
            };
        }
        macro_rules! since_mark {
            () => {{
                let m = marks.pop().context("the pickle has no mark to pop to")?;
                if m > stack.len() {
                    bail!("the pickle's mark is above its stack");
                }
                stack.split_off(m)
            }};
        }
        match op {
            0x80 => {
                r.u8()?; // PROTO
            }
            0x95 => {
                r.take(8)?; // FRAME
            }
            b'.' => {
                let root = pop!();
                return Ok(Pickle { nodes, root });
            }
            b'(' => marks.push(stack.len()),
            b')' => push(&mut nodes, &mut stack, Value::List(Vec::new())),
            b']' => push(&mut nodes, &mut stack, Value::List(Vec::new())),
            b'}' => push(&mut nodes, &mut stack, Value::Dict(Vec::new())),
            b'l' | b't' => {
                let items = since_mark!();
                push(&mut nodes, &mut stack, Value::List(items));
            }
            0x85..=0x87 => {
                let n = usize::from(op - 0x84);
                if stack.len() < n {
                    bail!("the pickle's tuple needs {n} values on the stack");
                }
                let items = stack.split_off(stack.len() - n);
                push(&mut nodes, &mut stack, Value::List(items));
            }
            b'a' | b'e' => {
                let items = if op == b'a' {
                    vec![pop!()]
                } else {
                    since_mark!()
                };
                let list = *stack.last().context("APPEND without a list")?;
                match &mut nodes[list] {
                    Value::List(l) => l.extend(items),
                    _ => bail!("the pickle appends to something that is not a list"),
                }
            }
            b's' | b'u' => {
                let items = if op == b's' {
                    let v = pop!();
                    let k = pop!();
                    vec![k, v]
                } else {
                    since_mark!()
                };
                let dict = *stack.last().context("SETITEM without a dict")?;
                match &mut nodes[dict] {
                    Value::Dict(d) => d.extend(items.chunks(2).filter_map(|c| match c {
                        [k, v] => Some((*k, *v)),
                        _ => None,
                    })),
                    _ => bail!("the pickle sets an item of something that is not a dict"),
                }
            }
            b'J' => {
                let v = r.le(4)? as u32 as i32;
                push(&mut nodes, &mut stack, Value::Int(i64::from(v)));
            }
            b'K' => {
                let v = r.le(1)?;
                push(&mut nodes, &mut stack, Value::Int(v as i64));
            }
            b'M' => {
                let v = r.le(2)?;
                push(&mut nodes, &mut stack, Value::Int(v as i64));
            }
            0x8a | 0x8b => {
                let n = if op == 0x8a { r.le(1)? } else { r.le(4)? } as usize;
                if n > 8 {
                    bail!("the pickle holds an integer beyond 64 bits");
                }
                let b = r.take(n)?;
                let mut v: i64 = 0;
                for (k, &x) in b.iter().enumerate() {
                    v |= i64::from(x) << (8 * k);
                }
                if n > 0 && n < 8 && b[n - 1] & 0x80 != 0 {
                    v -= 1i64 << (8 * n);
                }
                push(&mut nodes, &mut stack, Value::Int(v));
            }
            b'N' => push(&mut nodes, &mut stack, Value::None),
            0x88 | 0x89 => push(&mut nodes, &mut stack, Value::Bool(op == 0x88)),
            b'G' => {
                let b = r.take(8)?;
                let mut a = [0u8; 8];
                a.copy_from_slice(b);
                push(&mut nodes, &mut stack, Value::Float(f64::from_be_bytes(a)));
            }
            b'X' | 0x8c | 0x8d | b'U' | b'T' => {
                let n = match op {
                    0x8c | b'U' => r.le(1)?,
                    0x8d => r.le(8)?,
                    _ => r.le(4)?,
                } as usize;
                let s = String::from_utf8_lossy(r.take(n)?).into_owned();
                push(&mut nodes, &mut stack, Value::Str(s));
            }
            b'C' | b'B' | 0x8e => {
                let n = match op {
                    b'C' => r.le(1)?,
                    b'B' => r.le(4)?,
                    _ => r.le(8)?,
                } as usize;
                let b = r.take(n)?.to_vec();
                push(&mut nodes, &mut stack, Value::Bytes(b));
            }
            b'c' => {
                let (module, name) = (r.line()?, r.line()?);
                push(&mut nodes, &mut stack, Value::Global(module, name));
            }
            0x93 => {
                let name = pop!();
                let module = pop!();
                let (Value::Str(m), Value::Str(n)) = (&nodes[module], &nodes[name]) else {
                    bail!("the pickle's STACK_GLOBAL names no module and name");
                };
                let g = Value::Global(m.clone(), n.clone());
                push(&mut nodes, &mut stack, g);
            }
            b'R' | 0x81 => {
                let args = pop!();
                let callable = pop!();
                let call = Value::Call {
                    callable,
                    args,
                    state: None,
                };
                push(&mut nodes, &mut stack, call);
            }
            b'b' => {
                let s = pop!();
                let obj = *stack.last().context("BUILD without an object")?;
                match &mut nodes[obj] {
                    Value::Call { state, .. } => *state = Some(s),
                    _ => bail!("the pickle builds something that is not an object"),
                }
            }
            b'q' | b'r' | 0x94 => {
                let key = match op {
                    b'q' => r.le(1)?,
                    b'r' => r.le(4)?,
                    _ => memo.len() as u64,
                };
                let top = *stack.last().context("MEMOIZE of an empty stack")?;
                memo.insert(key, top);
            }
            b'h' | b'j' => {
                let key = if op == b'h' { r.le(1)? } else { r.le(4)? };
                let v = *memo
                    .get(&key)
                    .context("the pickle reads an unknown memo entry")?;
                stack.push(v);
            }
            other => bail!("unsupported pickle opcode 0x{other:02x}"),
        }
    }
}

impl Pickle {
    /// The name of the global node `i` calls, if it is a call of a global.
    fn called(&self, i: usize) -> Option<(&Value, &str)> {
        match self.node(i) {
            Value::Call { callable, .. } => match self.node(*callable) {
                Value::Global(_, name) => Some((self.node(i), name.as_str())),
                _ => None,
            },
            _ => None,
        }
    }

    fn items(&self, i: usize) -> Option<&[usize]> {
        match self.node(i) {
            Value::List(items) => Some(items),
            _ => None,
        }
    }

    /// A NumPy dtype node's (kind char, byte size, little endian).
    fn dtype(&self, i: usize) -> Option<(char, usize, bool)> {
        let Some((Value::Call { args, state, .. }, "dtype")) = self.called(i) else {
            return None;
        };
        let Value::Str(code) = self.node(*self.items(*args)?.first()?) else {
            return None;
        };
        let kind = code.chars().next()?;
        let size = code[1..].parse().ok()?;
        let little = match state.and_then(|s| self.items(s)?.get(1).copied()) {
            Some(e) => !matches!(self.node(e), Value::Str(s) if s == ">"),
            None => true,
        };
        Some((kind, size, little))
    }

    /// Integers in raw NumPy bytes of `dtype`.
    fn ints_of(&self, dtype: usize, bytes: &[u8]) -> Result<Vec<i64>> {
        let (kind, size, little) = self
            .dtype(dtype)
            .context("an array element of unknown dtype")?;
        if !matches!(kind, 'i' | 'u')
            || !matches!(size, 1 | 2 | 4 | 8)
            || !bytes.len().is_multiple_of(size)
        {
            bail!("an array of dtype {kind}{size} is not a list of indices");
        }
        Ok(bytes
            .chunks(size)
            .map(|c| {
                let mut v: u64 = 0;
                for k in 0..size {
                    let b = if little { c[k] } else { c[size - 1 - k] };
                    v |= u64::from(b) << (8 * k);
                }
                if kind == 'i' && size < 8 && v >> (8 * size - 1) & 1 == 1 {
                    (v as i64) - (1i64 << (8 * size))
                } else {
                    v as i64
                }
            })
            .collect())
    }

    /// A NumPy array node's `(shape, element nodes or raw integers)`.
    fn array(&self, i: usize) -> Option<(Vec<usize>, Result<Elements>)> {
        let Some((Value::Call { state: Some(s), .. }, "_reconstruct")) = self.called(i) else {
            return None;
        };
        // state = (version, shape, dtype, is_fortran, data)
        let st = self.items(*s)?;
        let (shape, dtype, data) = (st.get(1)?, *st.get(2)?, *st.get(4)?);
        let shape = self
            .items(*shape)?
            .iter()
            .map(|&d| match self.node(d) {
                Value::Int(v) => usize::try_from(*v).ok(),
                _ => None,
            })
            .collect::<Option<Vec<_>>>()?;
        let elements = match self.node(data) {
            Value::List(items) => Ok(Elements::Objects(items.clone())),
            Value::Bytes(b) => self.ints_of(dtype, b).map(Elements::Ints),
            _ => Err(anyhow::anyhow!(
                "an array whose data is neither objects nor bytes"
            )),
        };
        Some((shape, elements))
    }

    /// Node `i` as indices: an int, a NumPy integer scalar, a list or tuple of those, or an
    /// integer array.
    pub fn indices(&self, i: usize) -> Result<Vec<i64>> {
        match self.node(i) {
            Value::Int(v) => return Ok(vec![*v]),
            Value::Bool(b) => return Ok(vec![i64::from(*b)]),
            Value::None => return Ok(Vec::new()),
            Value::List(items) => {
                let mut out = Vec::new();
                for &k in items {
                    out.extend(self.indices(k)?);
                }
                return Ok(out);
            }
            _ => {}
        }
        if let Some((Value::Call { args, .. }, "scalar")) = self.called(i) {
            let a = self
                .items(*args)
                .context("a NumPy scalar without arguments")?;
            if let (Some(&dt), Some(&b)) = (a.first(), a.get(1)) {
                if let Value::Bytes(bytes) = self.node(b) {
                    return self.ints_of(dt, bytes);
                }
            }
        }
        if let Some((_, elements)) = self.array(i) {
            return match elements? {
                Elements::Ints(v) => Ok(v),
                Elements::Objects(items) => {
                    let mut out = Vec::new();
                    for k in items {
                        out.extend(self.indices(k)?);
                    }
                    Ok(out)
                }
            };
        }
        bail!(
            "a value that is not an index or a list of indices: {:?}",
            self.node(i)
        )
    }
}

/// An array's elements: object nodes, or integers from raw bytes.
enum Elements {
    Objects(Vec<usize>),
    Ints(Vec<i64>),
}

/// The rows of a pickled 2-D object array with two columns, VPR-Bench's ground-truth form:
/// `(query, [references])` per row.
pub fn object_rows(data: &[u8]) -> Result<Vec<(usize, Vec<usize>)>> {
    let p = read(data)?;
    let (shape, elements) = p
        .array(p.root())
        .context("the pickle is not a NumPy array")?;
    let Elements::Objects(items) = elements? else {
        bail!("not an object array");
    };
    let (rows, cols) = match shape[..] {
        [r, 2] => (r, 2),
        [r] => (r, 1),
        _ => bail!("expected rows of [query index, [reference indices]], got shape {shape:?}"),
    };
    if items.len() != rows * cols {
        bail!(
            "the array's data has {} values for shape {shape:?}",
            items.len()
        );
    }
    let index = |v: i64| usize::try_from(v).context("a negative index");
    let mut out = Vec::with_capacity(rows);
    for k in 0..rows {
        let (q, refs) = if cols == 2 {
            (items[2 * k], items[2 * k + 1])
        } else {
            // A 1-D array of [query, refs] pairs.
            let pair = p
                .items(items[k])
                .context("a row that is not [query, refs]")?;
            match pair {
                [q, r] => (*q, *r),
                _ => bail!("row {k} is not [query index, [reference indices]]"),
            }
        };
        let qs = p.indices(q)?;
        let [q] = qs[..] else {
            bail!("row {k}: the query is not one index");
        };
        let refs = p
            .indices(refs)
            .with_context(|| format!("row {k}"))?
            .into_iter()
            .map(index)
            .collect::<Result<Vec<_>>>()?;
        out.push((index(q)?, refs));
    }
    Ok(out)
}
