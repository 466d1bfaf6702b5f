//! Importing third-party Siamese trackers from ONNX into a model directory like the one
//! `prl build` writes (`template.onnx`, `search.onnx`, `manifest.json`), so that compile,
//! quantize, track, bench, compare and eval work on them unchanged.
//!
//! A Siamese model comes split one of two ways ([`Parts`]): a backbone and a head (the backbone
//! runs on both crops, the head correlates the two feature maps), or a backbone and a whole
//! search graph. The template graph is the backbone at the exemplar size; the search graph takes
//! the search crop and the template features and is the backbone at the instance size followed
//! by the head, in one graph. A family ([`nanotrack`]) only supplies its settings and names.

pub mod nanotrack;
mod proto;

use std::path::{Path, PathBuf};

use prl_runtime::{GraphInfo, Preprocessing, SourceFile, TensorInfo, TrackerConfig, WeightsInfo};
use prost::Message;
use sha2::{Digest, Sha256};
use tract_onnx::pb;

use crate::artefacts::{BuiltModel, Manifest, FORMAT_VERSION};
use crate::checkpoint::hex;
use crate::{Error, Result};
use proto::Onnx;

/// One ONNX file as read: where it came from and its bytes.
#[derive(Debug, Clone)]
pub struct OnnxFile {
    /// The file (named in every error about it).
    pub path: PathBuf,
    /// Its bytes.
    pub bytes: Vec<u8>,
}

impl OnnxFile {
    /// Read `path`.
    pub fn read(path: &Path) -> Result<OnnxFile> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Ok(OnnxFile { path: path.to_path_buf(), bytes })
    }

    fn source(&self, role: &str) -> SourceFile {
        SourceFile {
            role: role.into(),
            path: self.path.display().to_string(),
            sha256: hex(&Sha256::digest(&self.bytes)),
        }
    }
}

/// How the model's ONNX files split the network.
#[derive(Debug, Clone)]
pub enum Parts {
    /// `backbone(crop) -> features` and `head(template features, search features) -> outputs`.
    BackboneHead {
        /// The feature extractor, run on both crops.
        backbone: OnnxFile,
        /// The correlation and heads.
        head: OnnxFile,
    },
    /// `backbone(crop) -> features` and `search(search crop, template features) -> outputs`.
    BackboneSearch {
        /// The feature extractor (the template graph).
        backbone: OnnxFile,
        /// The whole search branch.
        search: OnnxFile,
    },
}

/// What a family says about an imported model.
#[derive(Debug, Clone)]
pub struct FamilyImport {
    /// The network's name in manifests (`nanotrack-v2`).
    pub model: String,
    /// Tracker settings (the family's, with the user's config applied).
    pub tracker: TrackerConfig,
    /// The config file the settings came from, if any: named when it disagrees with the model.
    pub config: Option<ConfigFile>,
}

/// A model's config file (its settings), recorded in the manifest.
#[derive(Debug, Clone)]
pub struct ConfigFile {
    /// The file.
    pub path: PathBuf,
    /// Its SHA-256, hex.
    pub sha256: String,
}

/// Import `parts` as a model directory's contents for `family`.
pub fn import(parts: &Parts, family: &FamilyImport) -> Result<BuiltModel> {
    let cfg = &family.tracker;
    cfg.check().map_err(|msg| config_error(family, msg))?;
    let (backbone_file, other_file, other_role) = match parts {
        Parts::BackboneHead { backbone, head } => (backbone, head, "head"),
        Parts::BackboneSearch { backbone, search } => (backbone, search, "search"),
    };
    let backbone = Onnx::decode(backbone_file)?;
    let other = Onnx::decode(other_file)?;
    backbone.expect_io(1, 1, "a backbone takes one image and gives one feature map")?;
    other.expect_io(2, family.tracker.family.search_outputs().len(), "")?;
    backbone.expect_image_input()?;

    // The template graph: the backbone at the exemplar size.
    let e = cfg.exemplar_size;
    let mut template = backbone.clone();
    template.rename_io("z", &["zf"]);
    template.set_input_shape(0, &[1, 3, e, e]);
    let zf = template.infer_output_shapes(&backbone_file.path, &format!("at {e}x{e} (the exemplar size)"))?;
    template.set_output_shapes(&zf);

    // The search graph: the backbone at the instance size, then the head (or the given one).
    let i = cfg.instance_size;
    let outputs: Vec<String> = cfg.family.search_outputs().iter().map(|(n, _)| n.to_string()).collect();
    let mut search = match parts {
        Parts::BackboneHead { .. } => {
            let mut xb = backbone.clone();
            xb.set_input_shape(0, &[1, 3, i, i]);
            let xf = xb.infer_output_shapes(&backbone_file.path, &format!("at {i}x{i} (the instance size)"))?;
            let (t_in, s_in) = other.feature_inputs(&zf[0], &xf[0]).map_err(|err| match &family.config {
                Some(_) => config_error(
                    family,
                    format!(
                        "with {e}x{e} template and {i}x{i} search crops in the settings, the head's {}",
                        strip_path(&err.to_string())
                    ),
                ),
                None => err,
            })?;
            let head_outputs = other.order_outputs(cfg.family.search_outputs())?;
            proto::join(&backbone, &other, t_in, s_in, &head_outputs, &outputs)?
        }
        Parts::BackboneSearch { .. } => {
            let mut s = other.clone();
            let order = s.order_outputs(cfg.family.search_outputs())?;
            s.reorder_outputs(&order);
            s.rename_io("x", &outputs.iter().map(String::as_str).collect::<Vec<_>>());
            s.rename_input(1, "zf");
            s
        }
    };
    search.set_input_shape(0, &[1, 3, i, i]);
    search.set_input_shape(1, &zf[0]);
    let what = format!("with a {i}x{i} search crop and template features {:?}", zf[0]);
    let shapes = search.infer_output_shapes(&other_file.path, &what)?;
    let n = cfg.score_size;
    for ((name, channels), shape) in cfg.family.search_outputs().iter().zip(&shapes) {
        if shape.len() != 4 || shape[1] != *channels {
            return Err(Error::format(
                &other_file.path,
                format!(
                    "output for `{name}` is {shape:?}; a {} tracker needs [1, {channels}, N, N]",
                    cfg.family.name()
                ),
            ));
        }
        if shape[2..] != [n, n] {
            return Err(config_error(
                family,
                format!(
                    "the score map is {n}x{n} in the settings, but the model's `{name}` output is {}x{} \
                     ({} at a {i}x{i} search crop)",
                    shape[2],
                    shape[3],
                    other_file.path.display()
                ),
            ));
        }
    }
    search.set_output_shapes(&shapes);

    let doc = format!("{} imported by prl-compiler {}", family.model, env!("CARGO_PKG_VERSION"));
    let (template, search) = (template.encode(&doc), search.encode(&doc));
    let info = |file: &str, bytes: &[u8], inputs: Vec<TensorInfo>, outputs: Vec<TensorInfo>| GraphInfo {
        file: file.into(),
        sha256: hex(&Sha256::digest(bytes)),
        inputs,
        outputs,
    };
    let t = |name: &str, shape: &[usize]| TensorInfo { name: name.into(), shape: shape.to_vec() };
    let mut files = vec![backbone_file.source("backbone"), other_file.source(other_role)];
    if let Some(c) = &family.config {
        files.push(SourceFile { role: "config".into(), path: c.path.display().to_string(), sha256: c.sha256.clone() });
    }
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: family.model.clone(),
        tool: format!("prl-compiler {}", env!("CARGO_PKG_VERSION")),
        opset: template_opset(&template),
        weights: WeightsInfo {
            kind: "onnx".into(),
            path: Some(backbone_file.path.display().to_string()),
            sha256: Some(hex(&Sha256::digest(&backbone_file.bytes))),
            seed: None,
            files,
            note: format!("trained weights of {}, imported from ONNX", family.model),
        },
        template: info("template.onnx", &template, vec![t("z", &[1, 3, e, e])], vec![t("zf", &zf[0])]),
        search: info(
            "search.onnx",
            &search,
            vec![t("x", &[1, 3, i, i]), t("zf", &zf[0])],
            outputs.iter().zip(&shapes).map(|(n, s)| t(n, s)).collect(),
        ),
        preprocessing: Preprocessing { template_size: e, search_size: i, ..crate::preprocessing() },
        variant: None,
        tracker: Some(cfg.clone()),
    };
    Ok(BuiltModel { manifest, template, search, unused_keys: vec![] })
}

/// An error message without its leading `path: `.
fn strip_path(msg: &str) -> &str {
    msg.split_once(": ").map_or(msg, |(_, rest)| rest)
}

fn template_opset(bytes: &[u8]) -> i64 {
    pb::ModelProto::decode(bytes)
        .ok()
        .and_then(|m| m.opset_import.iter().find(|o| o.domain.is_empty()).map(|o| o.version))
        .unwrap_or(0)
}

fn config_error(family: &FamilyImport, msg: String) -> Error {
    match &family.config {
        Some(c) => Error::format(&c.path, msg),
        None => Error::Other(format!("{} settings: {msg}", family.model)),
    }
}
