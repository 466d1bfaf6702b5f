//! One forward pass of tract's shape inference over an imported graph, node by node, that stops
//! at the first node whose output size is not a number.
//!
//! The importer fixes every input's shape, so every size in the graph is a number or not yet
//! known. tract 0.23.9 keeps an impossible broadcast of two numbers (16 against 3) as the
//! expression `broadcast(16, 3)` instead of failing, and every later layer grows it: on a head
//! of 40 convolutions its whole-graph analysis then spent seconds simplifying the expressions
//! (found by the `onnx_import` fuzz target: one stride of a fuzzed head changed). The work grows
//! about tenfold with each convolution after the broadcast: without bound. This pass finds such a node first, in time linear in the graph,
//! and the import refuses the file naming it.

use tract_onnx::prelude::*;
use tract_onnx::tract_hir::infer::{Factoid, InferenceFact};

/// The first node, in evaluation order, whose inferred output shape holds a size that is not a
/// number: its name and the shape. `None` when there is none, or when tract's inference fails on
/// a node (the full analysis that follows reports that error as it always has).
pub(crate) fn first_unfixed_shape(model: &mut InferenceModel) -> Option<(String, String)> {
    let order = model.eval_order().ok()?;
    for id in order {
        let (inputs, outputs, observed) = facts(model, id).ok()?;
        let node = model.node_mut(id);
        let (inputs, outputs, observed) = (refs(&inputs), refs(&outputs), refs(&observed));
        let (new_inputs, new_outputs, _) = node.op.infer(inputs, outputs, observed).ok()?;
        let input_outlets = model.node(id).inputs.clone();
        for (outlet, fact) in input_outlets.into_iter().zip(new_inputs) {
            let unified = fact.unify(model.outlet_fact(outlet).ok()?).ok()?;
            model.set_outlet_fact(outlet, unified).ok()?;
        }
        for (slot, fact) in new_outputs.into_iter().enumerate() {
            let outlet = OutletId::new(id, slot);
            let unified = model.outlet_fact(outlet).ok()?.unify(&fact).ok()?;
            let unfixed = unified.shape.dims().any(|d| d.concretize().is_some_and(|d| d.to_i64().is_err()));
            if unfixed {
                return Some((model.node(id).name.clone(), format!("{:?}", unified.shape)));
            }
            model.set_outlet_fact(outlet, unified).ok()?;
        }
    }
    None
}

type Facts = TVec<InferenceFact>;

/// A node's input, output and observed facts, owned (the node's op is borrowed mutably next).
fn facts(model: &InferenceModel, id: usize) -> TractResult<(Facts, Facts, Facts)> {
    let (inputs, outputs) = model.node_facts(id)?;
    let node = model.node(id);
    let observed = node.op.observe_outlets(model, node)?;
    let observed = observed.iter().map(|&o| model.outlet_fact(o).cloned()).collect::<TractResult<_>>()?;
    Ok((inputs.into_iter().cloned().collect(), outputs.into_iter().cloned().collect(), observed))
}

fn refs(facts: &Facts) -> TVec<&InferenceFact> {
    facts.iter().collect()
}
