//! Checkpoint import: PyTorch `.pth` archives (read without Python, the pickle interpreted and
//! never executed) and `.safetensors` files, into a flat map of named tensors.

mod cycles;
mod pickle;
mod safetensors_file;
mod torch;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use crate::{Error, Result, Tensor};

pub use pickle::{parse as parse_pickle, PickleError, Value as PickleValue};

/// Element type of a tensor as stored in the checkpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DType {
    /// IEEE binary32.
    F32,
    /// IEEE binary16.
    F16,
    /// bfloat16.
    BF16,
    /// IEEE binary64 (converted to f32).
    F64,
    /// 64-bit signed integer (converted to f32; only bookkeeping such as `num_batches_tracked`).
    I64,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F16 | DType::BF16 => 2,
            DType::F32 => 4,
            DType::F64 | DType::I64 => 8,
        }
    }

    /// Decode little-endian elements to f32.
    pub(crate) fn decode(self, bytes: &[u8]) -> Vec<f32> {
        let n = self.size();
        let chunks = bytes.chunks_exact(n);
        match self {
            DType::F32 => chunks.map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect(),
            DType::F16 => chunks.map(|c| half::f16::from_le_bytes(c.try_into().unwrap()).to_f32()).collect(),
            DType::BF16 => chunks.map(|c| half::bf16::from_le_bytes(c.try_into().unwrap()).to_f32()).collect(),
            DType::F64 => chunks.map(|c| f64::from_le_bytes(c.try_into().unwrap()) as f32).collect(),
            DType::I64 => chunks.map(|c| i64::from_le_bytes(c.try_into().unwrap()) as f32).collect(),
        }
    }
}

/// One entry of a state dict.
#[derive(Debug, Clone)]
pub enum Entry {
    /// A tensor, converted to f32, with its stored element type.
    Tensor { dtype: DType, tensor: Tensor },
    /// Something that is not a tensor we can rebuild (an opaque global, a number...), described.
    Other(String),
}

/// A loaded checkpoint: named entries of its state dict, `module.` prefixes removed.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    /// Where it was read from.
    pub path: PathBuf,
    /// SHA-256 of the file, hex.
    pub sha256: String,
    /// The state dict.
    pub entries: BTreeMap<String, Entry>,
}

impl Checkpoint {
    /// Load a `.pth`/`.pt` (torch zip archive) or `.safetensors` file, told apart by content.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Self::from_bytes(path, &bytes)
    }

    /// Load from bytes already in memory; `path` names them in errors.
    pub fn from_bytes(path: &Path, bytes: &[u8]) -> Result<Self> {
        let sha256 = hex(&Sha256::digest(bytes));
        let raw = if bytes.starts_with(b"PK") {
            torch::read(path, bytes)?
        } else if bytes.len() >= 8 && bytes.get(8) == Some(&b'{') {
            safetensors_file::read(path, bytes)?
        } else if bytes.starts_with(&[0x80]) {
            return Err(Error::format(
                path,
                "legacy (pre-1.6) torch serialisation is not supported: re-save it with a current torch.save",
            ));
        } else {
            return Err(Error::format(path, "neither a torch zip archive nor a safetensors file"));
        };
        let entries =
            raw.into_iter().map(|(k, v)| (k.strip_prefix("module.").map(str::to_string).unwrap_or(k), v)).collect();
        Ok(Checkpoint { path: path.to_path_buf(), sha256, entries })
    }
}

/// Lower-case hex of bytes.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
