//! A reader for PyTorch's legacy checkpoint format (what `torch.save` wrote before PyTorch 1.6,
//! and what `_legacy_load` still reads): five pickles one after another — a magic number, the
//! protocol version, the writer's system information, the object itself (a `state_dict` here:
//! names → tensors, each tensor a call of `torch._utils._rebuild_tensor_v2` on a storage named by
//! a persistent id), the list of storage keys — then, for each key in that order, the storage's
//! element count (8 bytes, little-endian) and its raw elements.
//!
//! No Rust crate reads this format: the pickle crates either refuse the `GLOBAL`/`REDUCE`/persistent
//! id opcodes a checkpoint is made of (serde-pickle) or read only the zip format of PyTorch ≥ 1.6
//! (repugnant-pickle, candle). So this module has its own small pickle machine ([`pickle`]), for
//! the opcodes protocol 2 uses. It never runs Python code: a `GLOBAL` is kept as a name, a `REDUCE` as the
//! name and its arguments (but `collections.OrderedDict()`, which becomes an empty dict to fill),
//! and `BUILD` drops the state it is given (an `OrderedDict`'s attributes, which a state_dict uses
//! only for version metadata). Objects live in one arena and values refer to them by index, so
//! the memo's shared references behave as in Python and no input, however nested, makes the
//! reader recurse. Every read is bounds-checked: a malformed file is an error, never a panic.

use std::collections::BTreeMap;

mod pickle;
use pickle::{Cursor, Object, Unpickled, Value, unpickle};

/// The magic number of the legacy format, the first pickle's value: `0x1950a86a20f9469cfc6c`,
/// as the little-endian two's-complement bytes of pickle's `LONG1`.
const MAGIC: [u8; 10] = [0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20, 0x6a, 0xa8, 0x50, 0x19];
/// The protocol version the legacy format writes (`torch.serialization.PROTOCOL_VERSION`).
const PROTOCOL_VERSION: i64 = 1001;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TorchError {
    #[error("a zip-format checkpoint (PyTorch ≥ 1.6); this reader takes the legacy format")]
    ZipFormat,
    #[error("byte {at}: {message}")]
    Pickle { at: usize, message: String },
    #[error("not a legacy PyTorch checkpoint: {0}")]
    Container(String),
    #[error("tensor {name}: {message}")]
    Tensor { name: String, message: String },
}

/// A tensor of a state_dict, its elements as stored (little-endian).
#[derive(Debug, Clone, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    /// The storage's type name (`FloatStorage`, `LongStorage`, …).
    pub storage: String,
    bytes: Vec<u8>,
}

impl Tensor {
    /// The elements as `f32`, for a tensor of `FloatStorage`.
    pub fn f32(&self) -> Option<Vec<f32>> {
        (self.storage == "FloatStorage").then(|| self.bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
    }

    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Bytes per element of a storage type.
fn element_size(storage: &str) -> Option<usize> {
    Some(match storage {
        "DoubleStorage" | "LongStorage" => 8,
        "FloatStorage" | "IntStorage" => 4,
        "HalfStorage" | "BFloat16Storage" | "ShortStorage" => 2,
        "CharStorage" | "ByteStorage" | "BoolStorage" => 1,
        _ => return None,
    })
}

/// Where a tensor's elements are: its storage, the first element's index, the shape.
struct TensorRef {
    key: String,
    storage: String,
    declared: usize,
    offset: usize,
    shape: Vec<usize>,
}

/// The tensor that `_rebuild_tensor_v2(storage, offset, size, stride, …)` makes, checked to be
/// contiguous (every tensor a `state_dict` saves is).
fn tensor_ref(pickle: &Unpickled, name: &str, value: Value) -> Result<TensorRef, TorchError> {
    let fail = |message: &str| TorchError::Tensor { name: name.to_string(), message: message.to_string() };
    let Some(Object::Call { callable, args }) = pickle.object(value) else { return Err(fail("not a tensor")) };
    if pickle.global(*callable) != Some(("torch._utils", "_rebuild_tensor_v2")) {
        return Err(fail("not made by torch._utils._rebuild_tensor_v2"));
    }
    let args = pickle.tuple(*args).ok_or_else(|| fail("arguments that are not a tuple"))?;
    let [id, Value::Int(offset), size, stride, ..] = *args else { return Err(fail("not (storage, offset, size, stride, …)")) };
    let Some(Object::PersistentId(id)) = pickle.object(id) else { return Err(fail("a storage that is not a persistent id")) };
    let id = pickle.tuple(*id).ok_or_else(|| fail("a persistent id that is not a tuple"))?;
    let [kind, storage_type, key, _location, Value::Int(declared), ..] = *id else { return Err(fail("a persistent id of another layout")) };
    if pickle.str(kind) != Some("storage") {
        return Err(fail("a persistent id that is not a storage"));
    }
    let storage = match pickle.global(storage_type) {
        Some(("torch", storage)) => storage.to_string(),
        _ => return Err(fail("a storage type that is not torch's")),
    };
    let key = pickle.str(key).ok_or_else(|| fail("a storage key that is not a string"))?.to_string();
    let (shape, strides) = (pickle.usizes(size), pickle.usizes(stride));
    let (Some(shape), Some(strides)) = (shape, strides) else { return Err(fail("a size or stride that is not a tuple of integers")) };
    let mut expected = 1usize;
    let contiguous = shape.len() == strides.len()
        && shape.iter().zip(&strides).rev().all(|(&n, &s)| {
            let ok = n <= 1 || s == expected;
            expected = expected.saturating_mul(n);
            ok
        });
    if !contiguous {
        return Err(fail("not contiguous"));
    }
    let (Ok(offset), Ok(declared)) = (usize::try_from(offset), usize::try_from(declared)) else {
        return Err(fail("a negative offset or size"));
    };
    Ok(TensorRef { key, storage, declared, offset, shape })
}

/// The tensors of a legacy-format `state_dict` checkpoint, by name (a `module.` prefix, which
/// `DataParallel` adds, is kept).
pub fn read_state_dict(bytes: &[u8]) -> Result<BTreeMap<String, Tensor>, TorchError> {
    if bytes.starts_with(b"PK\x03\x04") {
        return Err(TorchError::ZipFormat);
    }
    let container = |m: &str| TorchError::Container(m.to_string());
    let mut cursor = Cursor { data: bytes, at: 0 };
    let magic = unpickle(&mut cursor)?;
    if magic.object(magic.value) != Some(&Object::Long(MAGIC.to_vec())) {
        return Err(container("the magic number is missing"));
    }
    let version = unpickle(&mut cursor)?;
    if version.value != Value::Int(PROTOCOL_VERSION) {
        return Err(container("another protocol version"));
    }
    let sys_info = unpickle(&mut cursor)?;
    let little_endian = match sys_info.object(sys_info.value) {
        Some(Object::Dict(items)) => items.iter().any(|(k, v)| sys_info.str(*k) == Some("little_endian") && *v == Value::Bool(true)),
        _ => false,
    };
    if !little_endian {
        return Err(container("not written on a little-endian machine"));
    }
    let state = unpickle(&mut cursor)?;
    let Some(Object::Dict(entries)) = state.object(state.value) else { return Err(container("the object is not a dict")) };
    let mut refs = Vec::with_capacity(entries.len());
    for (k, v) in entries {
        let name = state.str(*k).ok_or_else(|| container("a key that is not a string"))?;
        refs.push((name.to_string(), tensor_ref(&state, name, *v)?));
    }
    let keys = unpickle(&mut cursor)?;
    let Some(Object::List(key_values)) = keys.object(keys.value) else { return Err(container("the storage keys are not a list")) };
    let mut storages: BTreeMap<String, &[u8]> = BTreeMap::new();
    for key in key_values {
        let key = keys.str(*key).ok_or_else(|| container("a storage key that is not a string"))?;
        let Some(r) = refs.iter().find(|(_, r)| r.key == key).map(|(_, r)| r) else {
            return Err(container("a storage that no tensor uses"));
        };
        let size = element_size(&r.storage).ok_or_else(|| TorchError::Container(format!("storage type {}", r.storage)))?;
        let count = cursor.u64()? as usize;
        if count != r.declared {
            return Err(TorchError::Container(format!("storage {key}: {count} elements where {} were declared", r.declared)));
        }
        let data = cursor.take(count.checked_mul(size).ok_or_else(|| container("a storage too large"))?)?;
        storages.insert(key.to_string(), data);
    }
    if cursor.at != bytes.len() {
        return Err(TorchError::Container(format!("{} bytes after the last storage", bytes.len() - cursor.at)));
    }
    let mut tensors = BTreeMap::new();
    for (name, r) in refs {
        let fail = |message: &str| TorchError::Tensor { name: name.clone(), message: message.to_string() };
        let data = storages.get(&r.key).ok_or_else(|| fail("its storage is not in the file"))?;
        let size = element_size(&r.storage).ok_or_else(|| fail("an unknown storage type"))?;
        let len = r.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d)).ok_or_else(|| fail("too many elements"))?;
        let span = (r.offset.checked_add(len).and_then(|end| end.checked_mul(size))).filter(|&end| end <= data.len());
        let Some(end) = span else { return Err(fail("runs past its storage")) };
        let bytes = data[r.offset * size..end].to_vec();
        tensors.insert(name, Tensor { shape: r.shape, storage: r.storage, bytes });
    }
    Ok(tensors)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Pickle protocol 2 as `torch.save` (legacy) writes a `state_dict`, for the tests.
    #[derive(Default)]
    pub(crate) struct Writer {
        pub(crate) out: Vec<u8>,
    }

    impl Writer {
        fn op(&mut self, bytes: &[u8]) -> &mut Self {
            self.out.extend_from_slice(bytes);
            self
        }

        fn str(&mut self, s: &str) -> &mut Self {
            self.op(b"X").op(&(s.len() as u32).to_le_bytes()).op(s.as_bytes())
        }

        fn int(&mut self, v: u16) -> &mut Self {
            self.op(b"M").op(&v.to_le_bytes())
        }

        fn ints(&mut self, values: &[usize]) -> &mut Self {
            self.op(b"(");
            for &v in values {
                self.int(v as u16);
            }
            self.op(b"t")
        }

        /// The five pickles and the storages of `tensors` (name, shape, values), in the legacy
        /// layout.
        pub(crate) fn checkpoint(tensors: &[(&str, Vec<usize>, Vec<f32>)]) -> Vec<u8> {
            let mut w = Writer::default();
            w.op(b"\x80\x02\x8a\x0a").op(&MAGIC).op(b".");
            w.op(b"\x80\x02").int(PROTOCOL_VERSION as u16).op(b".");
            w.op(b"\x80\x02}(").str("little_endian").op(b"\x88u.");
            w.op(b"\x80\x02ccollections\nOrderedDict\nq\x00)R(");
            for (i, (name, shape, values)) in tensors.iter().enumerate() {
                let strides: Vec<usize> = (0..shape.len()).map(|d| shape[d + 1..].iter().product()).collect();
                w.str(name).op(b"ctorch._utils\n_rebuild_tensor_v2\n((").str("storage").op(b"ctorch\nFloatStorage\n");
                w.str(&format!("key{i}")).str("cpu").int(values.len() as u16).op(b"tQK\x00").ints(shape).ints(&strides);
                w.op(b"\x89h\x00)Rtr").op(&(i as u32 + 1).to_le_bytes()).op(b"R");
            }
            w.op(b"u}b.");
            w.op(b"\x80\x02](");
            for i in 0..tensors.len() {
                w.str(&format!("key{i}"));
            }
            w.op(b"e.");
            for (_, _, values) in tensors {
                w.op(&(values.len() as u64).to_le_bytes());
                for v in values {
                    w.op(&v.to_le_bytes());
                }
            }
            w.out
        }
    }

    #[test]
    fn reads_the_tensors_of_a_legacy_checkpoint() {
        let bytes = Writer::checkpoint(&[("a.weight", vec![2, 3], (0..6).map(|i| i as f32).collect()), ("b", vec![1], vec![-2.5])]);
        let tensors = read_state_dict(&bytes).unwrap();
        assert_eq!(tensors.len(), 2);
        assert_eq!(tensors["a.weight"].shape, vec![2, 3]);
        assert_eq!(tensors["a.weight"].f32().unwrap(), vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(tensors["b"].f32().unwrap(), vec![-2.5]);
    }

    #[test]
    fn malformed_input_is_an_error_never_a_panic() {
        let good = Writer::checkpoint(&[("w", vec![2, 2], vec![1.0, 2.0, 3.0, 4.0])]);
        // Every truncation, and every single-byte corruption, of a valid file.
        for end in 0..good.len() {
            assert!(read_state_dict(&good[..end]).is_err(), "cut at {end}");
        }
        for at in 0..good.len() {
            for flip in [0x01u8, 0x80, 0xff] {
                let mut bad = good.clone();
                bad[at] ^= flip;
                let _ = read_state_dict(&bad);
            }
        }
        assert_eq!(read_state_dict(b"PK\x03\x04rest"), Err(TorchError::ZipFormat));
        assert!(matches!(read_state_dict(b"\x80\x02\xff."), Err(TorchError::Pickle { at: 2, .. })));
        assert!(matches!(read_state_dict(b"\x80\x02h\x05."), Err(TorchError::Pickle { .. })));
        // Deep nesting does not make the reader recurse.
        let mut deep = b"\x80\x02N".to_vec();
        deep.extend(std::iter::repeat_n(b'\x85', 200_000));
        deep.push(b'.');
        assert!(matches!(read_state_dict(&deep), Err(TorchError::Container(_))));
    }

    #[test]
    fn a_storage_shorter_than_declared_is_refused() {
        let mut bytes = Writer::checkpoint(&[("w", vec![3], vec![1.0, 2.0, 3.0])]);
        // The element count of the one storage: 3 → 2.
        let at = bytes.len() - 3 * 4 - 8;
        bytes[at] = 2;
        bytes.truncate(bytes.len() - 4);
        assert!(matches!(read_state_dict(&bytes), Err(TorchError::Container(m)) if m.contains("2 elements where 3")));
    }
}
