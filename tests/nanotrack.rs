//! NanoTrack v2 through the toolchain: import of the shipped ONNX files, the official tracker
//! loop's boxes on real footage, and import errors.

mod common;

use std::path::Path;
use std::process::Command;

use prl_runtime::{Family, Plan, TargetState, Tracker};
use prl_track::occlusion::LostAndFound;
use prl_track::{init_box_from_groundtruth, tracking, Sequence};

fn read_boxes(path: &Path) -> Vec<[f64; 4]> {
    prl_track::parse_boxes(path, 10_000).unwrap()
}

#[test]
fn shipped_files_are_the_shared_model() {
    use sha2::{Digest, Sha256};
    let shared = common::golden_dir().join("../../models/nanotrack-v2");
    for f in ["nanotrack_backbone_sim.onnx", "nanotrack_head_sim.onnx", "configv2.yaml", "LICENSE"] {
        let a = Sha256::digest(std::fs::read(common::nanotrack_dir().join(f)).unwrap());
        let b = Sha256::digest(std::fs::read(shared.join(f)).unwrap());
        assert_eq!(a, b, "{f}");
    }
}

#[test]
fn fp32_plan_reproduces_the_official_tracker_on_building4() {
    let tmp = tempfile::tempdir().unwrap();
    let plan_dir = common::nanotrack_plan(tmp.path());
    let plan = Plan::load(&plan_dir).unwrap();
    let m = plan.manifest();
    assert_eq!((m.tracker.family, m.model.as_str()), (Family::Nanotrack, "nanotrack-v2"));
    assert_eq!(m.tracker, prl_runtime::TrackerConfig::nanotrack());
    let names: Vec<&str> = m.search.outputs.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, ["cls", "loc"]);
    let config = m.tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    let seq = Sequence::open(&common::sequence("building4")).unwrap();
    let gt = seq.groundtruth().cloned().unwrap();
    let run = tracking::track(&mut tracker, seq.frames.as_slice(), init_box_from_groundtruth(gt[0]), |_, _, _| Ok(()))
        .unwrap();
    let reference = read_boxes(&common::nanotrack_ref_dir().join("building4.txt"));
    assert_eq!(run.boxes.len(), reference.len());
    let ours = run.xywh();
    let within =
        ours.iter().zip(&reference).filter(|(a, b)| a.iter().zip(*b).all(|(x, y)| (x - y).abs() <= 0.5)).count();
    let worst = ours
        .iter()
        .zip(&reference)
        .map(|(a, b)| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max))
        .fold(0.0, f64::max);
    eprintln!("building4: {within}/{} frames within 0.5 px, worst {worst:.4} px", reference.len());
    assert!(within as f64 >= 0.99 * reference.len() as f64, "{within} of {} frames within 0.5 px", reference.len());
    // A trained tracker really tracks: most frames overlap the ground truth, and its state says
    // so (all 263 frames `tracking` when measured).
    let miou = run.mean_iou(&gt).unwrap();
    assert!(miou > 0.5, "mean IoU with the ground truth {miou}");
    let tracking = run.states.iter().filter(|&&s| s == TargetState::Tracking).count();
    assert!(tracking as f64 >= 0.97 * run.states.len() as f64, "{tracking} of {} frames tracking", run.states.len());
}

#[test]
fn the_state_tells_a_hidden_target_from_a_tracked_one() {
    // wakeboard10 made lost-and-found: the target hidden on frames 40..70 while the view pans
    // 240 px, so the short-term tracker stays on background afterwards (IoU 0).
    let tmp = tempfile::tempdir().unwrap();
    let plan_dir = common::nanotrack_plan(tmp.path());
    let spec = LostAndFound { hide_from: 40, hide_frames: 30, pan: (240, 0), view: (960, 540) };
    let dir = tmp.path().join("wakeboard10-lf");
    assert_eq!(spec.make(&common::sequence("wakeboard10"), &dir).unwrap(), 157);
    let seq = Sequence::open(&dir).unwrap();
    let gt = seq.groundtruth().cloned().unwrap();
    assert!(gt[40..70].iter().all(|b| b[0].is_nan()) && gt[39][0].is_finite() && gt[70][0].is_finite());
    let plan = Plan::load(&plan_dir).unwrap();
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    let run = tracking::track(&mut tracker, seq.frames.as_slice(), init_box_from_groundtruth(gt[0]), |_, _, _| Ok(()))
        .unwrap();
    let count = |r: std::ops::Range<usize>, s: TargetState| run.states[r].iter().filter(|&&x| x == s).count();
    // Measured: frames 1..40 all tracking, 40..157 all lost.
    assert!(count(1..40, TargetState::Tracking) >= 37, "{:?}", &run.states[1..40]);
    assert!(count(40..70, TargetState::Lost) >= 27, "hidden: {:?}", &run.confidences[40..70]);
    assert!(count(70..157, TargetState::Tracking) <= 5, "off target, yet: {:?}", &run.states[70..157]);
    // The best score alone would not tell: NanoTrack's stays high on the hidden frames.
    let mut hidden: Vec<f64> = run.scores[40..70].to_vec();
    hidden.sort_by(f64::total_cmp);
    assert!(hidden[15] > 0.7, "median best score on hidden frames {}", hidden[15]);
}

#[test]
fn the_long_term_mode_finds_a_target_the_short_term_tracker_loses() {
    // wakeboard10 made lost-and-found: hidden on frames 30..50 while the view pans by -80,30,
    // so the target comes back about 90 px from where it went (docs/lost-target.md, `wb10p80`).
    let tmp = tempfile::tempdir().unwrap();
    let plan_dir = common::nanotrack_plan(tmp.path());
    let spec = LostAndFound { hide_from: 30, hide_frames: 20, pan: (-80, 30), view: (960, 540) };
    let dir = tmp.path().join("wakeboard10-lf");
    spec.make(&common::sequence("wakeboard10"), &dir).unwrap();
    let seq = Sequence::open(&dir).unwrap();
    let gt = seq.groundtruth().cloned().unwrap();
    let init = init_box_from_groundtruth(gt[0]);
    let plan = Plan::load(&plan_dir).unwrap();
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    let short = tracking::track(&mut tracker, seq.frames.as_slice(), init, |_, _, _| Ok(())).unwrap();
    tracker.set_long_term(true);
    let long = tracking::track(&mut tracker, seq.frames.as_slice(), init, |_, _, _| Ok(())).unwrap();
    // Frames after the target is back (50..) on which a run's box overlaps it (IoU > 0.3).
    let found =
        |run: &tracking::TrackRun| (50..gt.len()).filter(|&i| prl_track::iou(run.xywh()[i], gt[i]) > 0.3).count();
    let (short_found, long_found) = (found(&short), found(&long));
    // Measured: short-term 8 of 107 frames (it stays on background until it drifts back at the
    // end), long-term 107 of 107.
    assert!(short_found <= 20, "the short-term tracker found it on {short_found} of {} frames", gt.len() - 50);
    assert!(long_found >= 95, "the long-term mode found it on {long_found} of {} frames", gt.len() - 50);
    // Before the cover both modes are the same tracker, to the bit.
    assert_eq!(short.boxes[..30], long.boxes[..30]);
    // While the target is hidden the long-term mode says so, and keeps its box.
    let lost = long.states[30..50].iter().filter(|&&s| s == TargetState::Lost).count();
    assert!(lost >= 18, "{:?}", &long.states[30..50]);
    // The region's crops searched on two threads: the same run.
    tracker.set_region_threads(2);
    let spread = tracking::track(&mut tracker, seq.frames.as_slice(), init, |_, _, _| Ok(())).unwrap();
    assert_eq!((spread.boxes, spread.states), (long.boxes, long.states));
}

#[test]
fn several_targets_give_each_the_boxes_of_a_single_target_run() {
    // Three targets on wakeboard7 (the annotated one and two boxes of background), spread over
    // two threads, the third in the long-term mode: each one's run equals its own single run.
    let tmp = tempfile::tempdir().unwrap();
    let plan = Plan::load(common::nanotrack_plan(tmp.path())).unwrap();
    let seq = Sequence::open(&common::sequence("wakeboard7")).unwrap();
    let frames = &seq.frames[..25];
    let inits = [
        init_box_from_groundtruth(seq.groundtruth().unwrap()[0]),
        prl_runtime::BBox { x: 200.0, y: 300.0, w: 60.0, h: 40.0 },
        prl_runtime::BBox { x: 1000.0, y: 100.0, w: 30.0, h: 50.0 },
    ];
    let config = plan.manifest().tracker.clone();
    let tracker = |k: usize| {
        let mut t = Tracker::new(plan.clone(), config.clone());
        t.set_long_term(k == 2);
        t
    };
    let mut trackers: Vec<Tracker> = (0..3).map(tracker).collect();
    let mut seen = 0;
    let runs =
        tracking::track_targets(&mut trackers, 2, tracking::in_order(frames), &inits, frames.len(), |_, _, p| {
            seen += usize::from(p.len() == 3);
            Ok(())
        })
        .unwrap();
    assert_eq!((runs.len(), seen), (3, frames.len()));
    for (k, run) in runs.iter().enumerate() {
        let single = tracking::track(&mut tracker(k), frames, inits[k], |_, _, _| Ok(())).unwrap();
        assert_eq!(run.boxes, single.boxes, "target {}", k + 1);
        assert_eq!((&run.scores, &run.states), (&single.scores, &single.states), "target {}", k + 1);
    }
    // A refused box names its target.
    let bad = [inits[0], prl_runtime::BBox { x: 5000.0, y: 0.0, w: 10.0, h: 10.0 }];
    let e = tracking::track_targets(&mut trackers[..2], 2, tracking::in_order(frames), &bad, 0, |_, _, _| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("(target 2)") && e.contains("outside"), "{e}");
}

/// A NanoTrack plan whose search graph's `graph.nnef` is `edit`ed, with a manifest whose digest
/// matches it (as a crafted plan would carry); `Plan::load`'s one-line error naming the file.
fn load_with_edited_graph(edit: impl Fn(&str) -> String) -> String {
    use sha2::{Digest, Sha256};
    let tmp = tempfile::tempdir().unwrap();
    let dir = common::nanotrack_plan(tmp.path());
    let manifest_path = dir.join("plan.json");
    let mut manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(&manifest_path).unwrap()).unwrap();
    let search = dir.join(manifest["search"]["file"].as_str().unwrap());
    let mut archive = tar::Archive::new(std::fs::File::open(&search).unwrap());
    let mut out = tar::Builder::new(Vec::new());
    let mut edited = false;
    for entry in archive.entries().unwrap() {
        let mut entry = entry.unwrap();
        let mut bytes = vec![];
        std::io::Read::read_to_end(&mut entry, &mut bytes).unwrap();
        let mut header = entry.header().clone();
        if entry.path().unwrap().to_str() == Some("graph.nnef") {
            bytes = edit(&String::from_utf8(bytes).unwrap()).into_bytes();
            header.set_size(bytes.len() as u64);
            header.set_cksum();
            edited = true;
        }
        out.append(&header, &bytes[..]).unwrap();
    }
    assert!(edited);
    let bytes = out.into_inner().unwrap();
    std::fs::write(&search, &bytes).unwrap();
    let digest: String = Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect();
    manifest["search"]["sha256"] = digest.into();
    std::fs::write(&manifest_path, serde_json::to_vec(&manifest).unwrap()).unwrap();
    let e = Plan::load(&dir).err().expect("refused").to_string();
    assert!(!e.contains('\n') && e.contains(&search.display().to_string()), "{e}");
    e
}

#[test]
fn a_malformed_graph_archive_is_an_error_not_a_panic() {
    // Fuzzing found tract-nnef panicking (an out-of-range slice) on a reshape whose axis_start
    // lies past the input's rank.
    load_with_edited_graph(|text| {
        let at = text.find("axis_start = 2").expect("a reshape in the search graph");
        format!("{}axis_start = 9{}", &text[..at], &text[at + 14..])
    });
}

#[test]
fn a_graph_nested_too_deep_to_parse_is_refused_before_parsing() {
    // Fuzzing found a plan on which tract-nnef's parser ran for ever: its work doubles with
    // each level of nesting, and the graph had a hundred open brackets. Closed or left open,
    // brackets or signs: refused at once, before tract-nnef sees it.
    for deep in ["[".repeat(100), format!("{}1.0{}", "[".repeat(100), "]".repeat(100)), "- ".repeat(100)] {
        let e = load_with_edited_graph(|text| {
            let at = text.find("= external").expect("an input");
            format!("{}= {deep}{}", &text[..at], &text[at + 1..])
        });
        assert!(e.contains("levels deep"), "{e}");
    }
}

fn import_err(backbone: &Path, head: &Path, config: Option<&Path>) -> String {
    let e = prl_compiler::import_nanotrack(backbone, head, config).unwrap_err().to_string();
    assert!(!e.contains('\n'), "one line: {e}");
    e
}

#[test]
fn import_errors_name_the_file_and_the_problem() {
    let n = common::nanotrack_dir();
    let (backbone, head) = (n.join("nanotrack_backbone_sim.onnx"), n.join("nanotrack_head_sim.onnx"));
    // The head where the backbone should be.
    let e = import_err(&head, &head, None);
    assert!(e.starts_with(&head.display().to_string()) && e.contains("is it the head?"), "{e}");
    // The backbone where the head should be.
    let e = import_err(&backbone, &backbone, None);
    assert!(e.contains("expected 2 and 2") && e.contains("is it the backbone?"), "{e}");
    // A truncated file.
    let tmp = tempfile::tempdir().unwrap();
    let cut = tmp.path().join("cut.onnx");
    let bytes = std::fs::read(&backbone).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let e = import_err(&cut, &head, None);
    assert!(e.starts_with(&cut.display().to_string()) && e.contains("not an ONNX model"), "{e}");
    // A graph output no node makes (fuzzing found tract-onnx panicking on it): one line.
    let orphan = tmp.path().join("orphan.onnx");
    let mut bytes = std::fs::read(&head).unwrap();
    let at = bytes.windows(7).rposition(|w| w == b"output1").unwrap();
    bytes[at + 5] = b'X';
    std::fs::write(&orphan, &bytes).unwrap();
    let e = import_err(&backbone, &orphan, None);
    assert!(e.starts_with(&orphan.display().to_string()) && e.contains("made by no node"), "{e}");
    // Two inputs of one name (fuzzing found the importer panicking on it): one line.
    let twice = tmp.path().join("twice.onnx");
    let mut bytes = std::fs::read(&head).unwrap();
    while let Some(at) = bytes.windows(6).position(|w| w == b"input1") {
        bytes[at + 5] = b'2';
    }
    std::fs::write(&twice, &bytes).unwrap();
    let e = import_err(&backbone, &twice, None);
    assert!(e.starts_with(&twice.display().to_string()) && e.contains("`input2` is made twice"), "{e}");
    // NaN weights (8 bytes of 0xff in the middle of the backbone's weights hold at least one
    // whole NaN float): refused, naming the weight.
    let nan = tmp.path().join("nan.onnx");
    let mut bytes = std::fs::read(&backbone).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid..mid + 8].fill(0xff);
    std::fs::write(&nan, &bytes).unwrap();
    let e = import_err(&nan, &head, None);
    assert!(e.starts_with(&nan.display().to_string()) && e.contains("NaN values"), "{e}");
    // A convolution of stride 0 (fuzzing found tract dividing by zero in its shape inference, a
    // panic): one line on standard error, exit 1, nothing written, no panic message.
    let stride0 = tmp.path().join("stride0.onnx");
    let mut bytes = std::fs::read(&backbone).unwrap();
    let at = bytes.windows(7).position(|w| w == b"strides").unwrap() + 7;
    let ints = bytes[at..at + 16].windows(4).position(|w| w == [0x40, 2, 0x40, 2]).expect("strides 2, 2") + at;
    bytes[ints + 1] = 0;
    bytes[ints + 3] = 0;
    std::fs::write(&stride0, &bytes).unwrap();
    let e = import_err(&stride0, &head, None);
    assert!(e.starts_with(&stride0.display().to_string()) && e.contains("malformed"), "{e}");
    let out = tmp.path().join("stride0-model");
    let (b, h, o) = (stride0.to_str().unwrap(), head.to_str().unwrap(), out.to_str().unwrap());
    let run = common::prl(&["import", "nanotrack", "--backbone", b, "--head", h, "--out", o]);
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "{err}");
    assert!(err.trim().lines().count() == 1 && !err.contains("panicked") && !out.exists(), "{err}");
    // Not a file at all.
    let e = import_err(&tmp.path().join("absent.onnx"), &head, None);
    assert!(e.contains("absent.onnx"), "{e}");
    // A config whose score map disagrees with the model's output.
    let cfg = tmp.path().join("config.yaml");
    let yaml = std::fs::read_to_string(n.join("configv2.yaml"))
        .unwrap()
        .replace("CONTEXT_AMOUNT: 0.5", "CONTEXT_AMOUNT: 0.5\n    OUTPUT_SIZE: 25");
    std::fs::write(&cfg, yaml).unwrap();
    let e = import_err(&backbone, &head, Some(&cfg));
    assert!(e.starts_with(&cfg.display().to_string()) && e.contains("25x25") && e.contains("16x16"), "{e}");
    // A config whose search crop the head cannot take (its correlation is tied to 16x16).
    let yaml =
        std::fs::read_to_string(n.join("configv2.yaml")).unwrap().replace("INSTANCE_SIZE: 255", "INSTANCE_SIZE: 287");
    std::fs::write(&cfg, yaml).unwrap();
    let e = import_err(&backbone, &head, Some(&cfg));
    assert!(e.starts_with(&cfg.display().to_string()) && e.contains("287x287") && e.contains("[1, 48, 18, 18]"), "{e}");
}

#[test]
fn cli_imports_compiles_and_tracks() {
    let tmp = tempfile::tempdir().unwrap();
    let (model, plan) = (tmp.path().join("model"), tmp.path().join("plan"));
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let out = common::ok(&common::prl(&["import", "nanotrack", "--out", &s(&model)]));
    assert!(out.contains("cls [1, 2, 16, 16], loc [1, 4, 16, 16]"), "{out}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(model.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["tracker"]["family"], "nanotrack");
    assert_eq!(manifest["weights"]["kind"], "onnx");
    assert_eq!(manifest["weights"]["files"].as_array().unwrap().len(), 2);
    common::ok(&common::prl(&["compile", "--model", &s(&model), "--out", &s(&plan)]));
    let json = tmp.path().join("summary.json");
    let seq = common::sequence("wakeboard7");
    let out = common::ok(&common::prl(&[
        "track",
        "--plan",
        &s(&plan),
        "--sequence",
        &s(&seq),
        "--max-frames",
        "20",
        "--json",
        &s(&json),
    ]));
    assert!(out.contains("mean IoU"), "{out}");
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(summary["frames"], 20);
    assert!(summary["peak_rss_mb"].as_f64().unwrap() > 10.0);
    // PRL-Track settings on a NanoTrack model are refused.
    let o = common::prl(&[
        "compile",
        "--model",
        &s(&model),
        "--tracker",
        "models/prl-track/tracker.toml",
        "--out",
        &s(&plan),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("the model is a nanotrack"));
    // The Winograd choice is recorded in the plan (absent when off); an unknown one is refused.
    let plan_json = |dir: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(dir.join("plan.json")).unwrap()).unwrap()
    };
    assert!(plan_json(&plan).get("winograd").is_none());
    let fast = tmp.path().join("plan-winograd");
    let out = common::ok(&common::prl(&["compile", "--model", &s(&model), "--winograd", "all", "--out", &s(&fast)]));
    assert!(out.contains("fp32, Winograd all"), "{out}");
    assert_eq!(plan_json(&fast)["winograd"], "all");
    let o = common::prl(&["compile", "--model", &s(&model), "--winograd", "5x5", "--out", &s(&fast)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("`5x5` is not one of off, 3x3, all"), "{err}");
    // Settings files with NaN (TOML has it), a zero stride, or no such file: one line each,
    // naming the file, and no plan written.
    let own = std::fs::read_to_string(common::nanotrack_dir().join("tracker.toml")).unwrap();
    let fresh = tmp.path().join("never-written");
    for (edit, says) in [
        (own.replace("penalty_k = 0.15", "penalty_k = nan"), "must be finite numbers"),
        (own.replace("stride = 16", "stride = 0"), "between 1 and 4096"),
        (String::new(), "No such file"),
    ] {
        let toml = tmp.path().join("bad-tracker.toml");
        let _ = std::fs::remove_file(&toml);
        if !edit.is_empty() {
            std::fs::write(&toml, &edit).unwrap();
        }
        let o = common::prl(&["compile", "--model", &s(&model), "--tracker", &s(&toml), "--out", &s(&fresh)]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.trim().lines().count() == 1, "{err}");
        assert!(err.contains("bad-tracker.toml") && err.contains(says), "{err}");
        assert!(!fresh.exists());
    }
}

/// A plan's recorded inputs and outputs (`prl bench --save-tensors`) replay to the same outputs
/// (`prl verify --plan --tensors`, what a camera runs on a plan compiled elsewhere), and a
/// recording that does not fit the plan is a one-line error naming the file.
#[test]
fn recorded_tensors_replay_and_bad_recordings_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = common::nanotrack_plan(tmp.path());
    let rec = tmp.path().join("rec");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let seq = common::sequence("building4");
    common::ok(&common::prl(&[
        "bench",
        "--plan",
        &s(&plan),
        "--runs",
        "1",
        "--top",
        "0",
        "--sequence",
        &s(&seq),
        "--save-tensors",
        &s(&rec),
    ]));
    let index: serde_json::Value = serde_json::from_slice(&std::fs::read(rec.join("tensors.json")).unwrap()).unwrap();
    assert_eq!(index["cls"], serde_json::json!([1, 2, 16, 16]));
    let out = common::ok(&common::prl(&["verify", "--plan", &s(&plan), "--tensors", &s(&rec)]));
    assert_eq!(out.lines().filter(|l| l.trim_end().ends_with(" ok")).count(), 3, "{out}");
    // The library gives the numbers: the same plan on the same machine is exact.
    let p = prl_runtime::Plan::load(&plan).unwrap();
    let m = prl_runtime::replay(&rec, &p).unwrap();
    assert!(m.iter().all(|t| t.rel == 0.0 && t.max_abs == 0.0), "{m:?}");
    // A changed output fails the check; a truncated one and a wrong shape are errors.
    let cls = rec.join("cls.f32");
    let mut bytes = std::fs::read(&cls).unwrap();
    bytes[0..4].copy_from_slice(&7.5f32.to_le_bytes());
    std::fs::write(&cls, &bytes).unwrap();
    let o = common::prl(&["verify", "--plan", &s(&plan), "--tensors", &s(&rec)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("cls exceed the tolerance"), "{err}");
    std::fs::write(&cls, &bytes[..100]).unwrap();
    let o = common::prl(&["verify", "--plan", &s(&plan), "--tensors", &s(&rec)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("cls.f32: 100 bytes"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    let text = std::fs::read_to_string(rec.join("tensors.json")).unwrap();
    std::fs::write(rec.join("tensors.json"), text.replacen("16", "15", 1)).unwrap(); // cls [1, 2, 15, 16]
    let o = common::prl(&["verify", "--plan", &s(&plan), "--tensors", &s(&rec)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("tensors.json") && err.contains("the plan's is"), "{err}");
}

/// Bounds on the int8 plan's relative error against fp32 on held-out wakeboard7 crops, when
/// calibrated on 16 building4 frames with `--budget 4` (the README's plan, on 128 frames with
/// `--budget 6`, measured cls 0.014 and loc 0.024 on 64 crops of wakeboard7 and wakeboard10;
/// with `--budget 4`, 0.016 and 0.030).
const MAX_CLS: f64 = 0.08;
const MAX_LOC: f64 = 0.08;

#[test]
fn int8_plan_runs_integer_kernels_near_fp32_on_held_out_footage() {
    let tmp = tempfile::tempdir().unwrap();
    let fp32 = common::nanotrack_plan(tmp.path());
    let int8 = tmp.path().join("int8");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let b4 = common::sequence("building4");
    // Thresholds that leave no layer int8 are an error, not a plan with no integer layer.
    let o = common::prl(&[
        "quantize",
        "--plan",
        &s(&fp32),
        "--calib",
        &s(&b4),
        "--frames-per-seq",
        "4",
        "--min-out-channels",
        "4096",
        "--out",
        &s(&int8),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("no layer would be int8"), "{err}");
    assert!(!int8.exists(), "nothing written");
    let args = [
        "--min-macs",
        "1000000",
        "--min-out-channels",
        "16",
        "--budget",
        "4",
        "--frames-per-seq",
        "16",
        "--method",
        "minmax",
    ];
    let (fp32s, b4s, int8s) = (s(&fp32), s(&b4), s(&int8));
    let mut q = vec!["quantize", "--plan", &fp32s, "--calib", &b4s, "--out", &int8s];
    q.extend(args);
    let out = common::ok(&common::prl(&q));
    assert!(out.contains("sensitivity cls/loc"), "{out}");
    let plan = Plan::load(&int8).unwrap();
    let qi = plan.manifest().quantization.as_ref().unwrap();
    let n8 = qi.layers.iter().filter(|l| l.decision == prl_runtime::LayerDecision::Int8).count();
    assert!(n8 >= 15, "{n8} int8 layers");
    // A HardSwish alone reads the stem's output and the expanding layers' of blocks 4-8: their u8
    // ranges start at -3 (the stem reaches about -95), the lowest code standing for -3 or less.
    let stem = qi.layers.iter().find(|l| l.node.ends_with("features.0.0/Conv")).unwrap();
    assert_eq!(stem.output_range.0, -3.0, "{stem:?}");
    let floored: Vec<f32> = qi
        .layers
        .iter()
        .filter(|l| l.decision == prl_runtime::LayerDecision::Int8 && l.output_range.0 == -3.0)
        .filter_map(|l| qi.ranges.iter().find(|(v, _)| v.starts_with(l.node.as_str())).map(|(_, r)| r.0))
        .collect();
    assert!(floored.len() >= 3 && floored.iter().all(|&lo| lo <= -3.0 && lo > -3.5), "{floored:?}");
    let kernels = common::int8_kernel_nodes(&plan);
    assert!(kernels.len() >= 10, "{kernels:?}");
    assert!(kernels.iter().any(|k| k.starts_with("head_")), "the head's pointwise convs: {kernels:?}");
    // The depthwise layers after integer ones read their bytes (the dequantisation in them).
    let reading = plan.search_nodes().into_iter().filter(|n| n.op == "DepthwiseConv" && n.info.contains("u8 input"));
    assert!(
        reading.count() >= 6,
        "{:?}",
        plan.search_nodes().iter().filter(|n| n.op == "DepthwiseConv").collect::<Vec<_>>()
    );
    assert!(common::int8_kernel_nodes(&Plan::load(&fp32).unwrap()).is_empty());
    // Held-out fidelity and tracking, through prl compare.
    let json = tmp.path().join("compare.json");
    let w7 = s(&common::sequence("wakeboard7"));
    let j = s(&json);
    common::ok(&common::prl(&[
        "compare",
        "--plan",
        &fp32s,
        "--plan",
        &int8s,
        "--sequence",
        &w7,
        "--crops-per-seq",
        "16",
        "--runs",
        "3",
        "--max-frames",
        "30",
        "--threads",
        "2",
        "--json",
        &j,
    ]));
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let errors = r["fidelity"][0]["errors"].as_array().unwrap();
    let (cls, loc) = (errors[0][1].as_f64().unwrap(), errors[1][1].as_f64().unwrap());
    eprintln!("held-out relative error: cls {cls:.4} loc {loc:.4}");
    assert_eq!((errors[0][0].as_str(), errors[1][0].as_str()), (Some("cls"), Some("loc")));
    assert!(cls < MAX_CLS && loc < MAX_LOC && loc > 0.0, "cls {cls} loc {loc}");
    let tracks = &r["sequences"][0]["plans"];
    assert!(tracks[1]["mean_iou_to_ref"].as_f64().unwrap() > 0.7, "{tracks}");
    assert!(r["plans"][1]["peak_rss_mb"].as_f64().is_some(), "peak memory from the child's JSON");
}

/// `--depthwise` makes the depthwise layers integer too: each runs as the runtime's
/// `DepthwiseQConv` where the machine has a path for it, and the plan's outputs are those of
/// tract's own integer kernels to the last bit (recorded with `PRL_OPS=tract-int8`, replayed at
/// tolerance 0).
#[test]
fn depthwise_layers_quantised_give_tract_s_outputs() {
    let tmp = tempfile::tempdir().unwrap();
    let fp32 = common::nanotrack_plan(tmp.path());
    let int8 = tmp.path().join("int8-dw");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (fp32s, b4s, int8s) = (s(&fp32), s(&common::sequence("building4")), s(&int8));
    common::ok(&common::prl(&[
        "quantize",
        "--plan",
        &fp32s,
        "--calib",
        &b4s,
        "--frames-per-seq",
        "8",
        "--min-macs",
        "1000000",
        "--min-out-channels",
        "16",
        "--depthwise",
        "--out",
        &int8s,
    ]));
    let plan = Plan::load(&int8).unwrap();
    let qi = plan.manifest().quantization.as_ref().unwrap();
    let dw = qi.layers.iter().filter(|l| l.op == "dwconv" && l.decision == prl_runtime::LayerDecision::Int8).count();
    assert_eq!(dw, 20, "NanoTrack's twenty depthwise layers: {:?}", qi.layers);
    assert!(qi.layers.iter().filter(|l| l.op == "dwconv").all(|l| l.per_channel), "per-channel weights");
    let made = plan.search_nodes().into_iter().filter(|n| n.op == "DepthwiseQConv").count();
    assert_eq!(made, 20, "every depthwise layer a DepthwiseQConv");
    drop(plan);
    // Record tract's outputs (its own integer kernels), replay with the runtime's operators.
    // This plan (calibrated in the test, with PRL_ISA=generic in CI) is the one where a sum of
    // block 2's depthwise layer lands on a half and tract's per-channel scale (a product with
    // the reciprocal, for 16 channels and more) must be matched to the last bit.
    let rec = tmp.path().join("tract-int8");
    let o = Command::new(env!("CARGO_BIN_EXE_prl"))
        .args(["bench", "--plan", &int8s, "--runs", "1", "--save-tensors", &s(&rec)])
        .env("PRL_OPS", "tract-int8")
        .output()
        .unwrap();
    common::ok(&o);
    let o = common::prl(&["verify", "--plan", &int8s, "--tensors", &s(&rec), "--tolerance", "0"]);
    let out = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    eprintln!("the --depthwise plan against tract's int8 outputs:\n{out}");
    assert!(o.status.success() && out.contains("cls") && out.contains("loc"), "{out}");
}

#[test]
fn a_backbone_and_a_whole_search_graph_import_to_the_same_model() {
    use prl_compiler::{FamilyImport, OnnxFile, Parts};
    let n = common::nanotrack_dir();
    let backbone = OnnxFile::read(&n.join("nanotrack_backbone_sim.onnx")).unwrap();
    let split = prl_compiler::import_nanotrack(&backbone.path, &n.join("nanotrack_head_sim.onnx"), None).unwrap();
    // The joined search graph, given as a whole (as a model published that way would be).
    let tmp = tempfile::tempdir().unwrap();
    let search = tmp.path().join("search.onnx");
    std::fs::write(&search, &split.search).unwrap();
    let family =
        FamilyImport { model: "nanotrack-v2".into(), tracker: prl_runtime::TrackerConfig::nanotrack(), config: None };
    let parts = Parts::BackboneSearch { backbone, search: OnnxFile::read(&search).unwrap() };
    let whole = prl_compiler::import::import(&parts, &family).unwrap();
    assert_eq!(whole.manifest.search.inputs, split.manifest.search.inputs);
    assert_eq!(whole.manifest.search.outputs, split.manifest.search.outputs);
    assert_eq!(whole.template, split.template);
    // Both search graphs compute the same function.
    let x = prl_compiler::Tensor::new(vec![1, 3, 255, 255], (0..3 * 255 * 255).map(|i| (i % 251) as f32).collect());
    let z = prl_compiler::Tensor::new(vec![1, 3, 127, 127], (0..3 * 127 * 127).map(|i| (i % 241) as f32).collect());
    let t = prl_compiler::OnnxRunner::new(&split.template, "template", &split.manifest.template.inputs, None).unwrap();
    let zf = t.run(&[&z]).unwrap();
    let run = |m: &prl_compiler::BuiltModel| {
        let s = prl_compiler::OnnxRunner::new(&m.search, "search", &m.manifest.search.inputs, None).unwrap();
        s.run(&[&x, &zf[0]]).unwrap()
    };
    let (a, b) = (run(&split), run(&whole));
    for (a, b) in a.iter().zip(&b) {
        assert_eq!(a.data, b.data);
    }
}

#[test]
fn demo_tracks_the_generated_video_with_the_trained_model() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let text = common::ok(&common::prl(&["demo", "--frames", "30", "--threads", "1", "--out", out.to_str().unwrap()]));
    assert!(text.contains("NanoTrack v2, trained weights"), "{text}");
    let miou: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("mean IoU with the ground truth: "))
        .expect("the demo prints its mean IoU")
        .trim()
        .parse()
        .unwrap();
    assert!(miou > 0.6, "a trained tracker follows the generated target: mean IoU {miou}");
    let results = std::fs::read_to_string(out.join("results.txt")).unwrap();
    assert_eq!(results.lines().count(), 30);
    // Weights options belong to PRL-Track: a clear error, nothing tracked.
    let o = common::prl(&["demo", "--family", "nanotrack", "--random-seed", "1", "--out", out.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--family prl-track"));
}

#[test]
fn graphs_with_no_layer_worth_splitting_run_on_one_thread() {
    // NanoTrack's largest layer has 7 M multiply-adds (under Plan's 2^24); PRL-Track's have
    // hundreds of millions and keep the thread setting.
    let tmp = tempfile::tempdir().unwrap();
    let nano = Plan::load(common::nanotrack_plan(tmp.path())).unwrap();
    assert_eq!(nano.single_threaded(), (true, true));
    let prl = Plan::load(common::reference_plan()).unwrap();
    assert_eq!(prl.single_threaded(), (false, false));
}
