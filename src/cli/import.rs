//! `prl import`: a third-party Siamese tracker's ONNX files into a model directory.

use std::path::{Path, PathBuf};

use clap::Args;

use super::spinner;

/// Where the NanoTrack v2 files ship in the repository (Apache-2.0, see its README).
pub const NANOTRACK_DIR: &str = "models/nanotrack-v2";

#[derive(Args)]
pub struct ImportArgs {
    /// The tracker family (`nanotrack`).
    #[arg(value_name = "FAMILY", value_parser = parse_importable)]
    family: prl_runtime::Family,
    /// The backbone ONNX (default: the NanoTrack v2 backbone shipped in `models/nanotrack-v2`).
    #[arg(long, value_name = "FILE")]
    backbone: Option<PathBuf>,
    /// The head ONNX (default: the shipped NanoTrack v2 head).
    #[arg(long, value_name = "FILE")]
    head: Option<PathBuf>,
    /// The model's YAML config (`configv2.yaml`); default: configv2's settings.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Model directory to write.
    #[arg(long, default_value = "models/nanotrack-v2/build")]
    out: PathBuf,
}

fn parse_importable(s: &str) -> Result<prl_runtime::Family, String> {
    match prl_runtime::Family::parse(s) {
        Some(f @ prl_runtime::Family::Nanotrack) => Ok(f),
        Some(f) => Err(format!("`{}` models are built from a checkpoint with `prl build`, not imported", f.name())),
        None => Err(format!("`{s}` is not a tracker family that can be imported; expected nanotrack")),
    }
}

/// The shipped NanoTrack v2 folder: `models/nanotrack-v2` under the current directory, else
/// the one of the source tree this binary was built from.
pub fn nanotrack_dir() -> PathBuf {
    let here = PathBuf::from(NANOTRACK_DIR);
    if here.join("nanotrack_backbone_sim.onnx").exists() {
        return here;
    }
    Path::new(env!("CARGO_MANIFEST_DIR")).join(NANOTRACK_DIR)
}

/// Import NanoTrack from `backbone` and `head` (the shipped files when `None`).
pub fn import_nanotrack(
    backbone: Option<&Path>,
    head: Option<&Path>,
    config: Option<&Path>,
) -> anyhow::Result<prl_compiler::BuiltModel> {
    let dir = nanotrack_dir();
    let backbone = backbone.map_or_else(|| dir.join("nanotrack_backbone_sim.onnx"), Path::to_path_buf);
    let head = head.map_or_else(|| dir.join("nanotrack_head_sim.onnx"), Path::to_path_buf);
    Ok(prl_compiler::import_nanotrack(&backbone, &head, config)?)
}

pub fn run(a: ImportArgs) -> anyhow::Result<()> {
    let pb = spinner("importing: checking both ONNX files and joining backbone and head");
    let model = match a.family {
        prl_runtime::Family::Nanotrack => {
            import_nanotrack(a.backbone.as_deref(), a.head.as_deref(), a.config.as_deref())
        }
        f => unreachable!("parse_importable refuses {}", f.name()),
    };
    let written = model.and_then(|m| m.write(&a.out).map(|_| m).map_err(Into::into));
    pb.finish_and_clear();
    let m = written?.manifest;
    println!("wrote {}, {} and manifest.json to {}", m.template.file, m.search.file, a.out.display());
    let shape = |t: &[prl_runtime::TensorInfo]| {
        t.iter().map(|t| format!("{} {:?}", t.name, t.shape)).collect::<Vec<_>>().join(", ")
    };
    println!("template graph: {} -> {}", shape(&m.template.inputs), shape(&m.template.outputs));
    println!("search graph: {} -> {}", shape(&m.search.inputs), shape(&m.search.outputs));
    println!(
        "tracker: {} settings recorded in the manifest (`prl compile --model {}` uses them)",
        m.model,
        a.out.display()
    );
    Ok(())
}
