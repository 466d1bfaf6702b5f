//! The ablation variants of the paper's Table II: each builds, compiles to a plan the runtime
//! loads and runs, and holds exactly the modules it names.

use prl_compiler::net::{build_variant, Variant};
use prl_compiler::{build_model_variant, compile, Tensor, Weights, WeightsSource};
use prl_runtime::{Plan, TrackerConfig};

#[test]
fn each_variant_keeps_exactly_its_modules_and_runs() {
    let weights = Weights::random(0);
    for v in Variant::ALL {
        let net = build_variant(&weights, v).unwrap();
        let bytes = net.search.encode("test");
        let text = String::from_utf8_lossy(&bytes);
        // Initializer names carry the module: AR's conv1, SR1's conv, the transformer blocks.
        assert_eq!(text.contains("grader.ar.conv1"), v.ar(), "{v:?}: AR");
        assert_eq!(text.contains("grader.sr1."), v.sr(), "{v:?}: SR");
        assert_eq!(text.contains("grader.vit."), v.flp(), "{v:?}: HMG");
        assert_eq!(Variant::parse(v.name()), Some(v));
    }
    assert_eq!(Variant::parse("nope"), None);
}

#[test]
fn a_variant_plan_loads_and_tracks_shapes_like_the_full_one() {
    let model = build_model_variant(&WeightsSource::Random(0), Variant::Baseline).unwrap();
    assert_eq!(model.manifest.variant.as_deref(), Some("baseline"));
    let plan = compile(&model, &TrackerConfig::default()).unwrap();
    assert_eq!(plan.manifest.variant.as_deref(), Some("baseline"));
    let dir = tempfile::tempdir().unwrap();
    plan.write(dir.path()).unwrap();
    let plan = Plan::load(dir.path()).unwrap();
    let z = Tensor::full([1, 3, 127, 127], 100.0);
    let x = Tensor::full([1, 3, 287, 287], 90.0);
    let zf = plan.template(&z.data).unwrap();
    let out = plan.search(&x.data, &zf).unwrap();
    let lens: Vec<usize> = out.outputs.iter().map(Vec::len).collect();
    assert_eq!(lens, [4 * 121, 2 * 121, 121]);
    assert!(out.outputs.iter().flatten().all(|v| v.is_finite()));
}
