//! `prl quantize` and `prl compare` on the shared fixture's checkpoint and the shared real
//! sequences: integer kernels really run, outputs stay near fp32 on held-out crops, every
//! option works, and bad arguments are one-line errors that write nothing.

mod common;

use common::{ok, prl};

use std::path::{Path, PathBuf};
use std::process::Output;

use prl_runtime::{LayerDecision, Plan, Tracker};
use prl_track::{calibration_crops, init_box_from_groundtruth, load_frame, CalibrationSpec, Sequence};

/// Bounds on the int8 plan's relative error against fp32 (‖int8 − fp32‖ / ‖fp32‖ over held-out
/// crops) when calibrated on 4 frames; the README's comparison, on 64 frames, is well inside them.
const MAX_LOC: f64 = 0.02;
const MAX_CLS: f64 = 0.25;

/// The one-line error of a failed run.
fn fails(o: &Output) -> String {
    assert!(!o.status.success(), "expected a failure: {}", String::from_utf8_lossy(&o.stdout));
    let err = String::from_utf8_lossy(&o.stderr).trim().to_string();
    assert_eq!(err.lines().count(), 1, "one line expected: {err}");
    err
}

fn shared(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/uav123_10fps").join(name)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Relative errors of `b`'s loc, cls1, cls2 against `a`'s on held-out crops of wakeboard7.
fn held_out_errors(a: &Path, b: &Path) -> [f64; 3] {
    let dir = shared("wakeboard7");
    let seq = Sequence::open(&dir).unwrap();
    let f0 = load_frame(&seq.frames[0]).unwrap();
    let init = init_box_from_groundtruth(seq.groundtruth().unwrap()[0]);
    let spec = CalibrationSpec {
        sequences: vec![dir],
        frames_per_sequence: 4,
        templates_per_sequence: 1,
        seed: 7,
        held_out: true,
    };
    let crops = calibration_crops(&spec, &prl_runtime::TrackerConfig::default(), &mut |_, _| {}).unwrap();
    let mut outs = vec![vec![]; 2];
    for (k, p) in [a, b].into_iter().enumerate() {
        let plan = Plan::load(p).unwrap();
        let config = plan.manifest().tracker.clone();
        let mut t = Tracker::new(plan, config);
        t.init(&f0, init).unwrap();
        for (_, x) in &crops.searches {
            let o = t.plan().search(&x.data, t.features().unwrap()).unwrap();
            let [loc, cls1, cls2]: [Vec<f32>; 3] = o.outputs.try_into().expect("three outputs");
            outs[k].push([loc, cls1, cls2]);
        }
    }
    let mut err = [0.0; 3];
    for (j, e) in err.iter_mut().enumerate() {
        let flat = |k: usize| -> Vec<f32> { outs[k].iter().flat_map(|o| o[j].clone()).collect() };
        *e = prl_compiler::relative_error(&flat(1), &flat(0)).0;
    }
    err
}

#[test]
fn int8_plan_runs_integer_kernels_near_fp32_and_compares() {
    let fp32 = common::reference_plan();
    let t = tempfile::tempdir().unwrap();
    let int8 = t.path().join("int8");
    let out = ok(&prl(&[
        "quantize",
        "--plan",
        s(&fp32),
        "--calib",
        s(&shared("building4")),
        "--frames-per-seq",
        "4",
        "--out",
        s(&int8),
    ]));
    assert!(out.contains("backbone.layer2.conv") && out.contains("wrote int8 plan"), "{out}");

    let plan = Plan::load(&int8).unwrap();
    let m = plan.manifest();
    assert_eq!(m.precision, "int8");
    let q = m.quantization.as_ref().unwrap();
    assert_eq!((q.method.as_str(), q.per_channel.as_str()), ("percentile", "auto"));
    assert_eq!(q.calibration.sequences, vec!["building4".to_string()]);
    // The default: the first box and 3 more per sequence.
    assert_eq!((q.calibration.template_crops, q.calibration.search_crops), (4, 4));
    let int8_layers = q.layers.iter().filter(|l| l.decision == LayerDecision::Int8).count();
    assert!(int8_layers >= 15, "{int8_layers} int8 layers");
    assert!(q.ranges.values().all(|(lo, hi)| lo <= &0.0 && hi >= &0.0 && hi > lo));

    // The optimised search graph multiplies on tract's integer kernels.
    let kernels = common::int8_kernel_nodes(&plan);
    assert!(kernels.iter().any(|n| n.starts_with("backbone_layer2")), "{kernels:?}");
    assert!(kernels.len() >= 10, "{kernels:?}");
    assert!(common::int8_kernel_nodes(&Plan::load(&fp32).unwrap()).is_empty());

    let [loc, cls1, cls2] = held_out_errors(&fp32, &int8);
    eprintln!("held-out relative error: loc {loc:.4} cls1 {cls1:.4} cls2 {cls2:.4}");
    assert!(loc < MAX_LOC && cls1 < MAX_CLS && cls2 < MAX_CLS, "loc {loc} cls1 {cls1} cls2 {cls2}");
    assert!(loc > 0.0, "int8 outputs equal fp32's: nothing was quantised");

    // The comparison report, on a short held-out sequence.
    let json = t.path().join("compare.json");
    let md = t.path().join("compare.md");
    let out = ok(&prl(&[
        "compare",
        "--plan",
        s(&fp32),
        "--plan",
        s(&int8),
        "--sequence",
        s(&shared("wakeboard7")),
        "--crops-per-seq",
        "2",
        "--runs",
        "2",
        "--max-frames",
        "4",
        "--threads",
        "1",
        "--json",
        s(&json),
        "--markdown",
        s(&md),
    ]));
    assert!(out.contains("### Latency") && out.contains("### Output fidelity") && out.contains("| wakeboard7 | 4 |"));
    assert_eq!(std::fs::read_to_string(&md).unwrap(), out);
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(r["plans"][1]["precision"], "int8");
    assert!(r["plans"][1]["size_mb"].as_f64().unwrap() < r["plans"][0]["size_mb"].as_f64().unwrap() / 1.5);
    assert!(r["plans"][0]["peak_rss_mb"].as_f64().unwrap() > 50.0);
    assert_eq!(r["fidelity"][0]["crops"], 2);
    let seq = &r["sequences"][0]["plans"];
    assert!((seq[0]["mean_iou_to_ref"].as_f64().unwrap() - 1.0).abs() < 1e-9);
    assert!(seq[1]["auc"].as_f64().unwrap() >= 0.0);
}

/// An attention product of two activations (`q·kᵀ` of HMG's first block), in the ONNX graph
/// and in tract's optimised graph.
const SCORES: &str = "hmg.blocks.0.attn.cross.x3.scores";
const SCORES_NODE: &str = "hmg_blocks_0_attn_cross_x3";

#[test]
fn every_method_works_keep_fp32_keeps_layers_in_f32_and_act_matmul_adds_attention() {
    let fp32 = common::reference_plan();
    let t = tempfile::tempdir().unwrap();
    let calib = shared("wakeboard7");
    for method in ["minmax", "entropy", "mse"] {
        let out = t.path().join(method);
        let mut args = vec!["quantize", "--plan", s(&fp32), "--calib", s(&calib)];
        args.extend(["--frames-per-seq", "2", "--method", method, "--per-channel", "off", "--out", s(&out)]);
        if method == "minmax" {
            args.extend(["--keep-fp32", "backbone.layer3.conv", "hmg.blocks.0.mlp.fc1.matmul"]);
        } else {
            args.push("--act-matmul");
        }
        ok(&prl(&args));
        let plan = Plan::load(&out).unwrap();
        let q = plan.manifest().quantization.clone().unwrap();
        assert_eq!((q.method.as_str(), q.per_channel.as_str()), (method, "off"));
        assert!(q.layers.iter().all(|l| !l.per_channel));
        let kernels = common::int8_kernel_nodes(&plan);
        assert!(kernels.iter().any(|n| n.starts_with("backbone_layer4")), "{kernels:?}");
        let decision = |n: &str| q.layers.iter().find(|l| l.node == n).unwrap().decision;
        if method == "minmax" {
            assert_eq!(decision("backbone.layer3.conv"), LayerDecision::KeptByUser);
            assert_eq!(decision("hmg.blocks.0.mlp.fc1.matmul"), LayerDecision::KeptByUser);
            assert!(!kernels.iter().any(|n| n.starts_with("backbone_layer3")), "{kernels:?}");
            assert!(!kernels.iter().any(|n| n.starts_with("hmg_blocks_0_mlp_fc1")), "{kernels:?}");
            assert_eq!(decision(SCORES), LayerDecision::ActivationProduct);
            assert!(!kernels.iter().any(|n| n.starts_with(SCORES_NODE)), "{kernels:?}");
        } else {
            assert_eq!(decision("backbone.layer3.conv"), LayerDecision::Int8);
            assert!(kernels.iter().any(|n| n.starts_with("backbone_layer3")), "{kernels:?}");
            // With --act-matmul the attention products multiply on the integer kernels too.
            assert_eq!(decision(SCORES), LayerDecision::Int8);
            assert!(kernels.iter().any(|n| n.starts_with(SCORES_NODE)), "{kernels:?}");
        }
    }
}

#[test]
fn bad_arguments_are_one_line_errors_that_write_nothing() {
    let fp32 = common::reference_plan();
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("out");
    let base = |calib: &Path| -> Vec<String> {
        ["quantize", "--plan", s(&fp32), "--calib", s(calib), "--frames-per-seq", "2", "--out", s(&out)]
            .map(String::from)
            .to_vec()
    };
    let run = |args: Vec<String>| prl(&args.iter().map(String::as_str).collect::<Vec<_>>());

    // Unknown layer.
    let mut args = base(&shared("wakeboard7"));
    args.extend(["--keep-fp32".into(), "backbone.layer9.conv".into()]);
    let e = fails(&run(args));
    assert!(
        e.contains("`backbone.layer9.conv` is not a quantisable layer") && e.contains("backbone.layer2.conv"),
        "{e}"
    );

    // A sequence whose only boxes after the first mark the target absent: no calibration frames.
    let seq = t.path().join("absent");
    std::fs::create_dir_all(seq.join("img")).unwrap();
    for i in 1..=2 {
        let f = format!("img/{i:06}.jpg");
        std::fs::copy(shared("wakeboard7").join(&f), seq.join(&f)).unwrap();
    }
    let gt = std::fs::read_to_string(shared("wakeboard7").join("groundtruth_rect.txt")).unwrap();
    std::fs::write(seq.join("groundtruth_rect.txt"), format!("{}\nNaN,NaN,NaN,NaN\n", gt.lines().next().unwrap()))
        .unwrap();
    let e = fails(&run(base(&seq)));
    assert!(e.contains("no calibration frames"), "{e}");

    // No ground truth to calibrate along.
    std::fs::remove_file(seq.join("groundtruth_rect.txt")).unwrap();
    let e = fails(&run(base(&seq)));
    assert!(e.contains("absent") && e.contains("no ground truth"), "{e}");

    // A plan that is already int8.
    let int8 = t.path().join("int8-plan");
    std::fs::create_dir_all(&int8).unwrap();
    let m = std::fs::read_to_string(fp32.join("plan.json")).unwrap().replace("\"fp32\"", "\"int8\"");
    std::fs::write(int8.join("plan.json"), m).unwrap();
    let mut args = base(&shared("wakeboard7"));
    args[2] = s(&int8).into();
    let e = fails(&run(args));
    assert!(e.contains("already int8"), "{e}");

    // A plan whose recorded source is not where the manifest says (a relative name from
    // elsewhere, a moved checkpoint): named, with the way out.
    let moved = t.path().join("moved-plan");
    std::fs::create_dir_all(&moved).unwrap();
    let text = std::fs::read_to_string(fp32.join("plan.json")).unwrap();
    let m: serde_json::Value = serde_json::from_str(&text).unwrap();
    let was = m["weights"]["path"].as_str().unwrap();
    std::fs::write(moved.join("plan.json"), text.replace(was, "elsewhere/checkpoint.pth")).unwrap();
    let mut args = base(&shared("wakeboard7"));
    args[2] = s(&moved).into();
    let e = fails(&run(args));
    assert!(e.contains("`elsewhere/checkpoint.pth`, is not found from this directory") && e.contains("--model"), "{e}");

    // clap's own usage errors span lines; they still name the bad value.
    let o = prl(&["quantize", "--plan", s(&fp32), "--calib", s(&shared("wakeboard7")), "--method", "kmeans"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("`kmeans` is not a method"));
    assert!(!out.exists(), "a failed run wrote {}", out.display());
}
