//! A plan's inputs and outputs on one crop, kept in a folder so that the same plan can be
//! checked on another machine (a plan compiled on x86, run on the camera) or another runtime
//! timed on exactly the same data (`benches/peers/`).
//!
//! The folder holds one raw little-endian f32 file per tensor (`<name>.f32`, row-major) and
//! `tensors.json`, an object from each tensor's name to its shape: the template graph's input
//! and outputs, the search graph's input and outputs, named as in the plan's manifest.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::{Error, Plan, Result, TensorInfo};

/// The index file of a recording.
pub const RECORDING_INDEX: &str = "tensors.json";

/// Run `plan` on the exemplar crop `z` and the search crop `x` (float NCHW, as
/// [`Plan::template`] and [`Plan::search`] take them) and write every input and output to `dir`
/// (created if absent; the files through temporaries, committed by `tensors.json`: see
/// [`crate::write_files_atomically`]).
pub fn record(dir: &Path, plan: &Plan, z: &[f32], x: &[f32]) -> Result<()> {
    let m = plan.manifest();
    let zf = plan.template(z)?;
    let out = plan.search(x, &zf)?;
    let mut index = BTreeMap::new();
    let mut files: Vec<(String, Vec<u8>)> = vec![];
    let mut put = |t: &TensorInfo, data: &[f32]| -> Result<()> {
        if t.shape.iter().product::<usize>() != data.len() {
            return Err(Error::Input(format!("{}: shape {:?} does not fit {} values", t.name, t.shape, data.len())));
        }
        files.push((format!("{}.f32", t.name), data.iter().flat_map(|v| v.to_le_bytes()).collect()));
        index.insert(t.name.clone(), t.shape.clone());
        Ok(())
    };
    put(&m.template.inputs[0], z)?;
    put(&m.search.inputs[0], x)?;
    for (t, v) in m.template.outputs.iter().zip(zf.to_vecs()?) {
        put(t, &v)?;
    }
    for (t, v) in m.search.outputs.iter().zip(&out.outputs) {
        put(t, v)?;
    }
    files.push((RECORDING_INDEX.to_string(), serde_json::to_vec_pretty(&index).expect("a map of shapes serialises")));
    let files: Vec<(&str, &[u8])> = files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).collect();
    crate::write_files_atomically(dir, &files, RECORDING_INDEX)
}

/// How one output of a replay compares with the recorded one.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TensorMatch {
    /// `template` or `search`.
    pub graph: &'static str,
    /// The output's name in the manifest.
    pub name: String,
    /// Largest absolute difference.
    pub max_abs: f64,
    /// ‖replayed − recorded‖ / ‖recorded‖ (the absolute norm where the recorded one is 0).
    pub rel: f64,
}

/// Run `plan` on the inputs recorded in `dir` and compare its outputs with the recorded ones.
/// The search graph is fed the *recorded* template features, so each graph is compared alone.
/// Errors name the file: a missing or unreadable tensor, or one whose shape or size is not the
/// plan's.
pub fn replay(dir: &Path, plan: &Plan) -> Result<Vec<TensorMatch>> {
    let index_path = dir.join(RECORDING_INDEX);
    let bytes = std::fs::read(&index_path).map_err(|e| Error::Io { path: index_path.clone(), err: e })?;
    let index: BTreeMap<String, Vec<usize>> = serde_json::from_slice(&bytes)
        .map_err(|e| Error::Plan { path: index_path.clone(), msg: format!("not a tensor index: {e}") })?;
    let m = plan.manifest();
    let read = |t: &TensorInfo| read_tensor(dir, &index_path, &index, t);
    let z = read(&m.template.inputs[0])?;
    let x = read(&m.search.inputs[0])?;
    let recorded_zf = m.template.outputs.iter().map(read).collect::<Result<Vec<_>>>()?;
    let recorded_out = m.search.outputs.iter().map(read).collect::<Result<Vec<_>>>()?;

    let zf = plan.template(&z)?;
    let mut matches = Vec::new();
    for ((t, ours), theirs) in m.template.outputs.iter().zip(zf.to_vecs()?).zip(&recorded_zf) {
        matches.push(compare("template", &t.name, &ours, theirs));
    }
    let out = plan.search(&x, &plan.template_features(recorded_zf)?)?;
    for ((t, ours), theirs) in m.search.outputs.iter().zip(&out.outputs).zip(&recorded_out) {
        matches.push(compare("search", &t.name, ours, theirs));
    }
    Ok(matches)
}

/// The recorded values of tensor `t`, checked against its shape in the plan.
fn read_tensor(
    dir: &Path,
    index_path: &Path,
    index: &BTreeMap<String, Vec<usize>>,
    t: &TensorInfo,
) -> Result<Vec<f32>> {
    let shape = index.get(&t.name).ok_or_else(|| Error::Plan {
        path: index_path.to_path_buf(),
        msg: format!("no tensor `{}` (this recording is not of this plan)", t.name),
    })?;
    if *shape != t.shape {
        return Err(Error::Plan {
            path: index_path.to_path_buf(),
            msg: format!("`{}` has shape {shape:?}; the plan's is {:?}", t.name, t.shape),
        });
    }
    let path: PathBuf = dir.join(format!("{}.f32", t.name));
    let want = t.shape.iter().try_fold(4usize, |n, &d| n.checked_mul(d)).ok_or_else(|| Error::Plan {
        path: index_path.to_path_buf(),
        msg: format!("`{}`: shape {:?} overflows", t.name, t.shape),
    })?;
    let len = std::fs::metadata(&path).map_err(|e| Error::Io { path: path.clone(), err: e })?.len();
    if len != want as u64 {
        return Err(Error::Plan { path, msg: format!("{len} bytes; shape {:?} needs {want}", t.shape) });
    }
    let bytes = std::fs::read(&path).map_err(|e| Error::Io { path: path.clone(), err: e })?;
    Ok(bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
}

fn compare(graph: &'static str, name: &str, ours: &[f32], theirs: &[f32]) -> TensorMatch {
    let (mut diff, mut norm, mut max_abs) = (0f64, 0f64, 0f64);
    for (&a, &b) in ours.iter().zip(theirs) {
        let d = (a as f64 - b as f64).abs();
        // NaN in either counts as an infinite difference.
        let d = if d.is_nan() { f64::INFINITY } else { d };
        diff += d * d;
        norm += (b as f64) * (b as f64);
        max_abs = max_abs.max(d);
    }
    let rel = if norm > 0.0 { (diff / norm).sqrt() } else { diff.sqrt() };
    TensorMatch { graph, name: name.to_string(), max_abs, rel }
}
