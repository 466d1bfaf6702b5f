//! `prl soak` as CI runs it (short): the trained NanoTrack plan over building4 looped; memory,
//! descriptors and time are sampled and the verdict printed. The full 100,000-frame runs of the
//! fp32 and int8 plans are `scripts/soak.sh` (docs/robustness.md has the figures).

mod common;

#[test]
fn a_short_soak_holds_and_reports_every_sample() {
    let dir = tempfile::tempdir().unwrap();
    let plan = common::nanotrack_plan(dir.path());
    let json = dir.path().join("soak.json");
    let seq = common::sequence("building4");
    let (plan, seq) = (plan.to_str().unwrap(), seq.to_str().unwrap());
    let soak = |more: &[&str]| {
        let mut args = vec!["soak", "--plan", plan, "--sequence", seq];
        args.extend(more);
        common::prl(&args)
    };
    // Memory is read after mimalloc has returned the pages it keeps after a free (it returns
    // them a second later on its own; before `prl soak` asked it to, CI saw 2.15% from that
    // alone). What is left is a step now and then, not a slope: the allocator keeping a frame
    // buffer's pages (2.7 MB, 5% of the process) when a small block pins them; CI once saw two
    // such steps (10.5%) inside 1,200 judged frames with no leak (a 20,000-frame run here stays
    // at 46.2 MB from frame 2,500 on). So the run is long enough that a leak outgrows the steps:
    // 8,000 judged frames, halves 4,000 frames apart, held to 15% (8 MB, three frame buffers);
    // a leak of 6 KB a frame fails it (tried: 29%).
    // The time is held to 2x (CI shares its cores): a tracker whose frames slow as it runs
    // still fails.
    let short = "--frames 10000 --every 200 --warm-up 2000 --rss-tolerance 0.15 --time-tolerance 1 --json";
    let short: Vec<&str> = short.split(' ').collect();
    let o = soak(&[&short[..], &[json.to_str().unwrap()]].concat());
    let out = common::ok(&o);
    assert!(out.contains("soak holds: memory within 15%, per-frame time within 100%"), "{out}");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(doc["holds"], true);
    let samples = doc["report"]["samples"].as_array().unwrap();
    assert_eq!(samples.len(), 50);
    assert_eq!(samples.last().unwrap()["frame"], 10000);
    assert_eq!(doc["report"]["warm"], 10);
    assert!(samples.iter().all(|s| s["rss_mb"].as_f64().unwrap() > 1.0
        && s["rss_held_mb"].as_f64().unwrap() > 1.0
        && s["fds"].as_u64().unwrap() >= 3));
    // A tolerance no run can meet fails, with a one-line error.
    let o = soak(&["--frames", "300", "--every", "20", "--rss-tolerance=-1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.trim().lines().count() == 1 && err.contains("soak failed"), "{err}");
}
