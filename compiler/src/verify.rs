//! `prl verify`: run every stage of the network with tract on golden inputs and compare each
//! tensor with the reference exported from the official implementation.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::checkpoint::{Checkpoint, Entry};
use crate::net::{self, TensorSpec};
use crate::{relative_error, Error, OnnxRunner, Result, Tensor, Weights};

/// The comparison of one tensor.
#[derive(Debug, Clone, Serialize)]
pub struct StageReport {
    /// Tensor name (`zf1`, `s3`, `loc`...).
    pub name: String,
    /// ‖out−ref‖/‖ref‖.
    pub rel_error: f64,
    /// Largest |out−ref|.
    pub max_abs_error: f64,
    /// Within tolerance.
    pub ok: bool,
}

/// The comparison of every tensor present in a golden file.
#[derive(Debug, Clone, Serialize)]
pub struct VerifyReport {
    /// Relative-error tolerance applied.
    pub tolerance: f64,
    /// One entry per compared tensor, in network order.
    pub stages: Vec<StageReport>,
    /// Golden keys that were not compared, with why.
    pub skipped: Vec<(String, String)>,
    /// All compared tensors within tolerance.
    pub passed: bool,
}

/// Read a golden `.safetensors` file as f32 tensors by name.
pub fn read_golden(path: &Path) -> Result<BTreeMap<String, Tensor>> {
    let ckpt = Checkpoint::load(path)?;
    let mut out = BTreeMap::new();
    for (k, e) in ckpt.entries {
        match e {
            Entry::Tensor { tensor, .. } => drop(out.insert(k, tensor)),
            Entry::Other(what) => return Err(Error::format(path, format!("tensor `{k}`: {what}"))),
        }
    }
    Ok(out)
}

/// Build the network from `weights`, run it on the golden inputs (`z`, `x`, and `zf1..zf5` when
/// present, else computed from `z`) and compare every golden tensor the network produces.
pub fn verify(weights: &Weights, golden: &BTreeMap<String, Tensor>, tolerance: f64) -> Result<VerifyReport> {
    let network = net::build_network(weights)?;
    let mut stages = Vec::new();
    let mut skipped = Vec::new();
    let mut compare = |spec: &TensorSpec, out: &Tensor| {
        if let Some(r) = golden.get(spec.name) {
            if r.shape != out.shape {
                skipped.push((
                    spec.name.to_string(),
                    format!("golden shape {:?}, network gives {:?}", r.shape, out.shape),
                ));
                stages.push(StageReport {
                    name: spec.name.into(),
                    rel_error: f64::INFINITY,
                    max_abs_error: f64::INFINITY,
                    ok: false,
                });
                return;
            }
            let (rel, max_abs) = relative_error(&out.data, &r.data);
            stages.push(StageReport {
                name: spec.name.into(),
                rel_error: rel,
                max_abs_error: max_abs,
                ok: rel <= tolerance,
            });
        }
    };
    let check_input = |spec: &TensorSpec| -> Result<Option<&Tensor>> {
        match golden.get(spec.name) {
            Some(t) if t.shape != spec.shape => {
                Err(Error::Other(format!("golden `{}` has shape {:?}, expected {:?}", spec.name, t.shape, spec.shape)))
            }
            t => Ok(t),
        }
    };
    let mut zf: Vec<Option<Tensor>> =
        net::TEMPLATE_FEATURES.iter().map(|s| check_input(s).map(Option::<&Tensor>::cloned)).collect::<Result<_>>()?;
    if let Some(z) = check_input(&net::TEMPLATE_INPUT)? {
        let names: Vec<&str> = net::TEMPLATE_FEATURES.iter().map(|s| s.name).collect();
        let runner =
            OnnxRunner::new(&network.template.encode(""), "template graph", &[net::TEMPLATE_INPUT], Some(&names))?;
        let outs = runner.run(&[z])?;
        for ((spec, out), slot) in net::TEMPLATE_FEATURES.iter().zip(outs).zip(zf.iter_mut()) {
            compare(spec, &out);
            slot.get_or_insert(out);
        }
    }
    let zf: Option<Vec<Tensor>> = zf.into_iter().collect();
    match (check_input(&net::SEARCH_INPUT)?, zf) {
        (Some(x), Some(zf)) => {
            let wanted: Vec<TensorSpec> = net::SEARCH_STAGES
                .iter()
                .chain(&net::SEARCH_OUTPUTS)
                .filter(|s| golden.contains_key(s.name))
                .copied()
                .collect();
            if !wanted.is_empty() {
                let names: Vec<&str> = wanted.iter().map(|s| s.name).collect();
                let runner =
                    OnnxRunner::new(&network.search.encode(""), "search graph", &net::search_inputs(), Some(&names))?;
                let args: Vec<&Tensor> = std::iter::once(x).chain(&zf).collect();
                for (spec, out) in wanted.iter().zip(runner.run(&args)?) {
                    compare(spec, &out);
                }
            }
        }
        (None, _) => skipped.extend(search_keys(golden).map(|k| (k, "no `x` in the golden file".to_string()))),
        (Some(_), None) => skipped.extend(
            search_keys(golden).map(|k| (k, "neither `z` nor all of `zf1..zf5` in the golden file".to_string())),
        ),
    }
    let known = |k: &str| {
        k == "z"
            || k == "x"
            || net::TEMPLATE_FEATURES.iter().chain(&net::SEARCH_STAGES).chain(&net::SEARCH_OUTPUTS).any(|s| s.name == k)
    };
    skipped
        .extend(golden.keys().filter(|k| !known(k)).map(|k| (k.clone(), "not a tensor of this network".to_string())));
    if stages.is_empty() {
        return Err(Error::Other("the golden file holds no tensor this network can be compared on (keys z, x, zf1..zf5, xf1..xf5, s1..s5, ar, sr1, sr2, hmg, loc, cls1, cls2)".into()));
    }
    let passed = stages.iter().all(|s| s.ok);
    Ok(VerifyReport { tolerance, stages, skipped, passed })
}

fn search_keys(golden: &BTreeMap<String, Tensor>) -> impl Iterator<Item = String> + '_ {
    net::SEARCH_STAGES
        .iter()
        .chain(&net::SEARCH_OUTPUTS)
        .filter(|s| golden.contains_key(s.name))
        .map(|s| s.name.to_string())
}
