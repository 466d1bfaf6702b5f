//! A safe pickle interpreter: it rebuilds the data a `torch.save` state dict holds and never
//! executes anything. Globals are names, not code: the few a state dict needs are recognised by
//! the torch reader; every other global stays an opaque value.

use std::cell::RefCell;
use std::rc::Rc;

/// A shared, mutable container (pickle containers are references, mutated after memoisation).
pub type Shared<T> = Rc<RefCell<T>>;

/// A value rebuilt from a pickle stream.
#[derive(Debug, Clone)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<Value>),
    List(Shared<Vec<Value>>),
    Dict(Shared<Vec<(Value, Value)>>),
    /// A reference to a global (`module.name`), never resolved to code.
    Global(String, String),
    /// `callee(*args)` recorded, not performed (REDUCE, NEWOBJ); `state` from BUILD.
    Call {
        callee: Box<Value>,
        args: Box<Value>,
        state: Option<Box<Value>>,
    },
    /// A persistent id (`BINPERSID`): torch uses it for storages.
    Persistent(Box<Value>),
}

impl Value {
    /// The first global this value was made from, if any (for error messages).
    pub fn global_name(&self) -> Option<String> {
        match self {
            Value::Global(m, n) => Some(format!("{m}.{n}")),
            Value::Call { callee, .. } => callee.global_name(),
            _ => None,
        }
    }

    /// The entries of a dict value.
    pub fn dict_items(&self) -> Option<Vec<(Value, Value)>> {
        match self {
            Value::Dict(d) => Some(d.borrow().clone()),
            _ => None,
        }
    }

    /// The string, if this is one.
    pub fn as_str(&self) -> Option<&str> {
        match self {
            Value::Str(s) => Some(s),
            _ => None,
        }
    }

    /// The integer, if this is one.
    pub fn as_int(&self) -> Option<i64> {
        match self {
            Value::Int(i) => Some(*i),
            Value::Bool(b) => Some(*b as i64),
            _ => None,
        }
    }

    /// The items of a tuple or list.
    pub fn items(&self) -> Option<Vec<Value>> {
        match self {
            Value::Tuple(t) => Some(t.clone()),
            Value::List(l) => Some(l.borrow().clone()),
            _ => None,
        }
    }
}

/// Why a pickle stream could not be interpreted.
#[derive(Debug, thiserror::Error)]
pub enum PickleError {
    #[error("pickle ends early (at byte {0})")]
    Truncated(usize),
    #[error("unsupported pickle opcode 0x{op:02x} at byte {at}")]
    Opcode { op: u8, at: usize },
    #[error("malformed pickle at byte {at}: {what}")]
    Malformed { at: usize, what: &'static str },
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], PickleError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.buf.len());
        let end = end.ok_or(PickleError::Truncated(self.buf.len()))?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, PickleError> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, PickleError> {
        Ok(u16::from_le_bytes(self.take(2)?.try_into().unwrap()))
    }
    fn u32(&mut self) -> Result<u32, PickleError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn u64(&mut self) -> Result<u64, PickleError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn line(&mut self) -> Result<String, PickleError> {
        let rest = &self.buf[self.pos..];
        let n = rest.iter().position(|&b| b == b'\n').ok_or(PickleError::Truncated(self.buf.len()))?;
        let s = String::from_utf8_lossy(&rest[..n]).into_owned();
        self.pos += n + 1;
        Ok(s)
    }
    fn string(&mut self, n: usize) -> Result<String, PickleError> {
        let at = self.pos;
        let bytes = self.take(n)?;
        String::from_utf8(bytes.to_vec()).map_err(|_| PickleError::Malformed { at, what: "invalid UTF-8" })
    }
}

/// Interpret a pickle stream (protocols 0-5, without out-of-band buffers) into a [`Value`].
pub fn parse(buf: &[u8]) -> Result<Value, PickleError> {
    let mut r = Reader { buf, pos: 0 };
    let mut stack: Vec<Value> = Vec::new();
    let mut marks: Vec<usize> = Vec::new();
    let mut memo: std::collections::HashMap<u64, Value> = Default::default();
    loop {
        let at = r.pos;
        let op = r.u8()?;
        let bad = |what| PickleError::Malformed { at, what };
        macro_rules! pop {
            () => {
                stack.pop().ok_or(bad("stack underflow"))?
            };
        }
        macro_rules! pop_mark {
            () => {{
                let m = marks.pop().ok_or(bad("no mark"))?;
                if m > stack.len() {
                    return Err(bad("mark past stack"));
                }
                stack.split_off(m)
            }};
        }
        match op {
            0x80 => {
                r.u8()?;
            } // PROTO
            0x95 => {
                r.u64()?;
            } // FRAME
            b'.' => return stack.pop().ok_or(bad("empty stack at STOP")),
            b'(' => marks.push(stack.len()),
            b'0' => {
                pop!();
            }
            b'1' => {
                let _ = pop_mark!();
            }
            b'2' => {
                let v = stack.last().ok_or(bad("stack underflow"))?.clone();
                stack.push(v)
            }
            b'N' => stack.push(Value::None),
            0x88 => stack.push(Value::Bool(true)),
            0x89 => stack.push(Value::Bool(false)),
            b'K' => stack.push(Value::Int(r.u8()? as i64)),
            b'M' => stack.push(Value::Int(r.u16()? as i64)),
            b'J' => stack.push(Value::Int(r.u32()? as i32 as i64)),
            b'I' => {
                let l = r.line()?;
                stack.push(match l.as_str() {
                    "00" => Value::Bool(false),
                    "01" => Value::Bool(true),
                    s => Value::Int(s.parse().map_err(|_| bad("bad INT"))?),
                })
            }
            b'L' => {
                let l = r.line()?;
                stack.push(Value::Int(l.trim_end_matches('L').parse().map_err(|_| bad("bad LONG"))?))
            }
            0x8a | 0x8b => {
                let n = if op == 0x8a { r.u8()? as usize } else { r.u32()? as usize };
                let bytes = r.take(n)?;
                if n > 8 {
                    return Err(bad("integer too large"));
                }
                let mut v: i64 = 0;
                for (i, b) in bytes.iter().enumerate() {
                    v |= (*b as i64) << (8 * i);
                }
                if n > 0 && n < 8 && bytes[n - 1] & 0x80 != 0 {
                    v -= 1i64 << (8 * n);
                }
                stack.push(Value::Int(v))
            }
            b'G' => stack.push(Value::Float(f64::from_be_bytes(r.take(8)?.try_into().unwrap()))),
            b'F' => stack.push(Value::Float(r.line()?.parse().map_err(|_| bad("bad FLOAT"))?)),
            b'X' => {
                let n = r.u32()? as usize;
                stack.push(Value::Str(r.string(n)?))
            }
            0x8c => {
                let n = r.u8()? as usize;
                stack.push(Value::Str(r.string(n)?))
            }
            0x8d => {
                let n = r.u64()? as usize;
                stack.push(Value::Str(r.string(n)?))
            }
            b'V' => stack.push(Value::Str(r.line()?)),
            b'S' => stack.push(Value::Str(r.line()?.trim_matches(|c| c == '\'' || c == '"').to_string())),
            b'U' => {
                let n = r.u8()? as usize;
                stack.push(Value::Bytes(r.take(n)?.to_vec()))
            }
            b'T' => {
                let n = r.u32()? as usize;
                stack.push(Value::Bytes(r.take(n)?.to_vec()))
            }
            b'C' => {
                let n = r.u8()? as usize;
                stack.push(Value::Bytes(r.take(n)?.to_vec()))
            }
            b'B' => {
                let n = r.u32()? as usize;
                stack.push(Value::Bytes(r.take(n)?.to_vec()))
            }
            0x8e | 0x96 => {
                let n = r.u64()? as usize;
                stack.push(Value::Bytes(r.take(n)?.to_vec()))
            }
            b')' => stack.push(Value::Tuple(vec![])),
            b't' => {
                let items = pop_mark!();
                stack.push(Value::Tuple(items))
            }
            0x85 => {
                let a = pop!();
                stack.push(Value::Tuple(vec![a]))
            }
            0x86 => {
                let b = pop!();
                let a = pop!();
                stack.push(Value::Tuple(vec![a, b]))
            }
            0x87 => {
                let c = pop!();
                let b = pop!();
                let a = pop!();
                stack.push(Value::Tuple(vec![a, b, c]))
            }
            b']' => stack.push(Value::List(Default::default())),
            b'l' => {
                let items = pop_mark!();
                stack.push(Value::List(Rc::new(RefCell::new(items))))
            }
            b'}' => stack.push(Value::Dict(Default::default())),
            b'd' => {
                let items = pop_mark!();
                stack.push(Value::Dict(Rc::new(RefCell::new(pairs(items).ok_or(bad("odd dict items"))?))))
            }
            0x8f => stack.push(Value::List(Default::default())), // EMPTY_SET: kept as a list
            0x90 | 0x91 => {
                let items = pop_mark!();
                if op == 0x91 {
                    stack.push(Value::List(Rc::new(RefCell::new(items))))
                } else {
                    extend(stack.last(), items).ok_or(bad("ADDITEMS on non-set"))?
                }
            }
            b'a' => {
                let v = pop!();
                extend(stack.last(), vec![v]).ok_or(bad("APPEND on non-list"))?
            }
            b'e' => {
                let items = pop_mark!();
                extend(stack.last(), items).ok_or(bad("APPENDS on non-list"))?
            }
            b's' => {
                let v = pop!();
                let k = pop!();
                set_items(stack.last(), vec![(k, v)]).ok_or(bad("SETITEM on non-dict"))?
            }
            b'u' => {
                let items = pop_mark!();
                let items = pairs(items).ok_or(bad("odd SETITEMS"))?;
                set_items(stack.last(), items).ok_or(bad("SETITEMS on non-dict"))?
            }
            b'c' => {
                let m = r.line()?;
                let n = r.line()?;
                stack.push(Value::Global(m, n))
            }
            0x93 => {
                let n = pop!();
                let m = pop!();
                match (m, n) {
                    (Value::Str(m), Value::Str(n)) => stack.push(Value::Global(m, n)),
                    _ => return Err(bad("STACK_GLOBAL needs two strings")),
                }
            }
            b'R' | 0x81 => {
                let args = pop!();
                let callee = pop!();
                stack.push(call(callee, args))
            }
            0x92 => {
                let _kwargs = pop!();
                let args = pop!();
                let callee = pop!();
                stack.push(Value::Call { callee: Box::new(callee), args: Box::new(args), state: None })
            }
            b'b' => {
                let state = pop!();
                match stack.last_mut().ok_or(bad("BUILD on empty stack"))? {
                    Value::Dict(d) => {
                        if let Some(items) = state.dict_items() {
                            d.borrow_mut().extend(items)
                        }
                    }
                    Value::Call { state: s, .. } => *s = Some(Box::new(state)),
                    _ => {}
                }
            }
            b'Q' => {
                let pid = pop!();
                stack.push(Value::Persistent(Box::new(pid)))
            }
            b'P' => stack.push(Value::Persistent(Box::new(Value::Str(r.line()?)))),
            b'q' => {
                let k = r.u8()? as u64;
                memo.insert(k, stack.last().ok_or(bad("PUT on empty stack"))?.clone());
            }
            b'r' => {
                let k = r.u32()? as u64;
                memo.insert(k, stack.last().ok_or(bad("PUT on empty stack"))?.clone());
            }
            b'p' => {
                let k = r.line()?.parse().map_err(|_| bad("bad PUT"))?;
                memo.insert(k, stack.last().ok_or(bad("PUT on empty stack"))?.clone());
            }
            0x94 => {
                let k = memo.len() as u64;
                memo.insert(k, stack.last().ok_or(bad("MEMOIZE on empty stack"))?.clone());
            }
            b'h' => {
                let k = r.u8()? as u64;
                stack.push(memo.get(&k).ok_or(bad("unknown memo key"))?.clone())
            }
            b'j' => {
                let k = r.u32()? as u64;
                stack.push(memo.get(&k).ok_or(bad("unknown memo key"))?.clone())
            }
            b'g' => {
                let k: u64 = r.line()?.parse().map_err(|_| bad("bad GET"))?;
                stack.push(memo.get(&k).ok_or(bad("unknown memo key"))?.clone())
            }
            _ => return Err(PickleError::Opcode { op, at }),
        }
    }
}

/// Record a call. `collections.OrderedDict(...)` is the one call performed: it only makes a dict.
fn call(callee: Value, args: Value) -> Value {
    if let Value::Global(m, n) = &callee {
        if m == "collections" && n == "OrderedDict" {
            let items = args.items().and_then(|a| a.first().and_then(|v| v.items()));
            let pairs = items.unwrap_or_default().into_iter().filter_map(|p| match p {
                Value::Tuple(kv) if kv.len() == 2 => Some((kv[0].clone(), kv[1].clone())),
                _ => None,
            });
            return Value::Dict(Rc::new(RefCell::new(pairs.collect())));
        }
    }
    Value::Call { callee: Box::new(callee), args: Box::new(args), state: None }
}

fn pairs(items: Vec<Value>) -> Option<Vec<(Value, Value)>> {
    if items.len() % 2 != 0 {
        return None;
    }
    let mut it = items.into_iter();
    let mut out = Vec::new();
    while let (Some(k), Some(v)) = (it.next(), it.next()) {
        out.push((k, v));
    }
    Some(out)
}

fn extend(target: Option<&Value>, items: Vec<Value>) -> Option<()> {
    match target? {
        Value::List(l) => {
            l.borrow_mut().extend(items);
            Some(())
        }
        // Appending to an opaque object (a list subclass): keep it opaque.
        Value::Call { .. } => Some(()),
        _ => None,
    }
}

fn set_items(target: Option<&Value>, items: Vec<(Value, Value)>) -> Option<()> {
    match target? {
        Value::Dict(d) => {
            let mut d = d.borrow_mut();
            for (k, v) in items {
                // Python dict semantics: a repeated key replaces the earlier value.
                if let Some(slot) = d.iter_mut().find(|(ek, _)| same_key(ek, &k)) {
                    slot.1 = v;
                } else {
                    d.push((k, v));
                }
            }
            Some(())
        }
        // Items set on an opaque object (a dict subclass): it stays opaque.
        Value::Call { .. } => Some(()),
        _ => None,
    }
}

fn same_key(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Str(a), Value::Str(b)) => a == b,
        (Value::Int(a), Value::Int(b)) => a == b,
        _ => false,
    }
}
