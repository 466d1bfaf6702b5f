//! `prl soak`: a long run of one plan over a looped sequence, checking that memory, open files
//! and the per-frame time stay flat (an unattended camera).

use std::path::PathBuf;

use clap::Args;
use prl_runtime::{set_threads, Plan, Tracker};
use prl_track::{init_box_from_groundtruth, soak, Sequence};

use super::write_atomically;

#[derive(Args)]
pub struct SoakArgs {
    /// Plan directory written by `prl compile` or `prl quantize`.
    #[arg(long, default_value = "models/prl-track/plan")]
    plan: PathBuf,
    /// OTB/UAV123-style sequence folder with ground truth (played forwards and backwards).
    #[arg(long, value_name = "DIR", default_value = "../shared/data/uav123_10fps/building4")]
    sequence: PathBuf,
    /// Frames to track in all.
    #[arg(long, default_value_t = 100_000)]
    frames: usize,
    /// Sample memory, descriptors and time every N frames.
    #[arg(long, value_name = "N", default_value_t = 1000)]
    every: usize,
    /// Frames of warm-up, not judged (default: a tenth of the run, at least 1,000).
    #[arg(long, value_name = "N")]
    warm_up: Option<usize>,
    /// Largest resident-memory growth after warm-up that passes (0.02: 2%).
    #[arg(long, default_value_t = 0.02)]
    rss_tolerance: f64,
    /// Largest drift of the per-frame time after warm-up that passes (0.25: the later half's
    /// median frame time at most 25% above the earlier half's).
    #[arg(long, default_value_t = 0.25)]
    time_tolerance: f64,
    /// Threads for the network.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Write the samples and the verdict here as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

pub fn run(a: SoakArgs) -> anyhow::Result<()> {
    set_threads(a.threads);
    let seq = Sequence::open(&a.sequence)?;
    let gt = seq.groundtruth().ok_or_else(|| anyhow::anyhow!("{}: no ground truth", a.sequence.display()))?;
    let plan = Plan::load(&a.plan)?;
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    println!("soak: {} on {} ({} frames, looped), {} frames", a.plan.display(), seq.name, seq.frames.len(), a.frames);
    println!("{:>9} {:>9} {:>9} {:>5} {:>10}", "frame", "RSS MB", "held MB", "fds", "median ms");
    let warm_up = a.warm_up.unwrap_or((a.frames / 10).max(1000));
    let init = init_box_from_groundtruth(gt[0]);
    // The binary's allocator is mimalloc (main.rs), which keeps freed pages for a second
    // before returning them: a sample would catch a varying part of a frame's transient buffers.
    // SAFETY: mi_collect takes no pointers and may be called at any time from any thread.
    let release_freed = || unsafe { libmimalloc_sys::mi_collect(true) };
    let report = soak::soak(&mut tracker, &seq.frames, init, a.frames, a.every, warm_up, release_freed, |s| {
        println!("{:>9} {:>9.1} {:>9.1} {:>5} {:>10.2}", s.frame, s.rss_mb, s.rss_held_mb, s.fds, s.median_ms)
    })?;
    let holds = report.holds(soak::SoakLimits { rss: a.rss_tolerance, time: a.time_tolerance });
    println!(
        "after warm-up ({} samples): resident memory {:.1}-{:.1} MB, growth {:+.2}% (later peak / earlier), \
         open descriptors {:+}, per-frame time drift {:+.1}% (later half's median / earlier), x{:.2} (last window / first)",
        report.warm,
        report.rss_range.0,
        report.rss_range.1,
        report.rss_growth * 100.0,
        report.fd_growth,
        report.time_drift * 100.0,
        report.time_ratio
    );
    if let Some(path) = &a.json {
        let doc = serde_json::json!({ "plan": a.plan, "sequence": a.sequence, "holds": holds, "report": report });
        write_atomically(path, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    }
    anyhow::ensure!(
        holds,
        "soak failed: resident memory grew {:.2}% (tolerance {:.2}%), per-frame time drifted {:+.1}% (tolerance {:.0}%), \
         open descriptors {:+}",
        report.rss_growth * 100.0,
        a.rss_tolerance * 100.0,
        report.time_drift * 100.0,
        a.time_tolerance * 100.0,
        report.fd_growth
    );
    println!(
        "soak holds: memory within {:.0}%, per-frame time within {:.0}%, no descriptor leaked",
        a.rss_tolerance * 100.0,
        a.time_tolerance * 100.0
    );
    Ok(())
}
