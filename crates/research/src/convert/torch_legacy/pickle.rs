//! The small pickle machine of [`super`]: the opcodes protocol 2 uses, read into an arena of
//! objects, never running Python code (the module documentation of [`super`] says what each
//! opcode keeps).

use std::collections::BTreeMap;

use super::TorchError;

/// A pickle value: small values inline, everything else an object of the arena.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Object(usize),
}

#[derive(Debug, Clone, PartialEq)]
pub(super) enum Object {
    Str(String),
    Bytes(Vec<u8>),
    /// An integer too long for `i64`: its little-endian two's-complement bytes.
    Long(Vec<u8>),
    Tuple(Vec<Value>),
    List(Vec<Value>),
    Dict(Vec<(Value, Value)>),
    /// `module.name`, never resolved.
    Global {
        module: String,
        name: String,
    },
    /// `callable(*args)`, never called.
    Call {
        callable: Value,
        args: Value,
    },
    PersistentId(Value),
}

/// The machine of one pickle: its stack, the marks, the memo, and the objects.
#[derive(Default)]
struct Machine {
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: BTreeMap<u32, Value>,
    objects: Vec<Object>,
}

/// One pickle's value, with the objects it refers to.
pub(super) struct Unpickled {
    pub(super) value: Value,
    objects: Vec<Object>,
}

impl Unpickled {
    pub(super) fn object(&self, v: Value) -> Option<&Object> {
        match v {
            Value::Object(i) => self.objects.get(i),
            _ => None,
        }
    }

    pub(super) fn str(&self, v: Value) -> Option<&str> {
        match self.object(v)? {
            Object::Str(s) => Some(s),
            _ => None,
        }
    }

    pub(super) fn tuple(&self, v: Value) -> Option<&[Value]> {
        match self.object(v)? {
            Object::Tuple(items) => Some(items),
            _ => None,
        }
    }

    pub(super) fn global(&self, v: Value) -> Option<(&str, &str)> {
        match self.object(v)? {
            Object::Global { module, name } => Some((module, name)),
            _ => None,
        }
    }

    pub(super) fn usizes(&self, v: Value) -> Option<Vec<usize>> {
        self.tuple(v)?.iter().map(|x| if let Value::Int(n) = *x { usize::try_from(n).ok() } else { None }).collect()
    }
}

/// Bytes read from `data` at a moving position, each read checked.
pub(super) struct Cursor<'a> {
    pub(super) data: &'a [u8],
    pub(super) at: usize,
}

impl<'a> Cursor<'a> {
    pub(super) fn take(&mut self, n: usize) -> Result<&'a [u8], TorchError> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.data.len()).ok_or(TorchError::Pickle {
            at: self.at,
            message: format!("{n} bytes wanted, {} left", self.data.len().saturating_sub(self.at)),
        })?;
        let bytes = &self.data[self.at..end];
        self.at = end;
        Ok(bytes)
    }

    fn byte(&mut self) -> Result<u8, TorchError> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> Result<u16, TorchError> {
        Ok(u16::from_le_bytes(self.take(2)?.try_into().expect("2 bytes")))
    }

    fn u32(&mut self) -> Result<u32, TorchError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }

    pub(super) fn u64(&mut self) -> Result<u64, TorchError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }

    /// A text line ending in `\n` (the `GLOBAL` opcode's module and name).
    fn line(&mut self) -> Result<String, TorchError> {
        let rest = &self.data[self.at..];
        let end = rest.iter().position(|&b| b == b'\n').ok_or(TorchError::Pickle { at: self.at, message: "an unended line".into() })?;
        let text = std::str::from_utf8(&rest[..end]).map_err(|e| TorchError::Pickle { at: self.at, message: e.to_string() })?;
        self.at += end + 1;
        Ok(text.to_string())
    }

    fn utf8(&mut self, n: usize) -> Result<String, TorchError> {
        let at = self.at;
        let bytes = self.take(n)?;
        String::from_utf8(bytes.to_vec()).map_err(|e| TorchError::Pickle { at, message: e.to_string() })
    }

    fn len_u32(&mut self) -> Result<usize, TorchError> {
        Ok(self.u32()? as usize)
    }
}

impl Machine {
    fn fail<T>(&self, at: usize, message: impl Into<String>) -> Result<T, TorchError> {
        Err(TorchError::Pickle { at, message: message.into() })
    }

    fn new_object(&mut self, object: Object) -> Value {
        self.objects.push(object);
        Value::Object(self.objects.len() - 1)
    }

    fn pop(&mut self, at: usize) -> Result<Value, TorchError> {
        match self.stack.pop() {
            Some(v) => Ok(v),
            None => self.fail(at, "the stack is empty"),
        }
    }

    /// The values pushed since the last mark, and the mark dropped.
    fn pop_mark(&mut self, at: usize) -> Result<Vec<Value>, TorchError> {
        let Some(mark) = self.marks.pop() else { return self.fail(at, "no mark") };
        if mark > self.stack.len() {
            return self.fail(at, "a mark above the stack");
        }
        Ok(self.stack.split_off(mark))
    }

    fn top(&self, at: usize) -> Result<Value, TorchError> {
        match self.stack.last() {
            Some(v) => Ok(*v),
            None => self.fail(at, "the stack is empty"),
        }
    }

    fn push_tuple(&mut self, items: Vec<Value>) {
        let v = self.new_object(Object::Tuple(items));
        self.stack.push(v);
    }

    fn memo_put(&mut self, at: usize, key: u32) -> Result<(), TorchError> {
        let v = self.top(at)?;
        self.memo.insert(key, v);
        Ok(())
    }

    fn memo_get(&mut self, at: usize, key: u32) -> Result<(), TorchError> {
        match self.memo.get(&key) {
            Some(v) => {
                self.stack.push(*v);
                Ok(())
            }
            None => self.fail(at, format!("memo {key} was never stored")),
        }
    }

    /// Appends `items` to the list (or sets `items` as key, value pairs in the dict) below them.
    fn extend(&mut self, at: usize, target: Value, items: Vec<Value>, pairs: bool) -> Result<(), TorchError> {
        let Value::Object(i) = target else { return self.fail(at, "adding items to a value that is not a container") };
        match (self.objects.get_mut(i), pairs) {
            (Some(Object::List(list)), false) => list.extend(items),
            (Some(Object::Dict(dict)), true) if items.len().is_multiple_of(2) => {
                dict.extend(items.chunks_exact(2).map(|kv| (kv[0], kv[1])));
            }
            _ => return self.fail(at, "adding items to a value that is not a container"),
        }
        Ok(())
    }

    /// `callable(*args)`: an empty dict for `collections.OrderedDict()` (a state_dict, filled
    /// next by `SETITEMS`), the call itself for anything else.
    fn reduce(&mut self, at: usize) -> Result<(), TorchError> {
        let args = self.pop(at)?;
        let callable = self.pop(at)?;
        let ordered_dict = matches!(callable, Value::Object(i) if matches!(self.objects.get(i),
            Some(Object::Global { module, name }) if module == "collections" && name == "OrderedDict"));
        let no_args = matches!(args, Value::Object(i) if matches!(self.objects.get(i), Some(Object::Tuple(t)) if t.is_empty()));
        let v = if ordered_dict && no_args {
            self.new_object(Object::Dict(Vec::new()))
        } else {
            self.new_object(Object::Call { callable, args })
        };
        self.stack.push(v);
        Ok(())
    }

    /// Runs the pickle that starts at `cursor`, up to its `STOP`.
    fn run(mut self, cursor: &mut Cursor) -> Result<Unpickled, TorchError> {
        loop {
            let at = cursor.at;
            let op = cursor.byte()?;
            if op == b'.' {
                let value = self.pop(at)?;
                return Ok(Unpickled { value, objects: self.objects });
            }
            self.step(op, at, cursor)?;
        }
    }

    /// One opcode other than `STOP`, at byte `at`, its arguments read from `cursor`.
    fn step(&mut self, op: u8, at: usize, cursor: &mut Cursor) -> Result<(), TorchError> {
        match op {
            b'\x80' => {
                let protocol = cursor.byte()?;
                if protocol > 5 {
                    return self.fail(at, format!("pickle protocol {protocol}"));
                }
            }
            b'\x95' => drop(cursor.u64()?), // FRAME: a length hint only.
            b'(' | b'0' | b'1' | b'2' => self.stack_op(op, at)?,
            b'N' | b'\x88' | b'\x89' | b'J' | b'K' | b'M' | b'\x8a' | b'G' => self.number(op, at, cursor)?,
            b'X' | b'\x8c' | b'U' | b'T' | b'C' | b'B' => self.text(op, at, cursor)?,
            b')' | b't' | b'\x85' | b'\x86' | b'\x87' | b']' | b'}' | b'a' | b'e' | b's' | b'u' => self.container(op, at)?,
            b'c' | b'\x93' | b'R' | b'b' | b'Q' => self.object_op(op, at, cursor)?,
            b'q' | b'r' | b'\x94' | b'h' | b'j' => self.memo_op(op, at, cursor)?,
            other => return self.unread(at, other),
        }
        Ok(())
    }

    fn unread<T>(&self, at: usize, op: u8) -> Result<T, TorchError> {
        self.fail(at, format!("opcode 0x{op:02x} is not read"))
    }

    /// `MARK`, `POP`, `POP_MARK`, `DUP`.
    fn stack_op(&mut self, op: u8, at: usize) -> Result<(), TorchError> {
        match op {
            b'(' => self.marks.push(self.stack.len()),
            b'0' => drop(self.pop(at)?),
            b'1' => drop(self.pop_mark(at)?),
            b'2' => {
                let v = self.top(at)?;
                self.stack.push(v);
            }
            other => return self.unread(at, other),
        }
        Ok(())
    }

    /// `None`, the booleans, the integers and `BINFLOAT`.
    fn number(&mut self, op: u8, at: usize, cursor: &mut Cursor) -> Result<(), TorchError> {
        match op {
            b'N' => self.stack.push(Value::None),
            b'\x88' => self.stack.push(Value::Bool(true)),
            b'\x89' => self.stack.push(Value::Bool(false)),
            b'J' => self.stack.push(Value::Int(i32::from_le_bytes(cursor.take(4)?.try_into().expect("4 bytes")) as i64)),
            b'K' => self.stack.push(Value::Int(cursor.byte()? as i64)),
            b'M' => self.stack.push(Value::Int(cursor.u16()? as i64)),
            b'\x8a' => {
                let n = cursor.byte()? as usize;
                let bytes = cursor.take(n)?;
                let v = match bytes.len() {
                    0 => Value::Int(0),
                    1..=8 => {
                        // Sign-extend the two's-complement bytes to 64 bits.
                        let fill = if bytes[bytes.len() - 1] & 0x80 != 0 { 0xff } else { 0 };
                        let mut wide = [fill; 8];
                        wide[..bytes.len()].copy_from_slice(bytes);
                        Value::Int(i64::from_le_bytes(wide))
                    }
                    _ => self.new_object(Object::Long(bytes.to_vec())),
                };
                self.stack.push(v);
            }
            b'G' => self.stack.push(Value::Float(f64::from_be_bytes(cursor.take(8)?.try_into().expect("8 bytes")))),
            other => return self.unread(at, other),
        }
        Ok(())
    }

    /// The strings and byte strings.
    fn text(&mut self, op: u8, at: usize, cursor: &mut Cursor) -> Result<(), TorchError> {
        let v = match op {
            b'X' => {
                let n = cursor.len_u32()?;
                let s = cursor.utf8(n)?;
                self.new_object(Object::Str(s))
            }
            b'\x8c' => {
                let n = cursor.byte()? as usize;
                let s = cursor.utf8(n)?;
                self.new_object(Object::Str(s))
            }
            b'U' | b'T' | b'C' | b'B' => {
                let n = if matches!(op, b'U' | b'C') { cursor.byte()? as usize } else { cursor.len_u32()? };
                let bytes = cursor.take(n)?.to_vec();
                self.new_object(Object::Bytes(bytes))
            }
            other => return self.unread(at, other),
        };
        self.stack.push(v);
        Ok(())
    }

    /// The tuples, lists and dicts, and the opcodes that fill them.
    fn container(&mut self, op: u8, at: usize) -> Result<(), TorchError> {
        match op {
            b')' => self.push_tuple(Vec::new()),
            b't' => {
                let items = self.pop_mark(at)?;
                self.push_tuple(items);
            }
            b'\x85' | b'\x86' | b'\x87' => {
                let n = (op - b'\x84') as usize;
                if self.stack.len() < n {
                    return self.fail(at, format!("a tuple of {n} from a stack of {}", self.stack.len()));
                }
                let items = self.stack.split_off(self.stack.len() - n);
                self.push_tuple(items);
            }
            b']' => {
                let v = self.new_object(Object::List(Vec::new()));
                self.stack.push(v);
            }
            b'}' => {
                let v = self.new_object(Object::Dict(Vec::new()));
                self.stack.push(v);
            }
            b'a' => {
                let item = self.pop(at)?;
                let list = self.top(at)?;
                self.extend(at, list, vec![item], false)?;
            }
            b'e' => {
                let items = self.pop_mark(at)?;
                let list = self.top(at)?;
                self.extend(at, list, items, false)?;
            }
            b's' => {
                let value = self.pop(at)?;
                let key = self.pop(at)?;
                let dict = self.top(at)?;
                self.extend(at, dict, vec![key, value], true)?;
            }
            b'u' => {
                let items = self.pop_mark(at)?;
                let dict = self.top(at)?;
                self.extend(at, dict, items, true)?;
            }
            other => return self.unread(at, other),
        }
        Ok(())
    }

    /// The globals, calls, `BUILD` and persistent ids: kept as they are, never run.
    fn object_op(&mut self, op: u8, at: usize, cursor: &mut Cursor) -> Result<(), TorchError> {
        match op {
            b'c' => {
                let module = cursor.line()?;
                let name = cursor.line()?;
                let v = self.new_object(Object::Global { module, name });
                self.stack.push(v);
            }
            b'\x93' => {
                let name = self.pop(at)?;
                let module = self.pop(at)?;
                let text = |v: Value, m: &Machine| match v {
                    Value::Object(i) => match m.objects.get(i) {
                        Some(Object::Str(s)) => Some(s.clone()),
                        _ => None,
                    },
                    _ => None,
                };
                let (Some(module), Some(name)) = (text(module, self), text(name, self)) else {
                    return self.fail(at, "STACK_GLOBAL of values that are not strings");
                };
                let v = self.new_object(Object::Global { module, name });
                self.stack.push(v);
            }
            b'R' => self.reduce(at)?,
            b'b' => {
                // BUILD: the object's state is dropped (see the module documentation).
                self.pop(at)?;
                self.top(at)?;
            }
            b'Q' => {
                let id = self.pop(at)?;
                let v = self.new_object(Object::PersistentId(id));
                self.stack.push(v);
            }
            other => return self.unread(at, other),
        }
        Ok(())
    }

    /// The memo's puts and gets.
    fn memo_op(&mut self, op: u8, at: usize, cursor: &mut Cursor) -> Result<(), TorchError> {
        match op {
            b'q' => {
                let key = cursor.byte()? as u32;
                self.memo_put(at, key)
            }
            b'r' => {
                let key = cursor.u32()?;
                self.memo_put(at, key)
            }
            b'\x94' => {
                let key = self.memo.len() as u32;
                self.memo_put(at, key)
            }
            b'h' => {
                let key = cursor.byte()? as u32;
                self.memo_get(at, key)
            }
            b'j' => {
                let key = cursor.u32()?;
                self.memo_get(at, key)
            }
            other => self.unread(at, other),
        }
    }
}

pub(super) fn unpickle(cursor: &mut Cursor) -> Result<Unpickled, TorchError> {
    Machine::default().run(cursor)
}
