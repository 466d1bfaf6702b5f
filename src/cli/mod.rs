//! Command-line parsing and dispatch.

mod bench;
mod build;
mod compare;
mod compare_report;
mod compile;
mod demo;
mod eval;
mod import;
mod occlude;
mod plots;
mod quantize;
mod run_benchmark;
mod soak;
mod track;
mod verify;

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

/// The deployment toolchain for Siamese UAV trackers (PRL-Track, NanoTrack).
#[derive(Parser)]
#[command(
    name = "prl",
    version,
    about = "Siamese UAV tracker toolchain (PRL-Track, NanoTrack): build or import, verify, compile plans, quantise, track"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Emit template.onnx, search.onnx and manifest.json from a checkpoint or random weights.
    Build(build::BuildArgs),
    /// Import a third-party Siamese tracker (NanoTrack) from its ONNX files into a model directory.
    Import(import::ImportArgs),
    /// Run every stage with tract on golden tensors and compare with the official outputs.
    Verify(verify::VerifyArgs),
    /// Compile a model (or a checkpoint, or random weights) into a plan for the runtime.
    Compile(compile::CompileArgs),
    /// Track a target through a frame sequence with a plan.
    Track(track::TrackArgs),
    /// Time each stage of a tracking step and profile the search graph's operators.
    Bench(bench::BenchArgs),
    /// Calibrate on real sequences and write an int8 plan (QLinear operators on tract's integer kernels).
    Quantize(quantize::QuantizeArgs),
    /// Track every video of a dataset (OPE) and write pysot-format results.
    RunBenchmark(run_benchmark::RunBenchmarkArgs),
    /// Score trackers' result folders on a dataset (OPE: success, precision, norm precision).
    Eval(eval::EvalArgs),
    /// Compare plans (e.g. fp32 and int8): latency, output fidelity, tracking agreement, memory.
    Compare(compare::CompareArgs),
    /// Track a looped sequence for a long time: memory, open files and frame time must stay flat.
    Soak(soak::SoakArgs),
    /// Make a lost-and-found sequence from a real one: the target hidden while the view pans.
    Occlude(occlude::OccludeArgs),
    /// Show the whole pipeline working with no input: seeded network, plan, generated video.
    Demo(demo::DemoArgs),
}

/// Where the weights come from: a checkpoint, or seeded random weights.
#[derive(Args, Clone)]
#[group(required = false, multiple = false)]
pub struct WeightsArgs {
    /// Official PyTorch checkpoint (.pth) or .safetensors file.
    #[arg(long, value_name = "FILE")]
    pub checkpoint: Option<PathBuf>,
    /// Seeded random weights (for users without a checkpoint; not a trained model).
    #[arg(long, value_name = "N")]
    pub random_seed: Option<u64>,
}

impl WeightsArgs {
    /// The source, or `default` when neither option was given.
    pub fn source_or(&self, default: impl FnOnce() -> prl_compiler::WeightsSource) -> prl_compiler::WeightsSource {
        match (&self.checkpoint, self.random_seed) {
            (Some(p), _) => prl_compiler::WeightsSource::Checkpoint(p.clone()),
            (None, Some(s)) => prl_compiler::WeightsSource::Random(s),
            (None, None) => default(),
        }
    }
}

/// Parse the command line and run it.
pub fn run() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Build(a) => build::run(a),
        Command::Import(a) => import::run(a),
        Command::Verify(a) => verify::run(a),
        Command::Compile(a) => compile::run(a),
        Command::Track(a) => track::run(a),
        Command::Demo(a) => demo::run(a),
        Command::Soak(a) => soak::run(a),
        Command::Occlude(a) => occlude::run(a),
        Command::Eval(a) => eval::run(a),
        Command::RunBenchmark(a) => run_benchmark::run(a),
        Command::Bench(a) => bench::run(a),
        Command::Quantize(a) => quantize::run(a),
        Command::Compare(a) => compare::run(a),
    }
}

/// A spinner on stderr for steps that take more than a moment (hidden when not a terminal).
pub fn spinner(msg: &str) -> indicatif::ProgressBar {
    let pb = indicatif::ProgressBar::new_spinner();
    pb.set_style(indicatif::ProgressStyle::with_template("{spinner} {msg} ({elapsed})").expect("static template"));
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb.set_message(msg.to_string());
    pb
}

/// Median and 90th percentile of `ms` (nearest rank; `ms` must not be empty).
pub fn median_p90(ms: &[f64]) -> (f64, f64) {
    let mut ms = ms.to_vec();
    ms.sort_by(f64::total_cmp);
    let at = |q: f64| ms[((ms.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.9))
}

/// A plan's manifest alone (no graph is loaded), with errors naming the file.
pub fn read_plan_manifest(dir: &std::path::Path) -> anyhow::Result<prl_runtime::PlanManifest> {
    use anyhow::Context;
    let path = dir.join(prl_runtime::PLAN_MANIFEST);
    let bytes = std::fs::read(&path).with_context(|| format!("{}: cannot read the plan manifest", path.display()))?;
    serde_json::from_slice(&bytes).with_context(|| format!("{}: not a plan manifest", path.display()))
}

/// The crops of `spec` (see [`prl_track::calibration_crops`]) behind a progress bar saying `msg`.
pub fn crops_with_progress(
    spec: &prl_track::CalibrationSpec,
    config: &prl_runtime::TrackerConfig,
    msg: &str,
) -> anyhow::Result<prl_compiler::Calibration> {
    let bar = progress_bar(0, msg);
    let crops = prl_track::calibration_crops(spec, config, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    Ok(crops?)
}

/// A progress bar on stderr with `msg` (hidden when not a terminal).
pub fn progress_bar(len: u64, msg: &str) -> indicatif::ProgressBar {
    let pb = indicatif::ProgressBar::new(len);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} ({elapsed}, {eta} left)")
            .expect("static template"),
    );
    pb.set_message(msg.to_string());
    pb
}

/// Write `bytes` to `path` whole or not at all ([`prl_runtime::write_atomically`]: a flushed
/// temporary beside it, renamed into place).
pub fn write_atomically(path: &std::path::Path, bytes: &[u8]) -> anyhow::Result<()> {
    prl_runtime::write_atomically(path, bytes).map_err(|e| match e {
        prl_runtime::Error::Io { err, .. } => anyhow::anyhow!("{}: cannot write: {err}", path.display()),
        other => other.into(),
    })
}

/// Write a run's pysot-format results to `path` and its per-frame confidences beside them
/// (`<stem>_confidence.value`, for `prl eval`'s long-term figures), each through a temporary.
pub fn write_results(path: &std::path::Path, run: &prl_track::tracking::TrackRun) -> anyhow::Result<()> {
    write_atomically(path, run.results_text().as_bytes())?;
    write_atomically(&prl_track::longterm::confidence_path(path), run.confidence_text().as_bytes())
}

/// Peak resident memory of this process so far, in MB (where the OS reports it). On Linux this
/// is `VmHWM` of `/proc/self/status`, which starts afresh at `exec`; `getrusage`'s maximum would
/// carry over the memory of the process that spawned us (`prl compare` runs `prl track`).
pub fn peak_rss_mb() -> Option<f64> {
    if let Ok(status) = std::fs::read_to_string("/proc/self/status") {
        let kb = status
            .lines()
            .find_map(|l| l.strip_prefix("VmHWM:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok());
        if let Some(kb) = kb {
            return Some(kb * 1024.0 / 1e6);
        }
    }
    #[cfg(unix)]
    {
        let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
        // SAFETY: getrusage fills the struct it is given; RUSAGE_SELF is always valid.
        let ok = unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } == 0;
        // SAFETY: initialised by the successful call above (zeroed otherwise).
        let kb = unsafe { usage.assume_init() }.ru_maxrss as f64; // kilobytes on Linux
        ok.then(|| kb * 1024.0 / 1e6)
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// `, Winograd 3x3` (or `all`) after a plan's precision where it runs convolutions as
/// Winograd's; nothing where it does not.
pub fn winograd_note(w: prl_runtime::Winograd) -> String {
    if w.is_off() {
        String::new()
    } else {
        format!(", Winograd {}", w.name())
    }
}

/// `--variant` values: the ablation variants of the paper's Table II.
pub fn parse_variant(s: &str) -> Result<prl_compiler::net::Variant, String> {
    use prl_compiler::net::Variant;
    Variant::parse(s).ok_or_else(|| {
        let names: Vec<&str> = Variant::ALL.iter().map(|v| v.name()).collect();
        format!("`{s}` is not a variant; expected one of {}", names.join(", "))
    })
}
