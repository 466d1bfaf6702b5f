//! The NNEF framework plans are written and read with: tract's own operators plus the `prl`
//! registry, which names operators tract's declutter pass produces but has no NNEF serialiser
//! for: the fused exact GELU, the f32 <-> u8 (de)quantisation at the edges of int8 layers, and
//! the 256-entry lookup tables tract makes of element-wise chains between two of them.

use tract_nnef::internal::*;
use tract_nnef::ser::ints;
use tract_nnef::tract_core::ops::element_wise::ElementWiseOp;
use tract_nnef::tract_core::ops::quant::{DequantizeLinearF32, LookupTable, QuantizeLinearU8};

/// tract's NNEF operators plus the `prl` registry, made once per process: making it parses
/// tract's NNEF standard library, which took longer than reading a small plan's graph.
pub fn nnef() -> &'static Nnef {
    static NNEF: std::sync::OnceLock<Nnef> = std::sync::OnceLock::new();
    NNEF.get_or_init(framework)
}

fn framework() -> Nnef {
    let mut prl = Registry::new("prl");
    prl.register_unit_element_wise("prl_gelu_exact", &tract_nnef::tract_core::ops::nn::GeluExact {});
    prl.register_element_wise(
        "prl_quantize_linear_u8",
        TypeId::of::<QuantizeLinearU8>(),
        Box::new(dump_quantize),
        vec![
            TypeName::Scalar.tensor().named("input"),
            TypeName::Scalar.named("inv_scale"),
            TypeName::Integer.named("zero_point"),
        ],
        load_quantize,
    );
    prl.register_dumper(dump_dequantize);
    prl.register_primitive(
        "prl_dequantize_linear_f32",
        &[
            TypeName::Scalar.tensor().named("input"),
            TypeName::Scalar.named("scale"),
            TypeName::Integer.named("zero_point"),
        ],
        &[("output", TypeName::Scalar.tensor())],
        load_dequantize,
    );
    prl.register_element_wise(
        "prl_lookup_table_u8",
        TypeId::of::<LookupTable>(),
        Box::new(dump_lookup),
        vec![TypeName::Scalar.tensor().named("input"), TypeName::Integer.array().named("table")],
        load_lookup,
    );
    tract_nnef::nnef().with_registry(prl)
}

/// `y = table[x]` on the bytes of a u8 or i8 tensor.
fn dump_lookup(ast: &mut IntoAst, node: &TypedNode) -> TractResult<Option<Arc<RValue>>> {
    let op = node.op_as::<ElementWiseOp>().and_then(|e| e.0.downcast_ref::<LookupTable>());
    let op = op.context("prl_lookup_table_u8 dumper called on another operator")?;
    let table: Vec<usize> = op.table.table().iter().map(|&b| b as usize).collect();
    let input = ast.mapping[&node.inputs[0]].clone();
    Ok(Some(invocation("prl_lookup_table_u8", &[input], &[("table", ints(&table))])))
}

fn load_lookup(builder: &mut ModelBuilder, invocation: &ResolvedInvocation) -> TractResult<Value> {
    let input = invocation.named_arg_as(builder, "input")?;
    let table: TVec<usize> = invocation.named_arg_as(builder, "table")?;
    ensure!(table.len() == 256 && table.iter().all(|&v| v < 256), "prl_lookup_table_u8: not a 256-byte table");
    let table: Vec<u8> = table.iter().map(|&v| v as u8).collect();
    let lut = tract_linalg::routines::lut_u8(&table)?;
    builder.wire(ElementWiseOp(Box::new(LookupTable { table: lut }), None), &[input])
}

/// `y = saturate_u8(round_half_even(x * inv_scale) + zero_point)` (tract keeps 1/scale).
fn dump_quantize(ast: &mut IntoAst, node: &TypedNode) -> TractResult<Option<Arc<RValue>>> {
    let op = node.op_as::<ElementWiseOp>().and_then(|e| e.0.downcast_ref::<QuantizeLinearU8>());
    let op = op.context("prl_quantize_linear_u8 dumper called on another operator")?;
    let input = ast.mapping[&node.inputs[0]].clone();
    Ok(Some(invocation(
        "prl_quantize_linear_u8",
        &[input],
        &[("inv_scale", numeric(op.scale)), ("zero_point", numeric(op.zero_point as i64))],
    )))
}

fn load_quantize(builder: &mut ModelBuilder, invocation: &ResolvedInvocation) -> TractResult<Value> {
    let input = invocation.named_arg_as(builder, "input")?;
    let scale: f32 = invocation.named_arg_as(builder, "inv_scale")?;
    let zero_point: i64 = invocation.named_arg_as(builder, "zero_point")?;
    let zero_point = u8::try_from(zero_point).context("prl_quantize_linear_u8: zero_point out of u8 range")?;
    builder.wire(ElementWiseOp(Box::new(QuantizeLinearU8 { scale, zero_point }), None), &[input])
}

/// `y = (x - zero_point) * scale`.
fn dump_dequantize(ast: &mut IntoAst, node: &TypedNode, op: &DequantizeLinearF32) -> TractResult<Option<Arc<RValue>>> {
    let input = ast.mapping[&node.inputs[0]].clone();
    Ok(Some(invocation(
        "prl_dequantize_linear_f32",
        &[input],
        &[("scale", numeric(op.scale)), ("zero_point", numeric(op.zero_point as i64))],
    )))
}

fn load_dequantize(builder: &mut ModelBuilder, invocation: &ResolvedInvocation) -> TractResult<Value> {
    let input = invocation.named_arg_as(builder, "input")?;
    let scale: f32 = invocation.named_arg_as(builder, "scale")?;
    let zero_point: i64 = invocation.named_arg_as(builder, "zero_point")?;
    builder.wire(DequantizeLinearF32::new(scale, zero_point as i32), &[input])
}
