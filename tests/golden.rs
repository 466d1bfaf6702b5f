//! Fidelity: the network built from the reference checkpoint reproduces the official
//! implementation's tensors at every stage, and real-snapshot variants load to the same weights.

mod common;

use common::{f32_bytes, torch_zip, Pickle};
use prl_compiler::checkpoint::{Checkpoint, Entry};
use prl_compiler::net::{self, sincos_pos_embed};
use prl_compiler::{read_golden, verify, NetworkRunner, Weights};

#[test]
fn every_stage_matches_the_official_implementation() {
    let dir = common::golden_dir();
    let weights = Weights::from_checkpoint(Checkpoint::load(dir.join("checkpoint.pth")).unwrap());
    let golden = read_golden(&dir.join("golden.safetensors")).unwrap();
    let report = verify(&weights, &golden, 1e-4).unwrap();
    let names: Vec<&str> = report.stages.iter().map(|s| s.name.as_str()).collect();
    let expected: Vec<&str> =
        net::TEMPLATE_FEATURES.iter().chain(&net::SEARCH_STAGES).chain(&net::SEARCH_OUTPUTS).map(|s| s.name).collect();
    assert_eq!(names, expected, "every stage of the golden file is compared");
    for s in &report.stages {
        assert!(s.rel_error <= 1e-4, "{}: relative error {:e}", s.name, s.rel_error);
    }
    assert!(report.passed && report.skipped.is_empty(), "{:?}", report.skipped);
    // Only BatchNorm bookkeeping is left over.
    assert!(weights.unused_keys().iter().all(|k| k.ends_with("num_batches_tracked")), "{:?}", weights.unused_keys());
}

/// The reference weights rewritten the way a real training snapshot stores them: float32,
/// `{"epoch", "state_dict", "optimizer"}`, `module.` prefixes, and keys the network never uses.
#[test]
fn wrapped_fp32_snapshot_with_extra_keys_gives_the_same_weights() {
    let reference = Checkpoint::load(common::golden_dir().join("checkpoint.pth")).unwrap();
    let mut tensors: Vec<(String, Vec<usize>, Vec<f32>)> = reference
        .entries
        .iter()
        .filter_map(|(k, e)| match e {
            Entry::Tensor { tensor, .. } => Some((format!("module.{k}"), tensor.shape.clone(), tensor.data.clone())),
            Entry::Other(_) => None,
        })
        .collect();
    let extras = [
        ("grader.vit.cls_token", vec![1, 1, 192]),
        ("grader.vit.pos_embed", vec![1, 65537, 192]),
        ("grader.vit.norm.weight", vec![192]),
        ("grader.vit.head.weight", vec![1000, 192]),
    ];
    for (k, shape) in &extras {
        let n = shape.iter().product();
        tensors.push((format!("module.{k}"), shape.clone(), (0..n).map(|i| i as f32 * 1e-3).collect()));
    }
    let mut p = Pickle::new();
    p.op(b'}').mark().str("epoch").int(42).str("state_dict").op(b'}').mark();
    let mut storages = Vec::new();
    for (i, (k, shape, data)) in tensors.iter().enumerate() {
        let mut stride = vec![1usize; shape.len()];
        for d in (0..shape.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * shape[d + 1];
        }
        p.str(k).tensor("FloatStorage", &i.to_string(), data.len(), 0, shape, &stride);
        storages.push((i.to_string(), f32_bytes(data)));
    }
    p.op(b'u');
    p.str("optimizer").op(b'}').mark().str("state").op(b'}').mark().int(0).op(b'}').mark().str("momentum_buffer");
    p.tensor("FloatStorage", "0", tensors[0].2.len(), 0, &tensors[0].1, &[363, 121, 11, 1]).op(b'u').op(b'u').op(b'u');
    p.op(b'u');
    let storages: Vec<(&str, Vec<u8>)> = storages.iter().map(|(k, v)| (k.as_str(), v.clone())).collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("snapshot.pth");
    std::fs::write(&path, torch_zip(Some(&p.finish()), &storages)).unwrap();

    let weights = Weights::from_checkpoint(Checkpoint::load(&path).unwrap());
    let built = net::build_network(&weights).unwrap();
    let reference_weights = Weights::from_checkpoint(reference);
    let reference_built = net::build_network(&reference_weights).unwrap();
    assert_eq!(built.search.encode(""), reference_built.search.encode(""), "same search graph, same weights");
    assert_eq!(built.template.encode(""), reference_built.template.encode(""));
    let unused = weights.unused_keys();
    for (k, _) in &extras {
        assert!(unused.contains(&k.to_string()), "{k} not reported unused: {unused:?}");
    }
}

#[test]
fn sincos_position_embedding_equals_the_checkpoints() {
    let c = Checkpoint::load(common::golden_dir().join("checkpoint.pth")).unwrap();
    let ours = sincos_pos_embed(192, 11);
    for key in ["grader.vit.pos_embed1", "grader.vit.pos_embed2", "grader.vit.pos_embed3"] {
        let Entry::Tensor { tensor, .. } = &c.entries[key] else { panic!("{key}") };
        assert_eq!(tensor.shape, ours.shape);
        let worst = tensor.data.iter().zip(&ours.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst <= 1e-3, "{key}: differs by {worst} (more than fp16 rounding)");
    }
}

#[test]
fn random_weights_are_seeded_and_give_finite_outputs() {
    let a = net::build_network(&Weights::random(7)).unwrap();
    let b = net::build_network(&Weights::random(7)).unwrap();
    let c = net::build_network(&Weights::random(8)).unwrap();
    assert_eq!(a.search.encode(""), b.search.encode(""));
    assert_ne!(a.search.encode(""), c.search.encode(""));
    let golden = read_golden(&common::golden_dir().join("golden.safetensors")).unwrap();
    let runner = NetworkRunner::new(&a, None).unwrap();
    let zf = runner.template(&golden["z"]).unwrap();
    let outs = runner.search(&golden["x"], &zf).unwrap();
    assert_eq!(runner.search.output_names(), ["loc", "cls1", "cls2"]);
    for (o, spec) in outs.iter().zip(net::SEARCH_OUTPUTS) {
        assert_eq!(o.shape, spec.shape);
        assert!(o.data.iter().all(|v| v.is_finite()), "{} not finite", spec.name);
        assert!(o.data.iter().any(|&v| v != o.data[0]), "{} is constant", spec.name);
    }
}
