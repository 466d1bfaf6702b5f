//! `prl build`.

use std::path::PathBuf;

use clap::Args;
use prl_compiler::WeightsSource;

use super::{spinner, WeightsArgs};

/// Default location of the fixture checkpoint shipped beside the repository.
pub const DEFAULT_CHECKPOINT: &str = "../shared/fixtures/prl-golden-v1/checkpoint.pth";

#[derive(Args)]
pub struct BuildArgs {
    #[command(flatten)]
    weights: WeightsArgs,
    /// Ablation variant of the paper's Table II (`baseline`, `flp`, `ar-flp`, `sr-flp`, `full`):
    /// which of AR, SR and the fine representation learning (HMG) the search graph keeps. Left-out
    /// modules become a seeded 3x3 stride-2 convolution; for latency studies (`prl bench`).
    #[arg(long, default_value = "full", value_parser = super::parse_variant)]
    variant: prl_compiler::net::Variant,
    /// Output directory.
    #[arg(long, default_value = "models/prl-track/build")]
    out: PathBuf,
    /// List checkpoint keys the network does not use.
    #[arg(long, short)]
    verbose: bool,
}

pub fn run(a: BuildArgs) -> anyhow::Result<()> {
    let source = a.weights.source_or(default_source);
    let pb = spinner(&format!("building PRL-Track from {}", describe(&source)));
    let report = prl_compiler::build_model_variant(&source, a.variant).and_then(|m| m.write(&a.out).map(|_| m));
    pb.finish_and_clear();
    let report = report?;
    let m = &report.manifest;
    println!("wrote {}, {} and manifest.json to {}", m.template.file, m.search.file, a.out.display());
    println!(
        "weights: {}{}",
        m.weights.note,
        m.weights.sha256.as_deref().map(|s| format!(" (sha256 {})", short(s))).unwrap_or_default()
    );
    if !report.unused_keys.is_empty() {
        if a.verbose {
            println!("{} checkpoint keys not used by the network:", report.unused_keys.len());
            for k in &report.unused_keys {
                println!("  {k}");
            }
        } else {
            println!("{} checkpoint keys not used by the network (--verbose lists them)", report.unused_keys.len());
        }
    }
    Ok(())
}

/// Without options: the reference checkpoint beside the repository if present, else seed 0.
pub fn default_source() -> WeightsSource {
    let p = PathBuf::from(DEFAULT_CHECKPOINT);
    if p.exists() {
        WeightsSource::Checkpoint(p)
    } else {
        WeightsSource::Random(0)
    }
}

pub fn describe(s: &WeightsSource) -> String {
    match s {
        WeightsSource::Checkpoint(p) => p.display().to_string(),
        WeightsSource::Random(seed) => format!("random weights (seed {seed})"),
    }
}

fn short(s: &str) -> &str {
    &s[..12.min(s.len())]
}
