//! `prl verify`.

use std::path::PathBuf;

use clap::Args;
use prl_compiler::{read_golden, verify};

use super::{build::default_source, spinner, WeightsArgs};

/// Default golden file beside the repository.
const DEFAULT_GOLDEN: &str = "../shared/fixtures/prl-golden-v1/golden.safetensors";

#[derive(Args)]
pub struct VerifyArgs {
    #[command(flatten)]
    weights: WeightsArgs,
    /// Golden tensors exported from the official implementation (.safetensors).
    #[arg(long, value_name = "FILE", default_value = DEFAULT_GOLDEN)]
    golden: PathBuf,
    /// Largest relative error ‖out−ref‖/‖ref‖ accepted per tensor.
    #[arg(long, default_value_t = 1e-4)]
    tolerance: f64,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: VerifyArgs) -> anyhow::Result<()> {
    let golden = read_golden(&a.golden)?;
    let source = a.weights.source_or(default_source);
    let pb = spinner("building the network and running every stage with tract");
    let report = source.load().and_then(|w| verify(&w, &golden, a.tolerance));
    pb.finish_and_clear();
    let report = report?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("{:<6} {:>12} {:>12}  result (tolerance {:e})", "tensor", "rel error", "max abs", a.tolerance);
        for s in &report.stages {
            println!(
                "{:<6} {:>12.3e} {:>12.3e}  {}",
                s.name,
                s.rel_error,
                s.max_abs_error,
                if s.ok { "ok" } else { "FAIL" }
            );
        }
        for (k, why) in &report.skipped {
            println!("skipped {k}: {why}");
        }
    }
    if !report.passed {
        let bad: Vec<_> = report.stages.iter().filter(|s| !s.ok).map(|s| s.name.as_str()).collect();
        anyhow::bail!("{}: {} exceed the tolerance {:e}", a.golden.display(), bad.join(", "), a.tolerance);
    }
    Ok(())
}
