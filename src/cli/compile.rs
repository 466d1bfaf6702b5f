//! `prl compile`.

use std::path::{Path, PathBuf};

use clap::Args;
use prl_compiler::{compile, BuiltModel};
use prl_runtime::{TrackerConfig, Winograd};

use super::build::{default_source, describe};
use super::{spinner, WeightsArgs};

/// The tracker settings file of the repository.
pub const DEFAULT_TRACKER_TOML: &str = "models/prl-track/tracker.toml";

#[derive(Args)]
pub struct CompileArgs {
    /// A model directory written by `prl build` (else the network is built from the weights
    /// options, or the default `prl build` uses).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["checkpoint", "random_seed"])]
    model: Option<PathBuf>,
    #[command(flatten)]
    weights: WeightsArgs,
    /// Ablation variant of the paper's Table II (`baseline`, `flp`, `ar-flp`, `sr-flp`, `full`):
    /// which of AR, SR and the fine representation learning (HMG) the search graph keeps. Left-out
    /// modules become a seeded 3x3 stride-2 convolution; for latency studies (`prl bench`).
    #[arg(long, default_value = "full", value_parser = super::parse_variant, conflicts_with = "model")]
    variant: prl_compiler::net::Variant,
    /// Tracker settings to store in the plan (TOML; default: the model's own, as `prl import`
    /// records them, else `models/prl-track/tracker.toml`).
    #[arg(long, value_name = "FILE")]
    tracker: Option<PathBuf>,
    /// Plan directory to write.
    #[arg(long, default_value = "models/prl-track/plan")]
    out: PathBuf,
    /// Convolutions to run as Winograd's fast algorithm (off, 3x3, all): the stride-1 3x3 ones
    /// (`all`: and 5x5) of 32+ channels where they pay. Faster (docs/performance.md), and a
    /// little further from the official tracker: PRL-Track's boxes within 2e-4 px of the
    /// official ones on the reference traces with `all`, against 1e-4 px with the direct form.
    /// Recorded in plan.json; `PRL_WINOGRAD` overrides it when a plan is loaded.
    #[arg(long, default_value = "off", value_name = "WHICH")]
    winograd: Winograd,
}

/// Tracker settings from `path`; the official ones when the default file is absent.
pub fn tracker_config(path: &Path) -> anyhow::Result<TrackerConfig> {
    match prl_track::read_text_bounded(path, 1 << 20, "a tracker settings file") {
        Ok(text) => {
            let t: TrackerConfig =
                toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.message()))?;
            t.check().map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            Ok(t)
        }
        Err(_) if path == Path::new(DEFAULT_TRACKER_TOML) && !path.exists() => Ok(TrackerConfig::default()),
        Err(e) => Err(e.into()),
    }
}

/// The settings a plan of `model` gets: those of `explicit` (a TOML file) when given, else the
/// model's own (imported models carry them), else PRL-Track's file.
pub fn settings_for(model: &BuiltModel, explicit: Option<&Path>) -> anyhow::Result<TrackerConfig> {
    let t = match (explicit, &model.manifest.tracker) {
        (Some(path), _) => tracker_config(path)?,
        (None, Some(t)) => t.clone(),
        (None, None) => tracker_config(Path::new(DEFAULT_TRACKER_TOML))?,
    };
    if let Some(own) = model.manifest.tracker.as_ref().filter(|own| own.family != t.family) {
        anyhow::bail!(
            "the settings are for a {} tracker, but the model is a {} ({})",
            t.family.name(),
            own.family.name(),
            model.manifest.model
        );
    }
    Ok(t)
}

pub fn run(a: CompileArgs) -> anyhow::Result<()> {
    let model = match &a.model {
        Some(dir) => BuiltModel::read(dir)?,
        None => {
            let source = a.weights.source_or(default_source);
            let pb = spinner(&format!("building PRL-Track from {}", describe(&source)));
            let m = prl_compiler::build_model_variant(&source, a.variant);
            pb.finish_and_clear();
            m?
        }
    };
    let tracker = settings_for(&model, a.tracker.as_deref())?;
    let pb = spinner("compiling: tract declutters both graphs and writes them as NNEF");
    let plan = compile(&model, &tracker).and_then(|mut p| {
        p.manifest.winograd = a.winograd;
        p.write(&a.out).map(|_| p)
    });
    pb.finish_and_clear();
    let plan = plan?;
    let size = |b: &[u8]| b.len() as f64 / 1e6;
    println!(
        "wrote plan {} ({}{}, {}: template {:.1} MB, search {:.1} MB, tract {})",
        a.out.display(),
        plan.manifest.precision,
        super::winograd_note(plan.manifest.winograd),
        plan.manifest.weights.note,
        size(&plan.template),
        size(&plan.search),
        plan.manifest.tract_version
    );
    Ok(())
}
