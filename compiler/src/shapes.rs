//! One forward pass of tract's shape inference over an ONNX graph, node by node, that stops at
//! the first node whose output size is not a number.
//!
//! The importer, the compiler and the verifier fix every input's shape, so every size in the
//! graph is a number or not yet known. tract 0.23.9 keeps an impossible broadcast of two numbers
//! (16 against 3) as the expression `broadcast(16, 3)` instead of failing, and every later layer
//! grows it: on a head of 40 convolutions its whole-graph analysis then spent seconds simplifying
//! the expressions (found by the `onnx_import` fuzz target: one stride of a fuzzed head changed).
//! The work grows about tenfold with each convolution after the broadcast: without bound. This
//! pass finds such a node first, in time linear in the graph, and the file is refused naming it.

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

/// [`first_unfixed_shape`] as an error, for the graphs of a model directory (compile, verify):
/// `node "NAME": output shape S is not fixed (shapes that do not broadcast?)`.
pub(crate) fn ensure_fixed_shapes(model: &mut InferenceModel) -> TractResult<()> {
    match first_unfixed_shape(model) {
        Some((node, shape)) => Err(TractError::msg(format!(
            "node {node:?}: output shape {shape} is not fixed (shapes that do not broadcast?)"
        ))),
        None => Ok(()),
    }
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

#[cfg(test)]
pub(crate) mod tests {
    use crate::onnx::{Attr, Graph};
    use crate::Tensor;

    /// A graph whose product `mismatch` takes maps 16 and 3 wide, then `convs` padded
    /// convolutions. Fuzzing found a head like it: tract kept the width as `broadcast(16, 3)` and
    /// its analysis spent seconds growing that expression through 40 convolutions; on this graph
    /// it took 1.9 s with 5 convolutions and 51 s with 6 before the check.
    pub(crate) fn unbroadcastable(convs: usize) -> Vec<u8> {
        let mut g = Graph::new("tiny");
        let x = g.input("input", &[1, 2, 16, 16]).unwrap();
        let c = g.constant("c", &Tensor::new([1, 2, 16, 3], vec![1.0; 96])).unwrap();
        let mut y = g.node("Mul", "mismatch", &[&x, &c], &[]).unwrap();
        let w = g.constant("w", &Tensor::new([2, 2, 3, 3], vec![0.1; 36])).unwrap();
        for i in 0..convs {
            let attrs = [("pads", Attr::Ints(vec![1; 4])), ("strides", Attr::Ints(vec![1, 1 + i as i64 % 2]))];
            y = g.node("Conv", &format!("conv{i}"), &[&y, &w], &attrs).unwrap();
        }
        g.output(&y, &[1, 2, 16, 16]).unwrap();
        g.encode("test")
    }

    #[test]
    fn a_model_directory_graph_whose_shapes_do_not_broadcast_is_refused_at_the_node() {
        // `prl compile` and `prl verify` load a model directory's graphs with this runner.
        let inputs = [prl_runtime::TensorInfo { name: "input".into(), shape: vec![1, 2, 16, 16] }];
        let e = crate::OnnxRunner::new(&unbroadcastable(5), "search.onnx", &inputs, None).err().expect("refused");
        let e = e.to_string();
        assert!(e.contains("node \"mismatch\": output shape 1,2,16,broadcast("), "{e}");
        assert!(e.ends_with("is not fixed (shapes that do not broadcast?)"), "{e}");
    }
}
