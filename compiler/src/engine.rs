//! Running an emitted ONNX graph with tract: fixed input facts, optimised, ready to run.

use std::sync::Arc;

use tract_onnx::prelude::{self as tp, Datum as _, Framework, InferenceFact, InferenceModelExt};

use crate::net::{self, Network, TensorSpec};
use crate::{Error, Result, Tensor};

type Plan = Arc<tp::TypedSimplePlan>;

/// A named input of fixed shape: the network's constant specs or a manifest's entries.
pub trait InputSpec {
    /// Value name.
    fn name(&self) -> &str;
    /// Fixed shape.
    fn shape(&self) -> &[usize];
}

impl InputSpec for TensorSpec {
    fn name(&self) -> &str {
        self.name
    }
    fn shape(&self) -> &[usize] {
        self.shape
    }
}

impl InputSpec for prl_runtime::TensorInfo {
    fn name(&self) -> &str {
        &self.name
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
}

/// An ONNX graph loaded in tract, optimised and ready to run.
pub struct OnnxRunner {
    plan: Plan,
    context: String,
    inputs: Vec<(String, Vec<usize>)>,
    outputs: Vec<String>,
}

impl OnnxRunner {
    /// Load ONNX `bytes` with the given fixed inputs (in order). `outputs` selects the values to
    /// compute by name (any named value of the graph, not only its outputs); `None` keeps the
    /// graph's own outputs. `context` names the graph in errors.
    pub fn new(bytes: &[u8], context: &str, inputs: &[impl InputSpec], outputs: Option<&[&str]>) -> Result<Self> {
        let err = |e: tp::TractError| Error::tract(context, format!("{e:#}").replace('\n', " "));
        let mut model = tract_onnx::onnx().model_for_read(&mut &*bytes).map_err(err)?;
        for (i, spec) in inputs.iter().enumerate() {
            model.set_input_fact(i, InferenceFact::dt_shape(f32::datum_type(), spec.shape())).map_err(err)?;
        }
        if let Some(names) = outputs {
            model.select_outputs_by_name(names.iter()).map_err(err)?;
        }
        crate::shapes::ensure_fixed_shapes(&mut model).map_err(err)?;
        let names = model
            .output_outlets()
            .map_err(err)?
            .iter()
            .map(|o| model.outlet_label(*o).map(str::to_string).unwrap_or_else(|| model.node(o.node).name.clone()))
            .collect();
        // The kernel choices a compiled plan is optimised with, so both run the same kernels.
        let knobs = crate::plan::optimizer_knobs();
        let knobs = tract_onnx::tract_core::knobs::KnobScope::new(knobs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .map_err(err)?;
        let model = knobs
            .enter(|| {
                let mut model = model.into_typed()?.into_decluttered()?;
                prl_runtime::accelerate(&mut model)?;
                model.optimize()?; // codegen only: the model is decluttered already
                Ok(model)
            })
            .map_err(err)?;
        let plan = tp::TypedSimplePlan::new(model).map_err(err)?;
        let inputs = inputs.iter().map(|s| (s.name().to_string(), s.shape().to_vec())).collect();
        Ok(OnnxRunner { plan, context: context.to_string(), inputs, outputs: names })
    }

    /// Names of the computed outputs, in order.
    pub fn output_names(&self) -> &[String] {
        &self.outputs
    }

    /// Run on `inputs` (in the order given at load); returns the outputs in order.
    pub fn run(&self, inputs: &[&Tensor]) -> Result<Vec<Tensor>> {
        let err = |e: tp::TractError| Error::tract(&self.context, format!("{e:#}").replace('\n', " "));
        if inputs.len() != self.inputs.len() {
            return Err(Error::tract(
                &self.context,
                format!("{} inputs given, {} expected", inputs.len(), self.inputs.len()),
            ));
        }
        let mut tv = tp::TVec::new();
        for (t, (name, shape)) in inputs.iter().zip(&self.inputs) {
            if &t.shape != shape {
                return Err(Error::tract(
                    &self.context,
                    format!("input `{name}` has shape {:?}, expected {shape:?}", t.shape),
                ));
            }
            tv.push(tp::Tensor::from_shape(&t.shape, &t.data).map_err(err)?.into());
        }
        let outs = self.plan.run(tv).map_err(err)?;
        outs.iter()
            .map(|o| {
                let data = o.try_as_plain_ram().and_then(|v| v.as_slice::<f32>().map(|s| s.to_vec())).map_err(err)?;
                Ok(Tensor::new(o.shape().to_vec(), data))
            })
            .collect()
    }
}

/// Both graphs of a built network loaded in tract: the template graph, then the search graph
/// fed with its outputs.
pub struct NetworkRunner {
    /// `z` -> `zf1..zf5`.
    pub template: OnnxRunner,
    /// `x`, `zf1..zf5` -> `loc`, `cls1`, `cls2` (or the values selected at load).
    pub search: OnnxRunner,
}

impl NetworkRunner {
    /// Load both graphs; `search_outputs` selects named values of the search graph to compute.
    pub fn new(network: &Network, search_outputs: Option<&[&str]>) -> Result<Self> {
        Ok(NetworkRunner {
            template: OnnxRunner::new(&network.template.encode(""), "template graph", &[net::TEMPLATE_INPUT], None)?,
            search: OnnxRunner::new(&network.search.encode(""), "search graph", &net::search_inputs(), search_outputs)?,
        })
    }

    /// Template features of a template crop.
    pub fn template(&self, z: &Tensor) -> Result<Vec<Tensor>> {
        self.template.run(&[z])
    }

    /// The search graph's outputs for a search crop and template features.
    pub fn search(&self, x: &Tensor, zf: &[Tensor]) -> Result<Vec<Tensor>> {
        let args: Vec<&Tensor> = std::iter::once(x).chain(zf).collect();
        self.search.run(&args)
    }
}
