//! `.safetensors` files.

use std::collections::BTreeMap;
use std::path::Path;

use safetensors::{Dtype, SafeTensors};

use super::{DType, Entry};
use crate::{Error, Result, Tensor};

pub(super) fn read(path: &Path, bytes: &[u8]) -> Result<BTreeMap<String, Entry>> {
    let st = SafeTensors::deserialize(bytes).map_err(|e| Error::format(path, format!("bad safetensors file: {e}")))?;
    let mut out = BTreeMap::new();
    for (name, view) in st.tensors() {
        let dtype = match view.dtype() {
            Dtype::F32 => DType::F32,
            Dtype::F16 => DType::F16,
            Dtype::BF16 => DType::BF16,
            Dtype::F64 => DType::F64,
            Dtype::I64 => DType::I64,
            other => {
                out.insert(name, Entry::Other(format!("unsupported dtype {other:?}")));
                continue;
            }
        };
        let tensor = Tensor::new(view.shape().to_vec(), dtype.decode(view.data()));
        out.insert(name, Entry::Tensor { dtype, tensor });
    }
    Ok(out)
}
