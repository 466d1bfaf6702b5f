//! Running the fp32 graphs on calibration crops and observing the tensors integer operators
//! would read and write.

use std::collections::HashMap;

use tract_onnx::pb;

use super::{Candidate, Kind, Observer};
use crate::net::{self, TEMPLATE_INPUT};
use crate::{BuiltModel, Error, OnnxRunner, Result, Tensor};

/// Calibration crops: what the network sees while tracking, cut by the runtime's crop code.
#[derive(Debug, Clone, Default)]
pub struct Calibration {
    /// Template crops `[1, 3, 127, 127]`, one per target.
    pub templates: Vec<Tensor>,
    /// Search crops `[1, 3, 287, 287]`, each with the index of its target's template.
    pub searches: Vec<(usize, Tensor)>,
    /// Where they came from (recorded in the plan; crop counts are filled in from the data).
    pub info: prl_runtime::CalibrationInfo,
}

/// What calibration saw.
pub(crate) struct Stats {
    /// Value name -> its observer.
    pub observers: HashMap<String, Observer>,
    /// Value name -> its shape.
    pub shapes: HashMap<String, Vec<usize>>,
    /// Template features (`zf1..zf5` as the search graph reads them) of each template.
    pub features: Vec<Vec<Tensor>>,
}

fn check(calib: &Calibration) -> Result<()> {
    if calib.searches.is_empty() {
        return Err(Error::Quantize("no calibration frames: give at least one sequence with ground truth".into()));
    }
    if let Some((t, _)) = calib.searches.iter().find(|(t, _)| *t >= calib.templates.len()) {
        return Err(Error::Quantize(format!("a search crop names template {t} of {}", calib.templates.len())));
    }
    Ok(())
}

/// Run the template graph on every template and the search graph on every search crop,
/// observing each candidate's input and output.
pub(crate) fn observe(
    model: &BuiltModel,
    graph: &pb::GraphProto,
    cands: &[Candidate],
    calib: &Calibration,
    progress: &mut dyn FnMut(&str, usize, usize),
) -> Result<Stats> {
    check(calib)?;
    let template = OnnxRunner::new(&model.template, "template graph", &[TEMPLATE_INPUT], None)?;
    let features = calib.templates.iter().map(|z| template.run(&[z])).collect::<Result<Vec<_>>>()?;
    let mut names: Vec<&str> =
        cands.iter().flat_map(|c| [c.input.as_str(), c.output.as_str()].into_iter().chain(dynamic(c))).collect();
    names.sort();
    names.dedup();
    let inputs = net::search_inputs();
    // Graph inputs read by a layer (the template's `zt1`) are observed in the template features.
    let fed: Vec<usize> = (1..inputs.len()).filter(|&i| names.contains(&inputs[i].name)).collect();
    names.retain(|n| !inputs.iter().any(|i| i.name == *n));
    if names.is_empty() {
        return Err(Error::Quantize(format!("search graph `{}`: nothing to quantise", graph.name)));
    }
    let search = OnnxRunner::new(&model.search, "search graph (calibration)", &inputs, Some(&names))?;
    let mut observers: HashMap<String, Observer> = HashMap::new();
    let mut shapes = HashMap::new();
    for (t, f) in features.iter().enumerate() {
        if calib.searches.iter().any(|(s, _)| *s == t) {
            for &i in &fed {
                observers.entry(inputs[i].name.to_string()).or_default().observe(&f[i - 1].data);
                shapes.insert(inputs[i].name.to_string(), f[i - 1].shape.clone());
            }
        }
    }
    for (i, (t, x)) in calib.searches.iter().enumerate() {
        progress("calibrating", i, calib.searches.len());
        let args: Vec<&Tensor> = std::iter::once(x).chain(&features[*t]).collect();
        let outs = search.run(&args)?;
        for (name, out) in search.output_names().iter().zip(outs) {
            observers.entry(name.clone()).or_default().observe(&out.data);
            shapes.insert(name.clone(), out.shape);
        }
    }
    progress("calibrating", calib.searches.len(), calib.searches.len());
    Ok(Stats { observers, shapes, features })
}

/// The right-hand activation of a product of two activations.
fn dynamic(c: &Candidate) -> Option<&str> {
    (c.kind == Kind::ActMatMul).then_some(c.weight.as_str())
}

/// The search graph `onnx`'s outputs (loc, cls1, cls2) on the calibration crops `samples`.
pub(crate) fn run_search(
    onnx: &[u8],
    calib: &Calibration,
    stats: &Stats,
    samples: &[usize],
) -> Result<Vec<Vec<Tensor>>> {
    let search = OnnxRunner::new(onnx, "search graph", &net::search_inputs(), None)?;
    samples
        .iter()
        .map(|&i| {
            let (t, x) = &calib.searches[i];
            let args: Vec<&Tensor> = std::iter::once(x).chain(&stats.features[*t]).collect();
            search.run(&args)
        })
        .collect()
}
