//! PyTorch zip archives as `torch.save` writes them: `<dir>/data.pkl` plus one raw little-endian
//! file per storage under `<dir>/data/<key>`.

use std::collections::BTreeMap;
use std::io::{Cursor, Read};
use std::path::Path;

use super::pickle::{self, Value};
use super::{DType, Entry};
use crate::{Error, Result, Tensor};

type Archive<'a> = zip::ZipArchive<Cursor<&'a [u8]>>;

pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<BTreeMap<String, Entry>> {
    let bad = |msg: String| Error::format(path, msg);
    let mut zip =
        zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| bad(format!("corrupt or truncated zip archive: {e}")))?;
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
    for (k, v) in state {
        let Some(key) = k.as_str() else { continue };
        let entry = match rebuild(&v) {
            Ok(spec) => {
                let tensor = spec.materialise(&mut zip, &dir).map_err(|m| bad(format!("tensor `{key}`: {m}")))?;
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

fn read_entry(zip: &mut Archive, name: &str) -> std::result::Result<Vec<u8>, String> {
    let mut f = zip.by_name(name).map_err(|e| e.to_string())?;
    let mut buf = Vec::with_capacity(f.size() as usize);
    f.read_to_end(&mut buf).map_err(|e| format!("cannot read: {e}"))?;
    Ok(buf)
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
fn rebuild(v: &Value) -> std::result::Result<TensorSpec, String> {
    let Value::Call { callee, args, .. } = v else {
        return Err(format!("a plain {} value", kind(v)));
    };
    let callee_name = callee.global_name().unwrap_or_default();
    let args = args.items().unwrap_or_default();
    match callee_name.as_str() {
        "torch._utils._rebuild_parameter" | "torch._utils._rebuild_parameter_with_state" => {
            rebuild(args.first().ok_or("a parameter without data")?)
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
        "" => Err(format!("made by calling a {} value", kind(callee))),
        other => Err(format!("built by `{other}`, which is never called")),
    }
}

fn storage_of(v: &Value) -> std::result::Result<(DType, String, usize), String> {
    let Value::Persistent(pid) = v else {
        return Err(match v.global_name() {
            Some(g) => format!("its storage is built by `{g}`, which is never called"),
            None => format!("its storage is a {} value", kind(v)),
        });
    };
    let items = pid.items().ok_or("a malformed storage record")?;
    let [tag, ty, key, _location, numel] = items.as_slice() else { return Err("a malformed storage record".into()) };
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
    fn materialise(&self, zip: &mut Archive, dir: &str) -> std::result::Result<Tensor, String> {
        let name = format!("{dir}data/{}", self.key);
        let raw = read_entry(zip, &name).map_err(|e| format!("storage {name}: {e}"))?;
        let es = self.dtype.size();
        if raw.len() < self.numel * es {
            return Err(format!("storage {name} holds {} bytes, {} expected (truncated?)", raw.len(), self.numel * es));
        }
        let n: usize = self.size.iter().product();
        if n == 0 {
            return Ok(Tensor::new(self.size.clone(), vec![]));
        }
        let last = self.offset + self.size.iter().zip(&self.stride).map(|(s, t)| (s - 1) * t).sum::<usize>();
        if last >= self.numel {
            return Err(format!(
                "size {:?} / stride {:?} / offset {} reach past its storage of {} elements",
                self.size, self.stride, self.offset, self.numel
            ));
        }
        let storage = self.dtype.decode(&raw[..self.numel * es]);
        // Gather in row-major order, honouring arbitrary strides.
        let mut data = Vec::with_capacity(n);
        let mut idx = vec![0usize; self.size.len()];
        for _ in 0..n {
            let at = self.offset + idx.iter().zip(&self.stride).map(|(i, s)| i * s).sum::<usize>();
            data.push(storage[at]);
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < self.size[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Ok(Tensor::new(self.size.clone(), data))
    }
}

fn kind(v: &Value) -> &'static str {
    match v {
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
        Value::Call { .. } => "object",
        Value::Persistent(_) => "persistent",
    }
}
