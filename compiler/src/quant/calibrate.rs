//! Running the fp32 graphs on calibration crops and observing the tensors integer operators
//! would read and write.

use std::collections::HashMap;

use tract_onnx::pb;

use super::{Candidate, Kind, Observer};
use crate::{BuiltModel, Error, OnnxRunner, Result, Tensor};

/// Calibration crops: what the network sees while tracking, cut by the runtime's crop code.
#[derive(Debug, Clone, Default)]
pub struct Calibration {
    /// Template crops `[1, 3, exemplar, exemplar]`, one per target.
    pub templates: Vec<Tensor>,
    /// Search crops `[1, 3, instance, instance]`, each with the index of its target's template.
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
}

/// Template features (the search graph's inputs after `x`) of the templates `wanted`, computed
/// one template at a time: each is tens of megabytes.
fn features_of(model: &BuiltModel, calib: &Calibration, wanted: &[usize]) -> Result<HashMap<usize, Vec<Tensor>>> {
    let template = OnnxRunner::new(&model.template, "template graph", &model.manifest.template.inputs, None)?;
    wanted.iter().map(|&t| Ok((t, template.run(&[&calib.templates[t]])?))).collect()
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
    let template = OnnxRunner::new(&model.template, "template graph", &model.manifest.template.inputs, None)?;
    let mut names: Vec<&str> =
        cands.iter().flat_map(|c| [c.input.as_str(), c.output.as_str()].into_iter().chain(dynamic(c))).collect();
    names.sort();
    names.dedup();
    let inputs = &model.manifest.search.inputs;
    // Graph inputs read directly by a layer are observed where they come from: the search crop
    // (backbone layer 1 reads it), the template features.
    let crop_read = names.contains(&inputs[0].name.as_str());
    let fed: Vec<usize> = (1..inputs.len()).filter(|&i| names.contains(&inputs[i].name.as_str())).collect();
    names.retain(|n| !inputs.iter().any(|i| i.name == *n));
    if names.is_empty() {
        return Err(Error::Quantize(format!("search graph `{}`: nothing to quantise", graph.name)));
    }
    let search = OnnxRunner::new(&model.search, "search graph (calibration)", inputs, Some(&names))?;
    let mut observers: HashMap<String, Observer> = HashMap::new();
    let mut shapes = HashMap::new();
    let mut done = 0;
    for (t, z) in calib.templates.iter().enumerate() {
        let crops: Vec<&Tensor> = calib.searches.iter().filter(|(s, _)| *s == t).map(|(_, x)| x).collect();
        if crops.is_empty() {
            continue;
        }
        let f = template.run(&[z])?;
        for &i in &fed {
            observers.entry(inputs[i].name.to_string()).or_default().observe(&f[i - 1].data);
            shapes.insert(inputs[i].name.to_string(), f[i - 1].shape.clone());
        }
        for x in crops {
            progress("calibrating", done, calib.searches.len());
            if crop_read {
                observers.entry(inputs[0].name.to_string()).or_default().observe(&x.data);
                shapes.insert(inputs[0].name.to_string(), x.shape.clone());
            }
            let args: Vec<&Tensor> = std::iter::once(x).chain(&f).collect();
            let outs = search.run(&args)?;
            for (name, out) in search.output_names().iter().zip(outs) {
                observers.entry(name.clone()).or_default().observe(&out.data);
                shapes.insert(name.clone(), out.shape);
            }
            done += 1;
        }
    }
    progress("calibrating", calib.searches.len(), calib.searches.len());
    Ok(Stats { observers, shapes })
}

/// The right-hand activation of a product of two activations.
fn dynamic(c: &Candidate) -> Option<&str> {
    (c.kind == Kind::ActMatMul).then_some(c.weight.as_str())
}

/// Calibration search crops with their template features, for running variants of the search
/// graph on the same inputs.
pub(crate) struct Samples<'a> {
    crops: Vec<(usize, &'a Tensor)>,
    features: HashMap<usize, Vec<Tensor>>,
}

impl<'a> Samples<'a> {
    /// Up to `n` search crops spread over the calibration set.
    pub fn spread(model: &BuiltModel, calib: &'a Calibration, n: usize) -> Result<Samples<'a>> {
        let len = calib.searches.len();
        let n = n.clamp(1, len);
        let crops: Vec<(usize, &Tensor)> = (0..n).map(|i| &calib.searches[i * len / n]).map(|(t, x)| (*t, x)).collect();
        let mut wanted: Vec<usize> = crops.iter().map(|(t, _)| *t).collect();
        wanted.dedup();
        Ok(Samples { features: features_of(model, calib, &wanted)?, crops })
    }

    /// How many crops.
    pub fn len(&self) -> usize {
        self.crops.len()
    }

    /// The search graph `onnx`'s outputs (PRL-Track: loc, cls1, cls2) on every crop.
    pub fn run(&self, model: &BuiltModel, onnx: &[u8]) -> Result<Vec<Vec<Tensor>>> {
        let search = OnnxRunner::new(onnx, "search graph", &model.manifest.search.inputs, None)?;
        self.crops
            .iter()
            .map(|(t, x)| {
                let args: Vec<&Tensor> = std::iter::once(*x).chain(&self.features[t]).collect();
                search.run(&args)
            })
            .collect()
    }
}
