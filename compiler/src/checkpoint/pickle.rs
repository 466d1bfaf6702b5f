//! A safe pickle interpreter: it rebuilds the data a `torch.save` state dict holds and never
//! executes anything. Globals are names, not code: the few a state dict needs are recognised by
//! the torch reader; every other global stays an opaque value.
//!
//! Hostile streams are bounded: values are shared, not copied (`DUP` and memo `GET` cost O(1)),
//! dict keys are hashed, the work spent copying containers is capped by the stream's length,
//! and nesting of any depth is dropped without recursion, so time and memory are linear in the
//! stream and nothing overflows the stack.

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

/// A shared, mutable container (pickle containers are references, mutated after memoisation).
pub type Shared<T> = Rc<RefCell<T>>;

/// A value rebuilt from a pickle stream. Cloning is cheap: every payload is shared.
#[derive(Clone)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(Rc<str>),
    Bytes(Rc<[u8]>),
    Tuple(Rc<[Value]>),
    List(Shared<Vec<Value>>),
    Dict(Shared<Dict>),
    /// A reference to a global (`module.name`), never resolved to code.
    Global(Rc<str>, Rc<str>),
    /// `callee(*args)` recorded, not performed (REDUCE, NEWOBJ); `state` from BUILD.
    Call(Rc<Call>),
    /// A persistent id (`BINPERSID`): torch uses it for storages.
    Persistent(Rc<Value>),
}

/// A call recorded, never made.
#[derive(Clone)]
pub struct Call {
    /// What would be called.
    pub callee: Value,
    /// Its arguments (a tuple, usually).
    pub args: Value,
    /// What `BUILD` would have set on the result.
    pub state: Option<Value>,
}

/// A dict: items in insertion order, string and integer keys hashed (Python semantics: a
/// repeated key replaces the earlier value in place).
#[derive(Clone, Default)]
pub struct Dict {
    items: Vec<(Value, Value)>,
    index: HashMap<Key, usize>,
}

#[derive(Clone, PartialEq, Eq, Hash)]
enum Key {
    Str(Rc<str>),
    Int(i64),
}

impl Dict {
    fn insert(&mut self, k: Value, v: Value) {
        let key = match &k {
            Value::Str(s) => Some(Key::Str(s.clone())),
            Value::Int(i) => Some(Key::Int(*i)),
            _ => None,
        };
        match key {
            Some(key) => match self.index.get(&key) {
                Some(&at) => self.items[at].1 = v,
                None => {
                    self.index.insert(key, self.items.len());
                    self.items.push((k, v));
                }
            },
            None => self.items.push((k, v)),
        }
    }

    /// The items, in insertion order.
    pub fn items(&self) -> &[(Value, Value)] {
        &self.items
    }
}

impl std::fmt::Debug for Value {
    /// Shallow: the kind, and the global a value comes from (values may be cyclic).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self, self.global_name()) {
            (Value::Int(i), _) => write!(f, "Int({i})"),
            (Value::Str(s), _) => write!(f, "Str({s:?})"),
            (v, Some(g)) => write!(f, "{}({g})", v.kind()),
            (v, None) => f.write_str(v.kind()),
        }
    }
}

impl Drop for Value {
    /// Iterative: a value nested a million deep is freed without a million stack frames.
    fn drop(&mut self) {
        let mut pending = Vec::new();
        self.take_children(&mut pending);
        while let Some(mut v) = pending.pop() {
            v.take_children(&mut pending);
        }
    }
}

impl Value {
    /// Child `i` of a value holding others (a sequence's items; a dict's keys and values in
    /// turn; a call's callee, arguments and state; a persistent id's value), `None` past the last.
    pub(super) fn child(&self, i: usize) -> Option<Value> {
        match self {
            Value::Tuple(t) => t.get(i).cloned(),
            Value::List(l) => l.borrow().get(i).cloned(),
            Value::Dict(d) => d.borrow().items.get(i / 2).map(|(k, v)| if i.is_multiple_of(2) { k } else { v }.clone()),
            Value::Call(c) => [Some(&c.callee), Some(&c.args), c.state.as_ref()].get(i).copied().flatten().cloned(),
            Value::Persistent(p) => (i == 0).then(|| (**p).clone()),
            _ => None,
        }
    }

    /// What identifies a value holding others (its shared payload's address); `None` for the
    /// rest.
    pub(super) fn node(&self) -> Option<*const ()> {
        match self {
            Value::Tuple(t) => Some(Rc::as_ptr(t) as *const ()),
            Value::List(l) => Some(Rc::as_ptr(l) as *const ()),
            Value::Dict(d) => Some(Rc::as_ptr(d) as *const ()),
            Value::Call(c) => Some(Rc::as_ptr(c) as *const ()),
            Value::Persistent(p) => Some(Rc::as_ptr(p) as *const ()),
            _ => None,
        }
    }

    /// Empty a list or dict (the one kind of value a stream can change after making it, so the
    /// one kind a cycle passes through).
    pub(super) fn empty(&self) {
        match self {
            Value::List(l) => drop(std::mem::take(&mut *l.borrow_mut())),
            Value::Dict(d) => drop(std::mem::take(&mut *d.borrow_mut())),
            _ => {}
        }
    }

    /// Move out the children this value alone owns (shared ones stay with their other owners).
    fn take_children(&mut self, out: &mut Vec<Value>) {
        let take = |v: &mut Value| std::mem::replace(v, Value::None);
        match self {
            Value::Tuple(t) => {
                if let Some(items) = Rc::get_mut(t) {
                    out.extend(items.iter_mut().map(take));
                }
            }
            Value::List(l) => {
                if let Some(items) = Rc::get_mut(l) {
                    out.append(items.get_mut());
                }
            }
            Value::Dict(d) => {
                if let Some(d) = Rc::get_mut(d) {
                    let d = d.get_mut();
                    d.index.clear();
                    for (k, v) in d.items.drain(..) {
                        out.push(k);
                        out.push(v);
                    }
                }
            }
            Value::Call(c) => {
                if let Some(c) = Rc::get_mut(c) {
                    out.push(take(&mut c.callee));
                    out.push(take(&mut c.args));
                    out.extend(c.state.take());
                }
            }
            Value::Persistent(p) => {
                if let Some(p) = Rc::get_mut(p) {
                    out.push(take(p));
                }
            }
            _ => {}
        }
    }

    /// What kind of value this is, for messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Value::None => "None",
            Value::Bool(_) => "bool",
            Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Bytes(_) => "bytes",
            Value::Tuple(_) => "tuple",
            Value::List(_) => "list",
            Value::Dict(_) => "dict",
            Value::Global(..) => "global",
            Value::Call(_) => "object",
            Value::Persistent(_) => "persistent",
        }
    }

    /// The first global this value was made from, if any (for error messages).
    pub fn global_name(&self) -> Option<String> {
        let mut v = self;
        loop {
            match v {
                Value::Global(m, n) => return Some(format!("{m}.{n}")),
                Value::Call(c) => v = &c.callee,
                _ => return None,
            }
        }
    }

    /// The entries of a dict value.
    pub fn dict_items(&self) -> Option<Vec<(Value, Value)>> {
        match self {
            Value::Dict(d) => Some(d.borrow().items.clone()),
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
            Value::Tuple(t) => Some(t.to_vec()),
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
    /// A list or dict that holds itself through some chain of values: a state dict never does,
    /// and reference counts would never free it.
    #[error("the pickle builds a container that holds itself")]
    Cycle,
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
    fn string(&mut self, n: usize) -> Result<Rc<str>, PickleError> {
        let at = self.pos;
        let bytes = self.take(n)?;
        std::str::from_utf8(bytes).map(Rc::from).map_err(|_| PickleError::Malformed { at, what: "invalid UTF-8" })
    }
}

/// Longest chain of values [`parse`] callers walk (a parameter wrapping a tensor wrapping...).
pub const MAX_WALK_DEPTH: usize = 16;

/// Interpret a pickle stream (protocols 0-5, without out-of-band buffers) into a [`Value`].
/// A stream that makes a container hold itself is refused ([`PickleError::Cycle`]), and what
/// it made is freed.
pub fn parse(buf: &[u8]) -> Result<Value, PickleError> {
    let (mut stack, mut memo) = (Vec::new(), HashMap::new());
    let mut shared = false;
    let result = interpret(buf, &mut stack, &mut memo, &mut shared);
    // Everything the stream made is reachable from the result, the stack or the memo.
    // Only a list or dict changed while something else also held it can have come to hold itself
    // (its new items would hold a reference to it): otherwise there is nothing to walk.
    let cycle = shared && super::cycles::break_cycles(result.iter().chain(&stack).chain(memo.values()));
    result.and_then(|v| if cycle { Err(PickleError::Cycle) } else { Ok(v) })
}

/// The interpreter loop of [`parse`], on its stack and memo.
/// `shared`: set when a list or dict is changed while something besides the stack holds it.
fn interpret(
    buf: &[u8],
    stack: &mut Vec<Value>,
    memo: &mut HashMap<u64, Value>,
    shared: &mut bool,
) -> Result<Value, PickleError> {
    let mut r = Reader { buf, pos: 0 };
    let mut marks: Vec<usize> = Vec::new();
    // Items copied out of containers (BUILD on a dict, OrderedDict(...)): at most a few times
    // the stream's length, so that re-using one large container cannot make parsing quadratic.
    let mut budget = buf.len().saturating_mul(4).saturating_add(1 << 16);
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
        macro_rules! spend {
            ($n:expr) => {
                budget = budget.checked_sub($n).ok_or(bad("too many items copied between containers"))?
            };
        }
        let bytes = |b: &[u8]| Value::Bytes(Rc::from(b));
        let line_str = |l: String| Value::Str(Rc::from(l));
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
                let n = usize::try_from(r.u64()?).map_err(|_| PickleError::Truncated(buf.len()))?;
                stack.push(Value::Str(r.string(n)?))
            }
            b'V' => stack.push(line_str(r.line()?)),
            b'S' => stack.push(line_str(r.line()?.trim_matches(|c| c == '\'' || c == '"').to_string())),
            b'U' | b'C' => {
                let n = r.u8()? as usize;
                stack.push(bytes(r.take(n)?))
            }
            b'T' | b'B' => {
                let n = r.u32()? as usize;
                stack.push(bytes(r.take(n)?))
            }
            0x8e | 0x96 => {
                let n = usize::try_from(r.u64()?).map_err(|_| PickleError::Truncated(buf.len()))?;
                stack.push(bytes(r.take(n)?))
            }
            b')' => stack.push(Value::Tuple(Rc::from([]))),
            b't' => {
                let items = pop_mark!();
                stack.push(Value::Tuple(Rc::from(items)))
            }
            0x85 => {
                let a = pop!();
                stack.push(Value::Tuple(Rc::from([a])))
            }
            0x86 => {
                let b = pop!();
                let a = pop!();
                stack.push(Value::Tuple(Rc::from([a, b])))
            }
            0x87 => {
                let c = pop!();
                let b = pop!();
                let a = pop!();
                stack.push(Value::Tuple(Rc::from([a, b, c])))
            }
            b']' => stack.push(Value::List(Default::default())),
            b'l' => {
                let items = pop_mark!();
                stack.push(Value::List(Rc::new(RefCell::new(items))))
            }
            b'}' => stack.push(Value::Dict(Default::default())),
            b'd' => {
                let items = pop_mark!();
                let mut d = Dict::default();
                for (k, v) in pairs(items).ok_or(bad("odd dict items"))? {
                    d.insert(k, v);
                }
                stack.push(Value::Dict(Rc::new(RefCell::new(d))))
            }
            0x8f => stack.push(Value::List(Default::default())), // EMPTY_SET: kept as a list
            0x90 | 0x91 => {
                let items = pop_mark!();
                if op == 0x91 {
                    stack.push(Value::List(Rc::new(RefCell::new(items))))
                } else {
                    extend(noted(stack.last(), shared), items).ok_or(bad("ADDITEMS on non-set"))?
                }
            }
            b'a' => {
                let v = pop!();
                extend(noted(stack.last(), shared), vec![v]).ok_or(bad("APPEND on non-list"))?
            }
            b'e' => {
                let items = pop_mark!();
                extend(noted(stack.last(), shared), items).ok_or(bad("APPENDS on non-list"))?
            }
            b's' => {
                let v = pop!();
                let k = pop!();
                set_items(noted(stack.last(), shared), vec![(k, v)]).ok_or(bad("SETITEM on non-dict"))?
            }
            b'u' => {
                let items = pop_mark!();
                let items = pairs(items).ok_or(bad("odd SETITEMS"))?;
                set_items(noted(stack.last(), shared), items).ok_or(bad("SETITEMS on non-dict"))?
            }
            b'c' => {
                let m = r.line()?;
                let n = r.line()?;
                stack.push(Value::Global(Rc::from(m), Rc::from(n)))
            }
            0x93 => {
                let n = pop!();
                let m = pop!();
                match (&m, &n) {
                    (Value::Str(m), Value::Str(n)) => stack.push(Value::Global(m.clone(), n.clone())),
                    _ => return Err(bad("STACK_GLOBAL needs two strings")),
                }
            }
            b'R' | 0x81 => {
                let args = pop!();
                let callee = pop!();
                let copied = ordered_dict_size(&callee, &args);
                spend!(copied);
                stack.push(call(callee, args))
            }
            0x92 => {
                let _kwargs = pop!();
                let args = pop!();
                let callee = pop!();
                stack.push(Value::Call(Rc::new(Call { callee, args, state: None })))
            }
            b'b' => {
                let state = pop!();
                match stack.last_mut().ok_or(bad("BUILD on empty stack"))? {
                    // `dict.__setstate__` is `update`; setting attributes on any other value
                    // is never done.
                    Value::Dict(d) => {
                        if let Some(items) = state.dict_items() {
                            spend!(items.len());
                            *shared |= Rc::strong_count(d) > 1;
                            set_items(Some(&Value::Dict(d.clone())), items);
                        }
                    }
                    Value::Call(c) => Rc::make_mut(c).state = Some(state),
                    _ => {}
                }
            }
            b'Q' => {
                let pid = pop!();
                stack.push(Value::Persistent(Rc::new(pid)))
            }
            b'P' => stack.push(Value::Persistent(Rc::new(line_str(r.line()?)))),
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

/// `target`, with `shared` set if it is a list or dict something else also holds.
fn noted<'v>(target: Option<&'v Value>, shared: &mut bool) -> Option<&'v Value> {
    *shared |= match target {
        Some(Value::List(l)) => Rc::strong_count(l) > 1,
        Some(Value::Dict(d)) => Rc::strong_count(d) > 1,
        _ => false,
    };
    target
}

fn is_ordered_dict(callee: &Value) -> bool {
    matches!(callee, Value::Global(m, n) if &**m == "collections" && &**n == "OrderedDict")
}

/// How many items `call(callee, args)` copies (an `OrderedDict` of a list of pairs).
fn ordered_dict_size(callee: &Value, args: &Value) -> usize {
    if !is_ordered_dict(callee) {
        return 0;
    }
    args.items().and_then(|a| a.first().and_then(|v| v.items())).map_or(0, |v| v.len())
}

/// Record a call. `collections.OrderedDict(...)` is the one call performed: it only makes a dict.
fn call(callee: Value, args: Value) -> Value {
    if is_ordered_dict(&callee) {
        let items = args.items().and_then(|a| a.first().and_then(|v| v.items()));
        let mut d = Dict::default();
        for p in items.unwrap_or_default() {
            if let Value::Tuple(kv) = &p {
                if let [k, v] = &kv[..] {
                    d.insert(k.clone(), v.clone());
                }
            }
        }
        return Value::Dict(Rc::new(RefCell::new(d)));
    }
    Value::Call(Rc::new(Call { callee, args, state: None }))
}

fn pairs(items: Vec<Value>) -> Option<Vec<(Value, Value)>> {
    if !items.len().is_multiple_of(2) {
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
        Value::Call(_) => Some(()),
        _ => None,
    }
}

fn set_items(target: Option<&Value>, items: Vec<(Value, Value)>) -> Option<()> {
    match target? {
        Value::Dict(d) => {
            // `d[k] = v` on a dict that holds itself is still one borrow at a time.
            let mut d = d.try_borrow_mut().ok()?;
            for (k, v) in items {
                d.insert(k, v);
            }
            Some(())
        }
        // Items set on an opaque object (a dict subclass): it stays opaque.
        Value::Call(_) => Some(()),
        _ => None,
    }
}
