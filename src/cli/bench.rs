//! `prl bench`: where the time of a tracking step goes on this machine, stage by stage and
//! operator by operator.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use clap::Args;
use prl_runtime::{set_threads, BBox, Frame, Plan, Threads, Tracker};
use prl_track::{init_box_from_groundtruth, load_frame, tracking, Sequence};
use serde::Serialize;

use super::write_atomically;

/// The real frame benchmarked by default (1280x720 JPEG, beside the repository).
const DEFAULT_SEQUENCE: &str = "../shared/data/uav123_10fps/building4";

#[derive(Args)]
pub struct BenchArgs {
    /// Plan directory written by `prl compile`.
    #[arg(long, default_value = "models/prl-track/plan")]
    plan: PathBuf,
    /// Threads for the network (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Timed runs per stage.
    #[arg(long, default_value_t = 20)]
    runs: usize,
    /// Timed runs of the template network, if not --runs (`scripts/orin-estimate.sh` counts
    /// instructions of runs that differ in tracking steps only).
    #[arg(long, value_name = "N")]
    template_runs: Option<usize>,
    /// Untimed runs of each stage before its timed ones: at least one, and until this many
    /// seconds have passed (an idle core, a virtual one above all, takes some tens of
    /// milliseconds to come up to speed; 0: one run, for instruction counts).
    #[arg(long, value_name = "SECONDS", default_value_t = 0.25)]
    warm_up: f64,
    /// A sequence folder whose first frame and box are used (default: UAV123 building4 if
    /// present, else a generated 1280x720 frame).
    #[arg(long, value_name = "DIR")]
    sequence: Option<PathBuf>,
    /// How many of the slowest operators to list.
    #[arg(long, default_value_t = 12)]
    top: usize,
    /// Also write the report as JSON (with every timed sample).
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Write the networks' inputs and outputs on the benchmarked frame to DIR (raw little-endian
    /// f32 files and `tensors.json` with their shapes), so another runtime can be timed on
    /// exactly the same data (see `benches/peers/`).
    #[arg(long, value_name = "DIR")]
    save_tensors: Option<PathBuf>,
    /// Also time the tracking step of N targets at once (one plan, the targets spread over the
    /// threads) against one target's step on all the threads, interleaved in one run.
    #[arg(long, value_name = "N", default_value_t = 1)]
    targets: usize,
}

/// The step of `n` targets against one target's, interleaved (`prl bench --targets`).
#[derive(Serialize)]
struct Targets {
    targets: usize,
    jobs: usize,
    one_target: Stat,
    all_targets: Stat,
    ratio: f64,
}

/// Time `runs` steps of one target on `threads` threads against `n` targets spread over them.
fn time_targets(
    plan: &Plan,
    frame: &Frame,
    init: BBox,
    n: usize,
    threads: usize,
    runs: usize,
) -> anyhow::Result<Targets> {
    let config = plan.manifest().tracker.clone();
    let mut one = Tracker::new(plan.clone(), config.clone());
    let mut many: Vec<Tracker> = (0..n).map(|_| Tracker::new(plan.clone(), config.clone())).collect();
    let jobs = threads.min(n);
    // Several targets: `jobs` threads of `threads / jobs` each; one target: all of them.
    set_threads((threads / jobs).max(1));
    let all = Threads::new(threads);
    all.run(|| one.init(frame, init))?;
    for t in &mut many {
        t.init(frame, init)?;
    }
    let (mut single, mut several) = (vec![], vec![]);
    for i in 0..runs + 1 {
        let t = Instant::now();
        all.run(|| one.track(frame))?;
        let t1 = Instant::now();
        tracking::step_targets(&mut many, jobs, frame).map_err(|(k, e)| anyhow::anyhow!("target {}: {e}", k + 1))?;
        if i > 0 {
            single.push(t1 - t);
            several.push(t1.elapsed());
        }
    }
    set_threads(threads);
    let (one_target, all_targets) = (stat("one target", &single), stat("all targets", &several));
    let ratio = all_targets.median_ms / one_target.median_ms;
    Ok(Targets { targets: n, jobs, one_target, all_targets, ratio })
}

#[derive(Serialize)]
struct Stat {
    stage: &'static str,
    median_ms: f64,
    p90_ms: f64,
    samples_ms: Vec<f64>,
}

#[derive(Serialize)]
struct Op {
    name: String,
    op: String,
    ms: f64,
    share: f64,
    gflops: f64,
    /// The kernel it runs (the runtime's path, or tract's matrix kernel).
    kernel: String,
}

/// The `top` slowest of a profile, with their share of it and their rate.
fn slowest(prof: &[prl_runtime::NodeTime], top: usize) -> Vec<Op> {
    let total: f64 = prof.iter().map(|n| n.time.as_secs_f64()).sum();
    prof.iter()
        .take(top)
        .map(|n| {
            let secs = n.time.as_secs_f64();
            Op {
                name: n.name.clone(),
                op: n.op.clone(),
                ms: secs * 1e3,
                share: secs / total,
                gflops: if secs > 0.0 && n.flop > 0.0 { n.flop / secs / 1e9 } else { 0.0 },
                kernel: n.kernel.clone(),
            }
        })
        .collect()
}

/// Print a profile's slowest operators under `title`.
fn print_ops(title: &str, ops: &[Op]) {
    let total = ops.first().map_or(0.0, |o| if o.share > 0.0 { o.ms / o.share } else { 0.0 });
    println!("\nslowest operators of the {title} (tract profile, {total:.1} ms in all):");
    println!("{:>9} {:>6} {:>8}  {:<16} {:<24} node", "ms", "share", "GFLOP/s", "op", "kernel");
    for o in ops {
        let gflops = if o.gflops > 0.0 { format!("{:.1}", o.gflops) } else { "-".into() };
        let kernel = if o.kernel.is_empty() { "-" } else { &o.kernel };
        println!("{:>9.2} {:>5.1}% {:>8}  {:<16} {:<24} {}", o.ms, o.share * 100.0, gflops, o.op, kernel, o.name);
    }
}

/// The network module a node of the search graph belongs to, from its name (PRL-Track's
/// modules; an imported model's `backbone/...` and `head/...` nodes).
fn module_of(node: &str) -> &'static str {
    let head = node.split(['_', '.']).next().unwrap_or("");
    match head {
        "backbone" | "x" | "xf1" | "xf2" | "xf3" | "xf4" | "xf5" => "backbone",
        "s1" => "s1 correlation (29x29)",
        "s2" | "s3" | "s4" | "s5" => "s2..s5 correlations",
        "ar" => "AR",
        "sr1" | "sr2" => "SR1 + SR2",
        "hmg" => "HMG (fine representation learning)",
        "grader" | "head" | "loc" | "cls" | "cls1" | "cls2" => "heads",
        _ => "inputs and other",
    }
}

#[derive(Serialize)]
struct Module {
    module: &'static str,
    ms: f64,
    share: f64,
}

#[derive(Serialize)]
struct Report {
    plan: String,
    precision: String,
    /// What the runtime's kernels may use here, and the cap (as printed).
    isa: String,
    threads: usize,
    runs: usize,
    frame: String,
    stages: Vec<Stat>,
    fps: f64,
    plan_load_ms: f64,
    peak_rss_mb: Option<f64>,
    top_ops: Vec<Op>,
    /// The template graph's slowest operators.
    template_ops: Vec<Op>,
    modules: Vec<Module>,
    #[serde(skip_serializing_if = "Option::is_none")]
    targets: Option<Targets>,
}

fn stat(stage: &'static str, v: &[Duration]) -> Stat {
    let samples_ms: Vec<f64> = v.iter().map(|d| d.as_secs_f64() * 1e3).collect();
    let (median_ms, p90_ms) = super::median_p90(&samples_ms);
    Stat { stage, median_ms, p90_ms, samples_ms }
}

fn input(seq: Option<&Path>) -> anyhow::Result<(Frame, BBox, String)> {
    let dir = seq.map(Path::to_path_buf).or_else(|| Some(PathBuf::from(DEFAULT_SEQUENCE)).filter(|p| p.is_dir()));
    if let Some(dir) = dir {
        let s = Sequence::open(&dir)?;
        let gt = s.groundtruth().and_then(|g| g.first()).copied().unwrap_or([600.0, 330.0, 80.0, 60.0]);
        return Ok((load_frame(&s.frames[0])?, init_box_from_groundtruth(gt), s.frames[0].display().to_string()));
    }
    let rgb: Vec<u8> = (0..1280 * 720 * 3).map(|i| ((i * 7919) % 251) as u8).collect();
    let frame = Frame::from_raw(1280, 720, &rgb, prl_runtime::PixelLayout::Rgb)?;
    Ok((frame, BBox { x: 600.0, y: 330.0, w: 80.0, h: 60.0 }, "generated 1280x720".into()))
}

/// Run `f` untimed at least once, and until `secs` seconds have passed.
fn warm_up<E>(secs: f64, mut f: impl FnMut() -> Result<(), E>) -> Result<(), E> {
    let t = Instant::now();
    loop {
        f()?;
        if t.elapsed().as_secs_f64() >= secs {
            return Ok(());
        }
    }
}

pub fn run(a: BenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.runs >= 1, "--runs must be at least 1");
    let template_runs = a.template_runs.unwrap_or(a.runs);
    anyhow::ensure!(template_runs >= 1, "--template-runs must be at least 1");
    anyhow::ensure!((1..=64).contains(&a.targets), "--targets must be 1 to 64");
    anyhow::ensure!((0.0..=60.0).contains(&a.warm_up), "--warm-up must be 0 to 60 seconds");
    let threads = a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    set_threads(threads);
    let (frame, init, frame_name) = input(a.sequence.as_deref())?;
    let t = Instant::now();
    let plan = Plan::load(&a.plan)?;
    let load = t.elapsed();
    let precision = match &plan.manifest().variant {
        Some(v) => format!("{}, variant {v}", plan.manifest().precision),
        None => plan.manifest().precision.clone(),
    };
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config.clone());
    let (mut template, mut crop, mut search, mut post, mut step) = (vec![], vec![], vec![], vec![], vec![]);
    let pb = indicatif::ProgressBar::new((a.runs + template_runs) as u64);
    warm_up(a.warm_up, || tracker.init(&frame, init))?;
    for _ in 0..template_runs {
        tracker.init(&frame, init)?;
        template.push(tracker.last_timings().network);
        pb.inc(1);
    }
    warm_up(a.warm_up, || tracker.track(&frame).map(|_| ()))?;
    for _ in 0..a.runs {
        let t = Instant::now();
        tracker.track(&frame)?;
        let total = t.elapsed();
        pb.inc(1);
        let s = tracker.last_timings();
        crop.push(s.crop);
        search.push(s.network);
        post.push(s.post);
        step.push(total);
    }
    pb.finish_and_clear();
    let targets = if a.targets > 1 {
        Some(time_targets(tracker.plan(), &frame, init, a.targets, threads, a.runs)?)
    } else {
        None
    };
    // Operator profile of the search graph on the real crops, around the initial box.
    tracker.init(&frame, init)?;
    let x = tracker.search_crop(&frame)?;
    let zf = tracker.features().expect("initialised just above");
    if let Some(dir) = &a.save_tensors {
        prl_runtime::record(dir, tracker.plan(), &tracker.exemplar_crop(&frame, init)?, &x)?;
    }
    let prof = if a.top > 0 { tracker.plan().profile_search(&x, zf, a.runs.min(5))? } else { vec![] };
    let total: f64 = prof.iter().map(|n| n.time.as_secs_f64()).sum();
    let top_ops = slowest(&prof, a.top);
    // The template graph's own profile (it runs once per target, and on every re-detection).
    let template_prof = if a.top > 0 {
        let z = tracker.exemplar_crop(&frame, init)?;
        tracker.plan().profile_template(&z, a.runs.min(5))?
    } else {
        vec![]
    };
    let template_ops = slowest(&template_prof, a.top);
    let mut modules: Vec<Module> = vec![];
    for n in &prof {
        let (m, secs) = (module_of(&n.name), n.time.as_secs_f64());
        match modules.iter_mut().find(|x| x.module == m) {
            Some(x) => x.ms += secs * 1e3,
            None => modules.push(Module { module: m, ms: secs * 1e3, share: 0.0 }),
        }
    }
    modules.iter_mut().for_each(|m| m.share = m.ms / (total * 1e3));
    modules.sort_by(|a, b| b.ms.total_cmp(&a.ms));
    let stages = vec![
        stat("template network", &template),
        stat("crop + resize", &crop),
        stat("search network", &search),
        stat("post-processing", &post),
        stat("tracking step", &step),
    ];
    let fps = 1e3 / stages[4].median_ms;
    let report = Report {
        plan: a.plan.display().to_string(),
        precision,
        isa: prl_runtime::isa().describe(),
        threads,
        runs: a.runs,
        frame: frame_name,
        stages,
        fps,
        plan_load_ms: load.as_secs_f64() * 1e3,
        peak_rss_mb: super::peak_rss_mb(),
        top_ops,
        template_ops,
        modules,
        targets,
    };

    println!(
        "plan {} ({}), {} thread(s), {} runs, frame {}; plan load {} ms",
        report.plan,
        report.precision,
        threads,
        a.runs,
        report.frame,
        load.as_millis()
    );
    if let Some(w) = prl_runtime::isa_warning() {
        eprintln!("warning: {w}");
    }
    println!("runtime kernels may use: {}", prl_runtime::isa().describe());
    if let Some(w) = prl_runtime::winograd_warning() {
        eprintln!("warning: {w}");
    }
    let (winograd, forced) = (tracker.plan().winograd(), tracker.plan().winograd_from_env());
    if !winograd.is_off() || forced {
        let from = if forced { "PRL_WINOGRAD" } else { "the plan's choice" };
        println!("convolutions as Winograd's: {} ({from})", winograd.name());
    }
    if !prl_runtime::own_operators() {
        println!("operators: tract's alone (PRL_OPS=tract)");
    }
    let serial = match tracker.plan().single_threaded() {
        (true, true) => "template and search graphs",
        (true, false) => "template graph",
        (false, true) => "search graph",
        (false, false) => "",
    };
    if threads > 1 && !serial.is_empty() {
        println!("{serial} on one thread (no layer large enough to split over threads)");
    }
    println!("{:<18} {:>10} {:>10}", "stage", "median ms", "p90 ms");
    for s in &report.stages {
        println!("{:<18} {:>10.2} {:>10.2}", s.stage, s.median_ms, s.p90_ms);
    }
    println!("FPS (tracking step): {:.1}", report.fps);
    if let Some(t) = &report.targets {
        println!(
            "{} targets, {} at a time: step {:.2} ms (p90 {:.2}) against {:.2} ms (p90 {:.2}) for one target on {} thread(s): {:.2}x",
            t.targets,
            t.jobs,
            t.all_targets.median_ms,
            t.all_targets.p90_ms,
            t.one_target.median_ms,
            t.one_target.p90_ms,
            threads,
            t.ratio
        );
    }
    if let Some(mb) = report.peak_rss_mb {
        println!("peak resident memory: {mb:.0} MB");
    }
    if report.top_ops.is_empty() {
        return finish(&a, &report);
    }
    print_ops("search graph", &report.top_ops);
    println!("\nsearch graph time by module (same profile):");
    for m in &report.modules {
        println!("{:>9.2} {:>5.1}%  {}", m.ms, m.share * 100.0, m.module);
    }
    print_ops("template graph", &report.template_ops);
    finish(&a, &report)
}

fn finish(a: &BenchArgs, report: &Report) -> anyhow::Result<()> {
    if let Some(path) = &a.json {
        write_atomically(path, &serde_json::to_vec_pretty(report)?)?;
    }
    Ok(())
}
