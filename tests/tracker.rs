//! The runtime against the official tracker: exact crops, the same boxes and scores frame by
//! frame on the three reference sequences, and the plan against the golden tensors.

mod common;

use prl_compiler::{net, read_golden, NetworkRunner, Weights};
use prl_runtime::{get_subwindow, Frame, Plan, Tracker};
use prl_track::{init_box_from_groundtruth, load_frame, Sequence};

struct Trace {
    boxes: Vec<[f64; 4]>,
    scores: Vec<Option<f64>>,
}

fn trace(name: &str) -> Trace {
    let text = std::fs::read_to_string(common::golden_dir().join(format!("trace_{name}.json"))).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let boxes =
        v["boxes"].as_array().unwrap().iter().map(|b| std::array::from_fn(|i| b[i].as_f64().unwrap())).collect();
    let scores = v["scores"].as_array().unwrap().iter().map(|s| s.as_f64()).collect();
    Trace { boxes, scores }
}

/// The official uint8 NCHW crops of a trace, as interleaved BGR like `get_subwindow` returns.
fn official_crop(name: &str, key: &str) -> Vec<u8> {
    let bytes = std::fs::read(common::golden_dir().join(format!("trace_{name}_crops.safetensors"))).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let t = st.tensor(key).unwrap();
    let (side, data) = (t.shape()[3], t.data());
    let plane = side * side;
    (0..plane).flat_map(|i| [data[i], data[plane + i], data[2 * plane + i]]).collect()
}

fn context(size: (f64, f64)) -> f64 {
    let ctx = 0.5 * (size.0 + size.1);
    ((size.0 + ctx) * (size.1 + ctx)).sqrt()
}

fn check_sequence(name: &str) {
    let seq = Sequence::open(&common::golden_dir().join(format!("seq_{name}"))).unwrap();
    let t = trace(name);
    assert_eq!(seq.frames.len(), t.boxes.len());
    let frames: Vec<Frame> = seq.frames.iter().map(|p| load_frame(p).unwrap()).collect();
    let init = init_box_from_groundtruth(seq.groundtruth().unwrap()[0]);
    assert_eq!([init.x, init.y, init.w, init.h], t.boxes[0], "{name}: init box as tools/test.py gives it");

    // Crops, exactly: z on frame 1, x on frames 2 and 3 from the official states.
    let avg = frames[0].channel_mean();
    let center = |b: [f64; 4]| (b[0] + (b[2] - 1.0) / 2.0, b[1] + (b[3] - 1.0) / 2.0);
    let s_z = context((init.w, init.h)).round_ties_even();
    assert_eq!(
        get_subwindow(&frames[0], center(t.boxes[0]), 127, s_z as usize, avg),
        official_crop(name, "z_crop"),
        "{name}: z crop"
    );
    let after = |b: [f64; 4]| (b[0] + b[2] / 2.0, b[1] + b[3] / 2.0);
    for (k, (c, size)) in [(center(t.boxes[0]), (init.w, init.h)), (after(t.boxes[1]), (t.boxes[1][2], t.boxes[1][3]))]
        .into_iter()
        .enumerate()
    {
        let mut s_z = context(size);
        if size.0 * size.1 > 0.5 * (frames[0].width() * frames[0].height()) as f64 {
            s_z = context((init.w, init.h)).round_ties_even();
        }
        let s_x = (s_z * 287.0 / 127.0).round_ties_even() as usize;
        let ours = get_subwindow(&frames[k + 1], c, 287, s_x, avg);
        assert!(ours == official_crop(name, &format!("x_crop{}", k + 1)), "{name}: x crop {}", k + 1);
    }

    // The tracker, frame by frame. Under emulation (scripts/aarch64.sh) a frame takes seconds:
    // `PRL_TRACE_FRAMES` bounds the frames checked, `PRL_TEST_THREADS` the network's threads.
    let limit = std::env::var("PRL_TRACE_FRAMES").ok().map(|v| v.parse::<usize>().expect("PRL_TRACE_FRAMES: a count"));
    if let Some(n) = limit.filter(|&n| n < frames.len()) {
        eprintln!("NOTE: {name}: only the first {n} of {} frames are checked (PRL_TRACE_FRAMES)", frames.len());
    }
    if let Some(n) = std::env::var("PRL_TEST_THREADS").ok().and_then(|v| v.parse::<usize>().ok()) {
        prl_runtime::set_threads(n);
    }
    let plan = Plan::load(common::reference_plan()).unwrap();
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    tracker.init(&frames[0], init).unwrap();
    for (i, f) in frames.iter().enumerate().skip(1).take(limit.unwrap_or(frames.len()).saturating_sub(1)) {
        let p = tracker.track(f).unwrap();
        let ours = [p.bbox.x, p.bbox.y, p.bbox.w, p.bbox.h];
        for k in 0..4 {
            assert!(
                (ours[k] - t.boxes[i][k]).abs() <= 0.05,
                "{name} frame {}: box {ours:?}, official {:?}",
                i + 1,
                t.boxes[i]
            );
        }
        let official = t.scores[i].unwrap();
        assert!((p.score - official).abs() <= 1e-3, "{name} frame {}: score {}, official {official}", i + 1, p.score);
    }
}

#[test]
fn drift_sequence_matches_the_official_tracker() {
    check_sequence("drift");
}

#[test]
fn large_target_sequence_matches_the_official_tracker() {
    check_sequence("large");
}

#[test]
fn border_sequence_matches_the_official_tracker() {
    check_sequence("border");
}

#[test]
fn plan_reproduces_the_golden_heads_and_the_onnx_graphs() {
    let dir = common::golden_dir();
    let golden = read_golden(&dir.join("golden.safetensors")).unwrap();
    let plan = Plan::load(common::reference_plan()).unwrap();
    // The five correlations, the stride-1 convolutions, the pools and HMG's norms, softmaxes
    // and linear layers run as the runtime's own operators.
    let nodes = plan.search_nodes();
    let named = |op: &str| -> Vec<String> { nodes.iter().filter(|n| n.op == op).map(|n| n.name.clone()).collect() };
    let mut xcorr = named("DepthwiseXCorr");
    xcorr.sort();
    assert_eq!(xcorr, ["s1_conv", "s2_conv", "s3_conv", "s4_conv", "s5_conv"]);
    // (Layers 3 and 4 are `WinogradConv` where `PRL_WINOGRAD` asks for it.)
    let mut convs = named("PackedConv");
    convs.extend(named("WinogradConv"));
    for layer in ["layer1", "layer2", "layer3", "layer4"] {
        assert!(convs.iter().any(|n| n.contains(layer)), "{layer} in {convs:?}");
    }
    assert_eq!(named("ChannelMaxPool").len(), 2, "the backbone's max pools");
    assert_eq!(named("LayerNormCore").len(), 4, "HMG's layer norms");
    assert_eq!(named("Attention").len(), 6, "HMG's attentions (scores, scale, softmax, mix)");
    let linear = named("ConstMatMul");
    for layer in ["blocks_0_attn_qkv", "blocks_0_mlp_fc1", "blocks_1_attn_qkv", "blocks_1_mlp_fc1", "patch_embed1"] {
        assert!(linear.iter().any(|n| n.contains(layer)), "{layer} in {linear:?}");
    }
    let zf = plan.template(&golden["z"].data).unwrap();
    let out = plan.search(&golden["x"].data, &zf).unwrap();
    for (name, ours) in ["loc", "cls1", "cls2"].into_iter().zip(&out.outputs) {
        let (rel, _) = prl_compiler::relative_error(ours, &golden[name].data);
        assert!(rel <= 1e-4, "{name}: relative error {rel:e}");
    }
    // Same function as the ONNX graphs run directly.
    let weights =
        Weights::from_checkpoint(prl_compiler::checkpoint::Checkpoint::load(dir.join("checkpoint.pth")).unwrap());
    let network = net::build_network(&weights).unwrap();
    let runner = NetworkRunner::new(&network, None).unwrap();
    let onnx = runner.search(&golden["x"], &runner.template(&golden["z"]).unwrap()).unwrap();
    for (ours, reference) in out.outputs.iter().zip(&onnx) {
        let (rel, _) = prl_compiler::relative_error(ours, &reference.data);
        assert!(rel <= 1e-6, "plan vs ONNX: relative error {rel:e}");
    }
}

/// The reference plan's files copied into a fresh folder, to be damaged.
fn copy_of_reference_plan() -> tempfile::TempDir {
    let (src, dir) = (common::reference_plan(), tempfile::tempdir().unwrap());
    for f in ["plan.json", "template.nnef.tar", "search.nnef.tar"] {
        std::fs::copy(src.join(f), dir.path().join(f)).unwrap();
    }
    dir
}

#[test]
fn corrupt_or_mismatched_plans_are_refused() {
    let dir = copy_of_reference_plan();
    let mut bytes = std::fs::read(dir.path().join("search.nnef.tar")).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    std::fs::write(dir.path().join("search.nnef.tar"), &bytes).unwrap();
    let err = Plan::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("search.nnef.tar") && err.contains("sha256"), "{err}");
    let mut manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("plan.json")).unwrap()).unwrap();
    manifest["optimizer_knobs"] = serde_json::json!({"TRACT_NO_SUCH_KNOB": "1"});
    std::fs::write(dir.path().join("plan.json"), serde_json::to_vec(&manifest).unwrap()).unwrap();
    let err = Plan::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("plan.json") && err.contains("optimizer_knobs"), "{err}");
    std::fs::write(dir.path().join("plan.json"), b"{\"format_version\": 99}").unwrap();
    let err = Plan::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("plan.json"), "{err}");
    std::fs::remove_file(dir.path().join("plan.json")).unwrap();
    assert!(Plan::load(dir.path()).is_err());
}

/// A plan whose tracker settings disagree with its graphs' shapes (an edited `plan.json`, its
/// hashes still right) is refused when loaded, naming the file and both shapes: the tracker
/// indexes the score map by the settings.
#[test]
fn plans_whose_settings_and_graphs_disagree_are_refused() {
    let (src, dir) = (common::reference_plan(), copy_of_reference_plan());
    let original: serde_json::Value = serde_json::from_slice(&std::fs::read(src.join("plan.json")).unwrap()).unwrap();
    let refused = |edit: &dyn Fn(&mut serde_json::Value)| {
        let mut m = original.clone();
        edit(&mut m);
        std::fs::write(dir.path().join("plan.json"), serde_json::to_vec(&m).unwrap()).unwrap();
        Plan::load(dir.path()).err().expect("refused").to_string()
    };
    let n = original["tracker"]["score_size"].as_u64().unwrap();
    let err = refused(&|m| m["tracker"]["score_size"] = (n + 1).into());
    assert!(err.contains("plan.json") && err.contains(&format!("{0}x{0} score map", n + 1)), "{err}");
    let err = refused(&|m| m["tracker"]["instance_size"] = 256.into());
    assert!(err.contains("plan.json") && err.contains("search crops of 256x256"), "{err}");
    let err = refused(&|m| m["tracker"]["stride"] = 0.into());
    assert!(err.contains("between 1 and 4096"), "{err}");
    // Settings and manifest shapes edited alike: the graph itself disagrees.
    let err = refused(&|m| {
        m["tracker"]["score_size"] = (n + 1).into();
        for o in m["search"]["outputs"].as_array_mut().unwrap() {
            let c = o["shape"][1].clone();
            o["shape"] = serde_json::json!([1, c, n + 1, n + 1]);
        }
    });
    assert!(
        err.contains("search.nnef.tar") && err.contains("in the graph") && err.contains("in the manifest"),
        "{err}"
    );
    std::fs::write(dir.path().join("plan.json"), serde_json::to_vec(&original).unwrap()).unwrap();
    Plan::load(dir.path()).expect("the untouched plan loads");
}

#[test]
fn search_profile_covers_every_node_slowest_first() {
    let plan = Plan::load(common::reference_plan()).unwrap();
    let golden = read_golden(&common::golden_dir().join("golden.safetensors")).unwrap();
    let zf = plan.template(&golden["z"].data).unwrap();
    let prof = plan.profile_search(&golden["x"].data, &zf, 1).unwrap();
    assert!(prof.len() > 100, "{} nodes", prof.len());
    assert!(prof.windows(2).all(|w| w[0].time >= w[1].time));
    assert!(prof.iter().any(|n| n.name.starts_with("s1")), "the s1 correlation is profiled");
}
