//! `prl verify`.

use std::path::{Path, PathBuf};

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
    /// Check a compiled plan instead: run it on the inputs recorded in `--tensors` and compare
    /// its outputs with the recorded ones (a plan compiled and recorded on one machine, checked
    /// on another: `prl bench --save-tensors DIR` records).
    #[arg(long, value_name = "DIR", requires = "tensors", conflicts_with_all = ["checkpoint", "random_seed"])]
    plan: Option<PathBuf>,
    /// Recorded inputs and outputs of `--plan` (a folder written by `prl bench --save-tensors`).
    #[arg(long, value_name = "DIR", requires = "plan")]
    tensors: Option<PathBuf>,
}

pub fn run(a: VerifyArgs) -> anyhow::Result<()> {
    if let (Some(plan), Some(tensors)) = (&a.plan, &a.tensors) {
        return replay(plan, tensors, a.tolerance, a.json);
    }
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

/// `prl verify --plan P --tensors D`: the plan on this machine against what was recorded.
fn replay(plan: &Path, tensors: &Path, tolerance: f64, json: bool) -> anyhow::Result<()> {
    let plan = prl_runtime::Plan::load(plan)?;
    let matches = prl_runtime::replay(tensors, &plan)?;
    let bad: Vec<&str> =
        matches.iter().filter(|m| m.rel.is_nan() || m.rel > tolerance).map(|m| m.name.as_str()).collect();
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(
                &serde_json::json!({ "tolerance": tolerance, "outputs": matches, "passed": bad.is_empty() })
            )?
        );
    } else {
        println!("runtime kernels may use: {}", prl_runtime::isa().describe());
        if !prl_runtime::own_operators() {
            println!("operators: tract's alone (PRL_OPS=tract)");
        }
        if plan.manifest().quantization.is_some() {
            let ints = plan.integer_nodes();
            let mut kernels: Vec<String> = ints.iter().map(|n| n.kernel.clone()).collect();
            kernels.sort();
            kernels.dedup();
            println!("integer products: {} nodes ({})", ints.len(), kernels.join(", "));
        }
        println!(
            "{:<9} {:<10} {:>12} {:>12}  result (tolerance {:e})",
            "graph", "output", "rel error", "max abs", tolerance
        );
        for m in &matches {
            let ok = if m.rel <= tolerance { "ok" } else { "FAIL" };
            println!("{:<9} {:<10} {:>12.3e} {:>12.3e}  {ok}", m.graph, m.name, m.rel, m.max_abs);
        }
    }
    anyhow::ensure!(bad.is_empty(), "{}: {} exceed the tolerance {tolerance:e}", tensors.display(), bad.join(", "));
    Ok(())
}
