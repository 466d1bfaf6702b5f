//! `prl run-benchmark` then `prl eval` end to end on the shared UAV123@10fps sequences (their
//! first frames, to keep CI short), with `--shard`, `--jobs` and `--resume`.

mod common;

use common::{ok, prl};

use std::path::Path;

const FRAMES: usize = 5;

/// An OTB-style copy of the shared sequences cut to their first `FRAMES` frames.
fn short_dataset(root: &Path) {
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/uav123_10fps");
    for name in ["building4", "wakeboard10", "wakeboard7"] {
        let src = shared.join(name);
        std::fs::create_dir_all(root.join(name).join("img")).unwrap();
        for i in 1..=FRAMES {
            let f = format!("img/{i:06}.jpg");
            std::fs::copy(src.join(&f), root.join(name).join(&f)).unwrap();
        }
        let gt = std::fs::read_to_string(src.join("groundtruth_rect.txt")).unwrap();
        let gt: String = gt.lines().take(FRAMES).map(|l| format!("{l}\n")).collect();
        std::fs::write(root.join(name).join("groundtruth_rect.txt"), gt).unwrap();
    }
}

#[test]
fn shards_merge_resume_skips_and_eval_scores() {
    let plan = common::reference_plan();
    let t = tempfile::tempdir().unwrap();
    let data = t.path().join("UAV10");
    short_dataset(&data);
    let results = t.path().join("results");
    let run = |extra: &[&str]| {
        let mut args = vec!["run-benchmark", "--plan", plan.to_str().unwrap(), "--dataset", data.to_str().unwrap()];
        args.extend_from_slice(&["--results", results.to_str().unwrap(), "--tracker", "prl"]);
        args.extend_from_slice(extra);
        prl(&args)
    };
    // Two shards, as two machines would run them; their folders simply merge.
    let s1 = ok(&run(&["--shard", "1/2"]));
    assert!(s1.contains("shard 1/2: 2 to track"), "{s1}");
    let s2 = ok(&run(&["--shard", "2/2", "--jobs", "2"]));
    assert!(s2.contains("shard 2/2: 1 to track"), "{s2}");
    let dir = results.join("UAV10/prl");
    for name in ["building4", "wakeboard10", "wakeboard7"] {
        let text = std::fs::read_to_string(dir.join(format!("{name}.txt"))).unwrap();
        assert_eq!(text.lines().count(), FRAMES, "{name}");
        assert_eq!(std::fs::read_to_string(dir.join(format!("{name}_time.txt"))).unwrap().lines().count(), FRAMES);
    }
    // The first line is the official init box [cx-(w-1)/2, cy-(h-1)/2, w, h] of 811,368,75,43.
    let first = std::fs::read_to_string(dir.join("building4.txt")).unwrap();
    assert!(first.starts_with("811.5,368.5,75,43\n"), "{first}");

    // --resume: nothing left; a truncated result is tracked again.
    let r = ok(&run(&["--resume", "--jobs", "2"]));
    assert!(r.contains("0 to track (3 already complete)"), "{r}");
    let wb7 = dir.join("wakeboard7.txt");
    std::fs::write(&wb7, "1,2,3,4\n").unwrap();
    let r = ok(&run(&["--resume"]));
    assert!(r.contains("1 to track (2 already complete)"), "{r}");
    assert_eq!(std::fs::read_to_string(&wb7).unwrap().lines().count(), FRAMES);

    // eval reads DIR/<dataset>/<tracker>/.
    let e = ok(&prl(&["eval", "--dataset", data.to_str().unwrap(), "--results", results.to_str().unwrap()]));
    assert!(e.contains("UAV10: 3 videos, 1 tracker(s)") && e.contains("|     prl      |"), "{e}");

    // Without --tracker the folder is named after the plan: prl-track-<precision>.
    let fresh = t.path().join("fresh");
    let o = prl(&[
        "run-benchmark",
        "--plan",
        plan.to_str().unwrap(),
        "--dataset",
        data.to_str().unwrap(),
        "--results",
        fresh.to_str().unwrap(),
        "--shard",
        "1/3",
    ]);
    let out = ok(&o);
    assert!(fresh.join("UAV10/prl-track-fp32/building4.txt").is_file(), "{out}");

    // Bad arguments are one-line errors.
    let o = run(&["--shard", "3/2"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("K/N"));
}
