//! OPE metrics against hand-computed cases and against pysot-toolkit's formulas evaluated with
//! numpy on the shared sequences' ground truth (values pinned below).

use std::path::{Path, PathBuf};

use prl_track::ope::{evaluate, overlap_ratio, success_thresholds, summarise};
use prl_track::parse_boxes;

const SEQS: &str = "../shared/data/uav123_10fps";

fn gt_of(name: &str) -> Vec<[f64; 4]> {
    parse_boxes(&Path::new(env!("CARGO_MANIFEST_DIR")).join(SEQS).join(name).join("groundtruth_rect.txt"), 10_000)
        .unwrap()
}

/// The synthetic result the pinned values were computed from: offsets cycling with the frame
/// index, and a NaN row every 25 frames.
pub fn synthetic(gt: &[[f64; 4]]) -> Vec<[f64; 4]> {
    gt.iter()
        .enumerate()
        .map(|(i, g)| {
            if i % 25 == 13 {
                return [f64::NAN; 4];
            }
            let d = [
                (i % 7) as f64 * 3.0 - 9.0,
                (i % 5) as f64 * 4.0 - 8.0,
                (i % 3) as f64 * 6.0 - 4.0,
                -((i % 4) as f64) * 3.0,
            ];
            [g[0] + d[0], g[1] + d[1], g[2] + d[2], g[3] + d[3]]
        })
        .collect()
}

#[test]
fn perfect_tracking() {
    let gt = vec![[10.0, 20.0, 30.0, 40.0]; 5];
    let c = evaluate(&gt, &gt).unwrap();
    // IoU 1 passes every threshold but 1.0 (strict >): 20 of 21.
    assert_eq!(c.success.iter().filter(|&&s| s == 1.0).count(), 20);
    assert_eq!(c.success[20], 0.0);
    assert!((c.auc() - 20.0 / 21.0).abs() < 1e-15);
    assert!(c.precision.iter().all(|&p| p == 1.0));
    assert!(c.norm_precision.iter().all(|&p| p == 1.0));
}

#[test]
fn constant_offset_and_threshold_edges() {
    // 20 px to the right of a 100x100 box: IoU 80*100/(2*10000-8000) = 2/3, distance exactly 20.
    let gt = vec![[100.0, 100.0, 100.0, 100.0]; 4];
    let res = vec![[120.0, 100.0, 100.0, 100.0]; 4];
    let c = evaluate(&gt, &res).unwrap();
    assert!((overlap_ratio(gt[0], res[0]) - 2.0 / 3.0).abs() < 1e-15);
    let expect: Vec<f64> = success_thresholds().iter().map(|&t| if 2.0 / 3.0 > t { 1.0 } else { 0.0 }).collect();
    assert_eq!(c.success, expect);
    assert_eq!(c.precision[19], 0.0, "19 px < 20 px");
    assert_eq!(c.precision[20], 1.0, "dist <= 20 counts at 20");
    // IoU exactly 0.5 counts below 0.5 and not at 0.5 (strict).
    let half = [[0.0, 0.0, 10.0, 10.0]];
    let res = [[0.0, 0.0, 10.0, 5.0]];
    let c = evaluate(&half, &res).unwrap();
    assert_eq!(overlap_ratio(half[0], res[0]), 0.5);
    assert_eq!(c.success[9], 1.0);
    assert_eq!(c.success[10], 0.0);
}

#[test]
fn lost_target_nan_rows_and_zero_sizes() {
    let gt = vec![[10.0, 10.0, 20.0, 20.0], [f64::NAN; 4], [10.0, 10.0, 0.0, 20.0], [10.0, 10.0, 20.0, 20.0]];
    let res = vec![[500.0, 500.0, 20.0, 20.0], [10.0, 10.0, 20.0, 20.0], [10.0, 10.0, 0.0, 20.0], [f64::NAN; 4]];
    let c = evaluate(&gt, &res).unwrap();
    // Frame 0 lost (IoU 0 is not > 0), frame 1 NaN ground truth and frame 2 zero width: IoU -1,
    // frame 3 NaN result: a miss. Success is 0 everywhere.
    assert!(c.success.iter().all(|&s| s == 0.0), "{:?}", c.success);
    // Precision: frame 1's NaN centre counts as a hit (pysot's quirk), frame 2 (centre 9.5,19.5,
    // same as the result) is a hit, frame 0 is far, frame 3 NaN is a miss: 2 of 4 from 0 px.
    assert_eq!(c.precision[0], 0.5);
    assert_eq!(c.precision[50], 0.5);
    // Fewer result lines than ground-truth frames is an error.
    assert!(evaluate(&gt, &res[..3]).is_err());
}

#[test]
fn shared_sequences_match_pysot_formulas_evaluated_with_numpy() {
    // (video, success AUC, precision@20, normalised precision@0.2) from pysot-toolkit's
    // success_overlap / success_error run with numpy on the same boxes.
    let pinned = [
        ("building4", 0.6539923954372624, 0.9619771863117871, 0.7604562737642585),
        ("wakeboard10", 0.30755232029117385, 0.9617834394904459, 0.19745222929936307),
        ("wakeboard7", 0.49893390191897663, 0.9552238805970149, 0.417910447761194),
    ];
    let mut all = vec![];
    for (name, auc, p20, n20) in pinned {
        let gt = gt_of(name);
        let c = evaluate(&gt, &synthetic(&gt)).unwrap();
        assert!((c.auc() - auc).abs() < 1e-12, "{name}: {} vs {auc}", c.auc());
        assert_eq!(c.precision_at_20(), p20, "{name}");
        assert_eq!(c.norm_precision_at_02(), n20, "{name}");
        all.push(c);
    }
    let s = summarise(&all);
    assert!((s.auc - 0.486826205882471).abs() < 1e-12, "{}", s.auc);
    assert!((s.precision_at_20 - 0.9596615021330827).abs() < 1e-12);
    assert!((s.norm_precision_at_02 - 0.4586063169416052).abs() < 1e-12);
}

/// Results of two trackers for the shared sequences: the ground truth itself and the synthetic one.
pub fn write_results(dir: &Path) -> PathBuf {
    for name in ["building4", "wakeboard10", "wakeboard7"] {
        let gt = gt_of(name);
        for (tracker, boxes) in [("perfect", gt.clone()), ("synthetic", synthetic(&gt))] {
            let d = dir.join(tracker);
            std::fs::create_dir_all(&d).unwrap();
            let text: String = boxes.iter().map(|b| format!("{},{},{},{}\n", b[0], b[1], b[2], b[3])).collect();
            std::fs::write(d.join(format!("{name}.txt")), text).unwrap();
        }
    }
    dir.to_path_buf()
}

#[test]
fn prl_eval_prints_the_pysot_table_and_json() {
    let tmp = tempfile::tempdir().unwrap();
    let results = write_results(&tmp.path().join("results"));
    let json = tmp.path().join("eval.json");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_prl"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["eval", "--dataset", SEQS, "--results", results.to_str().unwrap(), "--per-video", "--json"])
        .arg(&json)
        .arg("--plots")
        .arg(tmp.path().join("plots"))
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("|   perfect    |  0.952  |     1.000      |   1.000   |"), "{out}");
    assert!(out.contains("|  synthetic   |  0.487  |     0.459      |   0.960   |"), "{out}");
    let perfect = out.find("perfect").unwrap();
    assert!(perfect < out.find("synthetic").unwrap(), "sorted by success");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let synth = &report["trackers"][1];
    assert_eq!(synth["name"], "synthetic");
    assert!((synth["success"].as_f64().unwrap() - 0.486826205882471).abs() < 1e-12);
    assert_eq!(synth["success_curve"].as_array().unwrap().len(), 21);
    for kind in ["success", "precision", "norm_precision"] {
        let svg = std::fs::read_to_string(tmp.path().join(format!("plots/uav123_10fps_{kind}.svg"))).unwrap();
        assert!(svg.contains("perfect [") && svg.contains("synthetic ["), "{kind}: labelled curves");
        let png = image::open(tmp.path().join(format!("plots/uav123_10fps_{kind}.png"))).unwrap();
        assert_eq!((png.width(), png.height()), (640, 480));
    }
    let svg = std::fs::read_to_string(tmp.path().join("plots/uav123_10fps_success.svg")).unwrap();
    assert!(svg.contains("synthetic [0.487]"), "AUC in the legend");

    // A result with a missing line is refused, naming the file.
    let short = results.join("synthetic/wakeboard7.txt");
    let text = std::fs::read_to_string(&short).unwrap();
    std::fs::write(&short, text.lines().skip(1).map(|l| format!("{l}\n")).collect::<String>()).unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_prl"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["eval", "--dataset", SEQS, "--results", results.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("wakeboard7.txt") && err.contains("ground-truth frames"), "{err}");
}

#[test]
fn attributes_give_their_own_tables_and_plots() {
    // A pysot JSON over the shared sequences' ground truth, with attributes.
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("UAVX");
    std::fs::create_dir_all(&root).unwrap();
    let mut doc = serde_json::Map::new();
    for (name, attrs) in [
        ("building4", vec!["Scale Variation"]),
        ("wakeboard10", vec!["Scale Variation", "Partial Occlusion"]),
        ("wakeboard7", vec![]),
    ] {
        let gt = gt_of(name);
        let imgs: Vec<String> = (1..=gt.len()).map(|i| format!("{name}/img/{i:06}.jpg")).collect();
        let rects: Vec<Vec<f64>> = gt.iter().map(|b| b.to_vec()).collect();
        doc.insert(name.into(), serde_json::json!({"video_dir": name, "init_rect": rects[0], "img_names": imgs, "gt_rect": rects, "attr": attrs}));
    }
    std::fs::write(root.join("UAVX.json"), serde_json::to_vec(&doc).unwrap()).unwrap();
    let results = write_results(&tmp.path().join("results").join("UAVX"));
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_prl"))
        .args(["eval", "--dataset", root.to_str().unwrap(), "--results", results.parent().unwrap().to_str().unwrap()])
        .args(["--attributes", "--plots"])
        .arg(tmp.path().join("plots"))
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("Scale Variation (2 videos)") && out.contains("Partial Occlusion (1 videos)"), "{out}");
    // Partial Occlusion is wakeboard10 alone: its figures are that video's.
    let c = evaluate(&gt_of("wakeboard10"), &synthetic(&gt_of("wakeboard10"))).unwrap();
    let row = format!(
        "|{:^14}|{:^9.3}|{:^16.3}|{:^11.3}|",
        "synthetic",
        c.auc(),
        c.norm_precision_at_02(),
        c.precision_at_20()
    );
    let po = &out[out.find("Partial Occlusion").unwrap()..];
    assert!(po.contains(&row), "{row}\n{po}");
    for f in ["UAVX_success_partial_occlusion.svg", "UAVX_precision_scale_variation.png", "UAVX_success.png"] {
        assert!(tmp.path().join("plots").join(f).is_file(), "{f}");
    }
}
