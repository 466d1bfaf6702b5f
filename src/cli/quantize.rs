//! `prl quantize`: calibrate on real frames and write an int8 plan.

use std::path::{Path, PathBuf};

use anyhow::bail;
use clap::Args;
use prl_compiler::{compile_int8, BuiltModel, Method, PerChannel, QuantizeOptions};
use prl_runtime::{LayerDecision, QuantizationInfo, TrackerConfig, Winograd, PLAN_MANIFEST};
use prl_track::CalibrationSpec;

use super::compile::settings_for;

#[derive(Args)]
pub struct QuantizeArgs {
    /// The fp32 plan to quantise: its network is rebuilt from the checkpoint (or seed) its manifest
    /// records, checked by SHA-256, with its tracker settings.
    #[arg(long, value_name = "DIR", conflicts_with = "model", default_value = "models/prl-track/plan")]
    plan: PathBuf,
    /// A model directory written by `prl build`, instead of a plan (tracker settings from --tracker).
    #[arg(long, value_name = "DIR")]
    model: Option<PathBuf>,
    /// Tracker settings for a plan made from --model (TOML; default: the model's own, else
    /// PRL-Track's).
    #[arg(long, value_name = "FILE", requires = "model")]
    tracker: Option<PathBuf>,
    /// Float convolutions to run as Winograd's (off, 3x3, all; `prl compile --winograd`):
    /// default the fp32 plan's choice (off with --model).
    #[arg(long, value_name = "WHICH")]
    winograd: Option<Winograd>,
    /// Calibration sequences (OTB/UAV123 layout, with ground truth); keep them apart from the
    /// sequences you evaluate on.
    #[arg(long, value_name = "SEQ_DIR", num_args = 1.., required = true)]
    calib: Vec<PathBuf>,
    /// Search crops per calibration sequence, from frames spread over it.
    #[arg(long, default_value_t = 64, value_name = "N")]
    frames_per_seq: usize,
    /// Template crops per calibration sequence: the first frame's and more from frames spread
    /// over it, so that ranges also cover targets that look otherwise.
    #[arg(long, default_value_t = 4, value_name = "N")]
    templates_per_seq: usize,
    /// How activation ranges are chosen: minmax, percentile (99.99% of each side), entropy (KL),
    /// mse (least squared error).
    #[arg(long, default_value = "percentile", value_parser = parse_method)]
    method: Method,
    /// Per-output-channel weight scales: auto (where one scale loses over 2% of a weight and
    /// per channel halves that), on, off.
    #[arg(long, default_value = "auto", value_parser = parse_per_channel)]
    per_channel: PerChannel,
    /// Layers (node names of the search graph) to keep in f32.
    #[arg(long, value_name = "NODE", num_args = 1..)]
    keep_fp32: Vec<String>,
    /// Rank layers by sensitivity (each quantised alone) and keep the N most sensitive in f32.
    #[arg(long, value_name = "N")]
    budget: Option<usize>,
    /// Layers with fewer multiply-adds per frame stay f32.
    #[arg(long, value_name = "MACS", default_value_t = QuantizeOptions::default().min_macs)]
    min_macs: u64,
    /// Convolutions with fewer output channels stay f32 (the runtime's int8 convolution on
    /// VNNI or the aarch64 dot product pays for 64; tract's, used on other CPUs, pays an im2col
    /// and zero-point sums per input element, which few output channels do not amortise).
    #[arg(long, value_name = "N", default_value_t = QuantizeOptions::default().min_out_channels)]
    min_out_channels: usize,
    /// Also quantise products of two activations (HMG's attention); measured no faster than
    /// f32 today, since both sides are quantised every frame.
    #[arg(long)]
    act_matmul: bool,
    /// Also quantise depthwise convolutions (MobileNet's, as in NanoTrack), whatever their
    /// multiply-adds: their input and output then stay u8.
    #[arg(long)]
    depthwise: bool,
    /// Seed of the calibration crops' jitter.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Plan directory to write.
    #[arg(long, default_value = "models/prl-track/plan-int8")]
    out: PathBuf,
}

fn parse_method(s: &str) -> Result<Method, String> {
    Method::parse(s).ok_or_else(|| format!("`{s}` is not a method; expected minmax, percentile, entropy or mse"))
}

fn parse_per_channel(s: &str) -> Result<PerChannel, String> {
    PerChannel::parse(s).ok_or_else(|| format!("`{s}` is not a setting; expected auto, on or off"))
}

/// The fp32 model a plan was compiled from, rebuilt from the sources its manifest records, with
/// the plan's tracker settings and Winograd choice.
fn model_of_plan(dir: &Path) -> anyhow::Result<(BuiltModel, TrackerConfig, Winograd)> {
    let path = dir.join(PLAN_MANIFEST);
    let m = super::read_plan_manifest(dir)?;
    if m.precision != "fp32" {
        bail!("{}: the plan is already {}; quantise an fp32 plan", path.display(), m.precision);
    }
    Ok((prl_compiler::rebuild_model(&m, &path)?, m.tracker, m.winograd))
}

pub fn run(a: QuantizeArgs) -> anyhow::Result<()> {
    if a.frames_per_seq == 0 {
        bail!("--frames-per-seq must be at least 1");
    }
    let (model, tracker, winograd) = match &a.model {
        Some(dir) => {
            let model = BuiltModel::read(dir)?;
            let tracker = settings_for(&model, a.tracker.as_deref())?;
            (model, tracker, Winograd::Off)
        }
        None => {
            let pb = super::spinner(&format!("rebuilding the network of {}", a.plan.display()));
            let r = model_of_plan(&a.plan);
            pb.finish_and_clear();
            r?
        }
    };
    let spec = CalibrationSpec {
        sequences: a.calib.clone(),
        frames_per_sequence: a.frames_per_seq,
        templates_per_sequence: a.templates_per_seq,
        seed: a.seed,
        held_out: false,
    };
    let calib = super::crops_with_progress(&spec, &tracker, "cutting calibration crops")?;
    let opts = QuantizeOptions {
        method: a.method,
        per_channel: a.per_channel,
        keep_fp32: a.keep_fp32.clone(),
        budget: a.budget,
        min_macs: a.min_macs,
        min_out_channels: a.min_out_channels,
        act_matmul: a.act_matmul,
        depthwise: a.depthwise,
        ..QuantizeOptions::default()
    };
    let bar = super::progress_bar(0, "");
    let result = prl_compiler::quantize(&model, &calib, &opts, &mut |stage, done, total| {
        bar.set_message(stage.to_string());
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    let (int8, info) = result?;
    let pb = super::spinner("compiling the int8 plan");
    let plan = compile_int8(&int8, &tracker, info).and_then(|mut p| {
        p.manifest.winograd = a.winograd.unwrap_or(winograd);
        p.write(&a.out).map(|_| p)
    });
    pb.finish_and_clear();
    let plan = plan?;
    let info = plan.manifest.quantization.as_ref().expect("an int8 plan records its quantisation");
    let outputs: Vec<&str> = plan.manifest.search.outputs.iter().map(|o| o.name.as_str()).collect();
    print_report(info, &outputs.join("/"));
    let mb = (plan.template.len() + plan.search.len()) as f64 / 1e6;
    println!(
        "wrote int8 plan {} ({mb:.1} MB; calibrated on {})",
        a.out.display(),
        info.calibration.sequences.join(", ")
    );
    Ok(())
}

fn range(r: (f32, f32)) -> String {
    format!("[{:.3}, {:.3}]", r.0, r.1)
}

fn slash(v: &[f64]) -> String {
    v.iter().map(|x| format!("{x:.4}")).collect::<Vec<_>>().join("/")
}

/// The per-layer table of a quantisation; `outputs` names the search outputs (`loc/cls1/cls2`).
pub fn print_report(info: &QuantizationInfo, outputs: &str) {
    println!(
        "quantised with {} ranges, per-channel {}, on {} search crops of {} sequence(s)",
        info.method,
        info.per_channel,
        info.calibration.search_crops,
        info.calibration.sequences.len()
    );
    let sens = info.layers.iter().any(|l| l.sensitivity.is_some());
    println!(
        "{:<36} {:>10} {:>7} {:<27} {:>5} {:>8}  {:<20} {:<20}{}",
        "layer",
        "op",
        "MMAC",
        "precision",
        "perch",
        "w err",
        "input range",
        "output range",
        if sens { format!("  sensitivity {outputs}") } else { String::new() }
    );
    for l in &info.layers {
        let s = l.sensitivity.as_ref().map(|s| format!("  {}", slash(s))).unwrap_or_default();
        println!(
            "{:<36} {:>10} {:>7.1} {:<27} {:>5} {:>8.4}  {:<20} {:<20}{s}",
            l.node,
            l.op,
            l.macs as f64 / 1e6,
            l.decision.describe(),
            if l.per_channel { "yes" } else { "no" },
            l.weight_error,
            range(l.input_range),
            range(l.output_range),
        );
    }
    let int8 = info.layers.iter().filter(|l| l.decision == LayerDecision::Int8);
    let (n, macs) = int8.fold((0, 0), |(n, m), l| (n + 1, m + l.macs));
    let all: u64 = info.layers.iter().map(|l| l.macs).sum();
    println!(
        "{n} of {} layers int8, {:.0}% of their multiply-adds",
        info.layers.len(),
        100.0 * macs as f64 / all as f64
    );
}
