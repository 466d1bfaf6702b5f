//! `prl run-benchmark`: track every video of a dataset as the official `tools/test.py` does (OPE:
//! initialised from the first ground-truth box, one result line per frame, the init box first) and
//! write pysot-format results, several videos at a time, resumable and shardable.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use anyhow::Context;
use clap::Args;
use prl_runtime::{set_threads, Plan, Tracker};
use prl_track::tracking::{self, TrackRun};
use prl_track::{init_box_from_groundtruth, Dataset, Format, Video};

use super::{write_atomically, write_results};

#[derive(Args)]
pub struct RunBenchmarkArgs {
    /// Plan directory written by `prl compile`.
    #[arg(long, default_value = "models/prl-track/plan")]
    plan: PathBuf,
    /// Dataset folder.
    #[arg(long, value_name = "ROOT")]
    dataset: PathBuf,
    /// Dataset layout.
    #[arg(long, value_enum, default_value = "auto")]
    format: Format,
    /// Results go to `DIR/<dataset>/<tracker>/<video>.txt`.
    #[arg(long, value_name = "DIR", default_value = "results")]
    results: PathBuf,
    /// Tracker name for the results folder (default: `<model>-<precision>`, such as
    /// `prl-track-fp32` or `nanotrack-v2-int8`, with the variant when the plan is an ablation
    /// variant).
    #[arg(long)]
    tracker: Option<String>,
    /// Videos tracked at once, each with its own copy of the plan (default: one per core, which
    /// scales better than threads inside one video).
    #[arg(long)]
    jobs: Option<usize>,
    /// Threads per job for the network (default: the cores divided among the jobs).
    #[arg(long)]
    threads: Option<usize>,
    /// Track only shard K of N (1-based) of the sorted video list: `--shard 2/4`.
    #[arg(long, value_name = "K/N", value_parser = parse_shard)]
    shard: Option<(usize, usize)>,
    /// Skip videos whose result file is already complete.
    #[arg(long)]
    resume: bool,
    /// Track in the long-term mode (re-detection of a lost target; `prl track --long-term`).
    #[arg(long)]
    long_term: bool,
}

fn parse_shard(s: &str) -> Result<(usize, usize), String> {
    let bad = || format!("`{s}`: expected K/N with 1 <= K <= N, such as 2/4");
    let (k, n) = s.split_once('/').ok_or_else(bad)?;
    let (k, n): (usize, usize) = (k.trim().parse().map_err(|_| bad())?, n.trim().parse().map_err(|_| bad())?);
    if k == 0 || n == 0 || k > n {
        return Err(bad());
    }
    Ok((k, n))
}

/// True when `path` holds one result line per ground-truth frame of `v`.
fn complete(path: &Path, v: &Video) -> bool {
    prl_track::read_text_bounded(path, prl_track::box_file_limit(v.groundtruth.len()), "a result file")
        .map(|t| t.lines().filter(|l| !l.trim().is_empty()).count() == v.groundtruth.len())
        .unwrap_or(false)
}

/// Track one video.
fn track_video(tracker: &mut Tracker, v: &Video, progress: &indicatif::ProgressBar) -> anyhow::Result<TrackRun> {
    let n = v.groundtruth.len();
    anyhow::ensure!(v.frames.len() >= n, "video {}: {} frames for {} ground-truth boxes", v.name, v.frames.len(), n);
    let init = init_box_from_groundtruth(v.init);
    let run = tracking::track(tracker, &v.frames[..n], init, |_, _, _| {
        progress.inc(1);
        Ok(())
    })?;
    Ok(run)
}

pub fn run(a: RunBenchmarkArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.jobs != Some(0), "--jobs must be at least 1");
    let dataset = Dataset::open(&a.dataset, a.format)?;
    // The plan's manifest, read before anything is written: a bad plan leaves no folder behind.
    let manifest = super::read_plan_manifest(&a.plan)?;
    let tracker_name = match (&a.tracker, &manifest.variant) {
        (Some(t), _) => t.clone(),
        (None, Some(v)) => format!("{}-{}-{v}", manifest.model, manifest.precision),
        (None, None) => format!("{}-{}", manifest.model, manifest.precision),
    };
    let out = a.results.join(&dataset.name).join(&tracker_name);
    std::fs::create_dir_all(&out).with_context(|| format!("{}: cannot create", out.display()))?;
    let (k, n) = a.shard.unwrap_or((1, 1));
    let mine: Vec<&Video> = dataset.videos.iter().enumerate().filter(|(i, _)| i % n == k - 1).map(|(_, v)| v).collect();
    let todo: Vec<&Video> =
        mine.iter().copied().filter(|v| !(a.resume && complete(&out.join(format!("{}.txt", v.name)), v))).collect();
    println!(
        "{}: {} videos, shard {k}/{n}: {} to track ({} already complete) -> {}",
        dataset.name,
        dataset.videos.len(),
        todo.len(),
        mine.len() - todo.len(),
        out.display()
    );
    if todo.is_empty() {
        return Ok(());
    }
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let jobs = a.jobs.unwrap_or(cores).min(todo.len());
    let per_job = a.threads.unwrap_or((cores / jobs).max(1));
    set_threads(per_job);
    let frames: usize = todo.iter().map(|v| v.groundtruth.len()).sum();
    let progress = indicatif::ProgressBar::new(frames as u64);
    progress.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta} {msg}")
            .expect("static template"),
    );
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let first_error: Mutex<Option<anyhow::Error>> = Mutex::new(None);
    let fps: Mutex<Vec<(String, f64)>> = Mutex::new(vec![]);
    std::thread::scope(|s| {
        for _ in 0..jobs {
            s.spawn(|| {
                let work = || -> anyhow::Result<()> {
                    let plan = Plan::load(&a.plan)?;
                    let config = plan.manifest().tracker.clone();
                    let mut tracker = Tracker::new(plan, config);
                    tracker.set_long_term(a.long_term);
                    tracker.set_region_threads(per_job);
                    while !failed.load(Ordering::Relaxed) {
                        let Some(v) = todo.get(next.fetch_add(1, Ordering::Relaxed)) else { break };
                        let run = track_video(&mut tracker, v, &progress)?;
                        write_results(&out.join(format!("{}.txt", v.name)), &run)?;
                        // The seconds each frame's tracking took (frame decoding excluded).
                        let times: Vec<f64> = run.timings.iter().map(|t| t.tracking().as_secs_f64()).collect();
                        let t: String = times.iter().map(|t| format!("{t:.6}\n")).collect();
                        write_atomically(&out.join(format!("{}_time.txt", v.name)), t.as_bytes())?;
                        let rate = times.len() as f64 / times.iter().sum::<f64>();
                        progress.set_message(format!("{} {rate:.1} FPS", v.name));
                        fps.lock().expect("no panic holds it").push((v.name.clone(), rate));
                    }
                    Ok(())
                };
                if let Err(e) = work() {
                    failed.store(true, Ordering::Relaxed);
                    first_error.lock().expect("no panic holds it").get_or_insert(e);
                }
            });
        }
    });
    progress.finish_and_clear();
    if let Some(e) = first_error.into_inner().expect("threads joined") {
        return Err(e);
    }
    let mut fps = fps.into_inner().expect("threads joined");
    fps.sort_by(|x, y| x.0.cmp(&y.0));
    for (name, rate) in &fps {
        println!("  {name:<28} {rate:>6.1} FPS (tracking, frame decoding excluded)");
    }
    println!(
        "results: {} (per-frame seconds in <video>_time.txt, confidences in <video>_confidence.value)",
        out.display()
    );
    Ok(())
}
