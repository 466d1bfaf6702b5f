//! PyTorch zip archives as `torch.save` writes them: `<dir>/data.pkl` plus one raw little-endian
//! file per storage under `<dir>/data/<key>`.
//!
//! Every size is checked before it is used: a member is read only up to its declared length
//! (nothing reserved from it), element counts, offsets and strides are overflow-checked against
//! their storage, and the tensors of one checkpoint hold at most [`MAX_ELEMENTS`] values in all (a
//! stride-0 view may expand a tiny storage, but not without bound). Archives that name a member
//! twice are refused: which copy a reader takes differs between readers.

use std::collections::{BTreeMap, HashMap};
use std::io::{Cursor, Read};
use std::path::Path;
use std::rc::Rc;

use super::pickle::{self, Value};
use super::{DType, Entry};
use crate::{Error, Result, Tensor};

type Archive<'a> = zip::ZipArchive<Cursor<&'a [u8]>>;

/// The most values the tensors of one checkpoint may hold in all (512 MiB as f32).
pub const MAX_ELEMENTS: usize = 1 << 27;

pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<BTreeMap<String, Entry>> {
    let bad = |msg: String| Error::format(path, msg);
    let mut zip =
        zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| bad(format!("corrupt or truncated zip archive: {e}")))?;
    if let Some(declared) = declared_members(bytes) {
        if declared != zip.len() {
            return Err(bad(format!(
                "zip archive lists {declared} members but {} distinct names: a member appears twice",
                zip.len()
            )));
        }
    }
    let pkl_name = zip
        .file_names()
        .filter(|n| n.ends_with("data.pkl") && n.matches('/').count() <= 1)
        .min_by_key(|n| n.len())
        .map(str::to_string)
        .ok_or_else(|| bad("zip archive holds no data.pkl: not a torch.save checkpoint".into()))?;
    let dir = pkl_name.strip_suffix("data.pkl").unwrap_or_default().to_string();
    if let Ok(order) = read_entry(&mut zip, &format!("{dir}byteorder")) {
        if order.trim_ascii() != b"little" {
            return Err(bad("big-endian checkpoints are not supported".into()));
        }
    }
    let pkl = read_entry(&mut zip, &pkl_name).map_err(|e| bad(format!("{pkl_name}: {e}")))?;
    let root = pickle::parse(&pkl).map_err(|e| bad(format!("{pkl_name}: {e}")))?;
    let state = state_dict(&root).ok_or_else(|| {
        bad(format!("{pkl_name}: not a state dict (a dict of tensors, or a dict with a `state_dict` entry)"))
    })?;
    let mut out = BTreeMap::new();
    let mut budget = Budget { left: MAX_ELEMENTS, storages: HashMap::new() };
    for (k, v) in state {
        let Some(key) = k.as_str() else { continue };
        let entry = match rebuild(&v, 0) {
            Ok(spec) => {
                let tensor =
                    spec.materialise(&mut zip, &dir, &mut budget).map_err(|m| bad(format!("tensor `{key}`: {m}")))?;
                Entry::Tensor { dtype: spec.dtype, tensor }
            }
            Err(what) => Entry::Other(what),
        };
        out.insert(key.to_string(), entry);
    }
    Ok(out)
}

/// The dict of tensors: the root itself, or the root's `state_dict` (or `model`) entry.
fn state_dict(root: &Value) -> Option<Vec<(Value, Value)>> {
    let items = root.dict_items()?;
    for wrapper in ["state_dict", "model"] {
        if let Some((_, v)) = items.iter().find(|(k, _)| k.as_str() == Some(wrapper)) {
            if let Some(inner) = v.dict_items() {
                return Some(inner);
            }
        }
    }
    Some(items)
}

/// The member count the archive's end-of-central-directory record declares (`None` for zip64
/// archives, whose count is elsewhere, or when the record is not found).
fn declared_members(bytes: &[u8]) -> Option<usize> {
    // The record is 22 bytes plus a comment of at most 65535.
    let from = bytes.len().saturating_sub(22 + 65535);
    let at = (from..=bytes.len().checked_sub(22)?).rev().find(|&i| bytes[i..].starts_with(b"PK\x05\x06"))?;
    let n = u16::from_le_bytes([bytes[at + 10], bytes[at + 11]]);
    (n != 0xffff).then_some(n as usize)
}

/// A member's bytes, read up to its declared length (checked by its CRC); nothing is reserved
/// from the declared length, the buffer grows with the bytes that are really there.
fn read_entry(zip: &mut Archive, name: &str) -> std::result::Result<Vec<u8>, String> {
    let f = zip.by_name(name).map_err(|e| e.to_string())?;
    let declared = f.size();
    let mut buf = Vec::new();
    // One byte past the declared length: the reader then reaches the member's end, where it
    // checks the CRC.
    f.take(declared.saturating_add(1)).read_to_end(&mut buf).map_err(|e| format!("cannot read: {e}"))?;
    if buf.len() as u64 != declared {
        return Err(format!("holds {} bytes, its header says {declared}", buf.len()));
    }
    Ok(buf)
}

/// What the tensors read so far have used: values left to hold, and the storages decoded (each
/// is read once, however many tensors view it).
struct Budget {
    left: usize,
    storages: HashMap<(String, DType), Rc<Vec<f32>>>,
}

/// What `_rebuild_tensor_v2(storage, offset, size, stride, ...)` describes.
struct TensorSpec {
    dtype: DType,
    key: String,
    numel: usize,
    offset: usize,
    size: Vec<usize>,
    stride: Vec<usize>,
}

/// Recognise a tensor; otherwise describe what the value is (naming any global it comes from).
fn rebuild(v: &Value, depth: usize) -> std::result::Result<TensorSpec, String> {
    let Value::Call(c) = v else {
        return Err(format!("a plain {} value", v.kind()));
    };
    if depth > pickle::MAX_WALK_DEPTH {
        return Err("parameters nested too deep".into());
    }
    let callee_name = c.callee.global_name().unwrap_or_default();
    let args = c.args.items().unwrap_or_default();
    match callee_name.as_str() {
        "torch._utils._rebuild_parameter" | "torch._utils._rebuild_parameter_with_state" => {
            rebuild(args.first().ok_or("a parameter without data")?, depth + 1)
        }
        "torch._utils._rebuild_tensor_v2" | "torch._utils._rebuild_tensor" => {
            let [storage, offset, size, stride, ..] = args.as_slice() else {
                return Err("a malformed tensor record".into());
            };
            let (dtype, key, numel) = storage_of(storage)?;
            let dims = |v: &Value| -> Option<Vec<usize>> {
                v.items()?.iter().map(|d| d.as_int().and_then(|i| usize::try_from(i).ok())).collect()
            };
            let offset = offset.as_int().and_then(|i| usize::try_from(i).ok()).ok_or("a bad storage offset")?;
            let size = dims(size).ok_or("a bad tensor size")?;
            let stride = dims(stride).ok_or("a bad tensor stride")?;
            if size.len() != stride.len() {
                return Err("a tensor whose size and stride disagree".into());
            }
            Ok(TensorSpec { dtype, key, numel, offset, size, stride })
        }
        "" => Err(format!("made by calling a {} value", c.callee.kind())),
        other => Err(format!("built by `{other}`, which is never called")),
    }
}

fn storage_of(v: &Value) -> std::result::Result<(DType, String, usize), String> {
    let Value::Persistent(pid) = v else {
        return Err(match v.global_name() {
            Some(g) => format!("its storage is built by `{g}`, which is never called"),
            None => format!("its storage is a {} value", v.kind()),
        });
    };
    let items = pid.items().ok_or("a malformed storage record")?;
    let [tag, ty, key, _location, numel] = items.as_slice() else {
        return Err("a malformed storage record".into());
    };
    if tag.as_str() != Some("storage") {
        return Err("an unknown persistent record".into());
    }
    let ty = ty.global_name().ok_or("a storage without a type")?;
    let dtype = match ty.as_str() {
        "torch.FloatStorage" => DType::F32,
        "torch.HalfStorage" => DType::F16,
        "torch.BFloat16Storage" => DType::BF16,
        "torch.DoubleStorage" => DType::F64,
        "torch.LongStorage" => DType::I64,
        other => return Err(format!("an unsupported storage type `{other}`")),
    };
    let key =
        key.as_str().map(str::to_string).or_else(|| key.as_int().map(|i| i.to_string())).ok_or("a bad storage key")?;
    let numel = numel.as_int().and_then(|i| usize::try_from(i).ok()).ok_or("a bad storage size")?;
    Ok((dtype, key, numel))
}

impl TensorSpec {
    /// The tensor, gathered from its storage (read once per checkpoint, into `budget`).
    fn materialise(&self, zip: &mut Archive, dir: &str, budget: &mut Budget) -> std::result::Result<Tensor, String> {
        let left = &mut budget.left;
        let what = || format!("size {:?} / stride {:?} / offset {}", self.size, self.stride, self.offset);
        let n = self.size.iter().try_fold(1usize, |n, &s| n.checked_mul(s));
        let n = n.filter(|&n| n <= *left).ok_or_else(|| {
            format!("{} asks for more values than a checkpoint may hold ({MAX_ELEMENTS} in all)", what())
        })?;
        *left -= n;
        if n == 0 {
            return Ok(Tensor::new(self.size.clone(), vec![]));
        }
        // The last element's position; every other one is smaller.
        let last = self
            .size
            .iter()
            .zip(&self.stride)
            .try_fold(self.offset, |at, (&s, &t)| at.checked_add((s - 1).checked_mul(t)?));
        if last.is_none_or(|l| l >= self.numel) {
            return Err(format!("{} reaches past its storage of {} elements", what(), self.numel));
        }
        let name = format!("{dir}data/{}", self.key);
        let storage = match budget.storages.get(&(name.clone(), self.dtype)) {
            Some(s) => s.clone(),
            None => {
                let raw = read_entry(zip, &name).map_err(|e| format!("storage {name}: {e}"))?;
                let s = Rc::new(self.dtype.decode(&raw));
                budget.storages.insert((name.clone(), self.dtype), s.clone());
                s
            }
        };
        // The storage record's element count against what the member holds.
        if self.numel > storage.len() {
            return Err(format!(
                "storage {name} holds {} elements of {} bytes, {} expected (truncated?)",
                storage.len(),
                self.dtype.size(),
                self.numel
            ));
        }
        // Gather in row-major order, honouring arbitrary strides, a row of the last dimension
        // at a time.
        let (outer, (row, step)) = match (self.size.split_last(), self.stride.last()) {
            (Some((&row, outer)), Some(&step)) => (outer, (row, step)),
            _ => (&[][..], (1, 1)),
        };
        let mut data = Vec::with_capacity(n);
        let mut idx = vec![0usize; outer.len()];
        while data.len() < n {
            let at = self.offset + idx.iter().zip(&self.stride).map(|(i, s)| i * s).sum::<usize>();
            match step {
                1 => data.extend_from_slice(&storage[at..at + row]),
                0 => data.resize(data.len() + row, storage[at]),
                _ => data.extend((0..row).map(|k| storage[at + k * step])),
            }
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < outer[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Ok(Tensor::new(self.size.clone(), data))
    }
}
