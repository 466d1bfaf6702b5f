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
    // alone). 1,200 judged frames are held to 10%, which still catches a leak of 6 KB a frame
    // (a leaked frame buffer is 2.7 MB). The time is held to 2x (CI shares its cores): a
    // tracker whose frames slow as it runs still fails.
    let short = "--frames 2400 --every 100 --warm-up 1200 --rss-tolerance 0.10 --time-tolerance 1 --json";
    let short: Vec<&str> = short.split(' ').collect();
    let o = soak(&[&short[..], &[json.to_str().unwrap()]].concat());
    let out = common::ok(&o);
    assert!(out.contains("soak holds: memory within 10%, per-frame time within 100%"), "{out}");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(doc["holds"], true);
    let samples = doc["report"]["samples"].as_array().unwrap();
    assert_eq!(samples.len(), 24);
    assert_eq!(samples.last().unwrap()["frame"], 2400);
    assert_eq!(doc["report"]["warm"], 12);
    assert!(samples.iter().all(|s| s["rss_mb"].as_f64().unwrap() > 1.0
        && s["rss_held_mb"].as_f64().unwrap() > 1.0
        && s["fds"].as_u64().unwrap() >= 3));
    // A tolerance no run can meet fails, with a one-line error.
    let o = soak(&["--frames", "300", "--every", "20", "--rss-tolerance=-1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.trim().lines().count() == 1 && err.contains("soak failed"), "{err}");
}
