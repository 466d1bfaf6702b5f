//! NanoTrack (HonglinChu/SiamTrackers, v2; OpenCV's `TrackerNano`): a MobileNetV3 backbone
//! ONNX and a head ONNX, with the tracker settings of its YAML config (`configv2.yaml`).

use std::path::Path;

use prl_runtime::TrackerConfig;
use sha2::{Digest, Sha256};
use yaml_rust2::{Yaml, YamlLoader};

use super::{import, ConfigFile, FamilyImport, OnnxFile, Parts};
use crate::checkpoint::hex;
use crate::{BuiltModel, Error, Result};

/// The network's name in manifests.
pub const MODEL: &str = "nanotrack-v2";

/// Import NanoTrack from its two ONNX files as shipped, with the settings of `config` where
/// given (else configv2's).
pub fn import_nanotrack(backbone: &Path, head: &Path, config: Option<&Path>) -> Result<BuiltModel> {
    let (tracker, config) = match config {
        Some(p) => {
            let bytes = std::fs::read(p).map_err(|e| Error::io(p, e))?;
            let text = String::from_utf8(bytes.clone()).map_err(|_| Error::format(p, "not UTF-8 text"))?;
            (settings(&text, p)?, Some(ConfigFile { path: p.to_path_buf(), sha256: hex(&Sha256::digest(&bytes)) }))
        }
        None => (TrackerConfig::nanotrack(), None),
    };
    let parts = Parts::BackboneHead { backbone: OnnxFile::read(backbone)?, head: OnnxFile::read(head)? };
    import(&parts, &FamilyImport { model: MODEL.into(), tracker, config })
}

/// configv2's settings with those `yaml` gives (`TRACK.*`, `POINT.STRIDE`) in their place.
pub fn settings(yaml: &str, path: &Path) -> Result<TrackerConfig> {
    let docs = YamlLoader::load_from_str(yaml).map_err(|e| Error::format(path, format!("not YAML: {e}")))?;
    let doc = docs.first().ok_or_else(|| Error::format(path, "empty YAML document"))?;
    if let Some(arc) = doc["META_ARC"].as_str() {
        if !arc.to_ascii_lowercase().contains("nanotrack") {
            return Err(Error::format(path, format!("META_ARC is `{arc}`, not a NanoTrack config")));
        }
    }
    let mut c = TrackerConfig::nanotrack();
    let real = |section: &str, key: &str, into: &mut f64| -> Result<()> {
        match &doc[section][key] {
            Yaml::BadValue => Ok(()),
            Yaml::Real(_) | Yaml::Integer(_) => {
                *into = doc[section][key]
                    .as_f64()
                    .or_else(|| doc[section][key].as_i64().map(|v| v as f64))
                    .unwrap_or(*into);
                Ok(())
            }
            other => Err(Error::format(path, format!("{section}.{key} is {other:?}, not a number"))),
        }
    };
    let size = |section: &str, key: &str, into: &mut usize| -> Result<()> {
        match &doc[section][key] {
            Yaml::BadValue => Ok(()),
            Yaml::Integer(v) if (1..=4096).contains(v) => {
                *into = *v as usize;
                Ok(())
            }
            other => Err(Error::format(path, format!("{section}.{key} is {other:?}, not a size from 1 to 4096"))),
        }
    };
    real("TRACK", "CONTEXT_AMOUNT", &mut c.context_amount)?;
    real("TRACK", "PENALTY_K", &mut c.penalty_k)?;
    real("TRACK", "WINDOW_INFLUENCE", &mut c.window_influence)?;
    real("TRACK", "LR", &mut c.lr)?;
    size("TRACK", "EXEMPLAR_SIZE", &mut c.exemplar_size)?;
    size("TRACK", "INSTANCE_SIZE", &mut c.instance_size)?;
    size("TRACK", "OUTPUT_SIZE", &mut c.score_size)?;
    size("POINT", "STRIDE", &mut c.stride)?;
    // `generate_points`: ori = -(size // 2) * stride.
    c.grid_origin = -((c.score_size / 2) as f64) * c.stride as f64;
    c.check().map_err(|m| Error::format(path, m))?;
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configv2_gives_the_documented_settings() {
        let yaml = "META_ARC: \"nanotrack\"\nPOINT:\n    STRIDE: 16\nTRACK:\n    WINDOW_INFLUENCE: 0.490\n    PENALTY_K: 0.150\n    LR: 0.385\n    EXEMPLAR_SIZE: 127\n    INSTANCE_SIZE: 255\n    CONTEXT_AMOUNT: 0.5\n";
        let c = settings(yaml, Path::new("configv2.yaml")).unwrap();
        assert_eq!(c, TrackerConfig::nanotrack());
        assert_eq!(c.grid_origin, -128.0);
    }

    #[test]
    fn bad_values_name_the_key() {
        let e = settings("TRACK:\n    LR: fast\n", Path::new("c.yaml")).unwrap_err().to_string();
        assert!(e.starts_with("c.yaml: TRACK.LR"), "{e}");
        let e = settings("TRACK:\n    INSTANCE_SIZE: 0\n", Path::new("c.yaml")).unwrap_err().to_string();
        assert!(e.contains("TRACK.INSTANCE_SIZE"), "{e}");
        let e = settings("META_ARC: siamrpn\n", Path::new("c.yaml")).unwrap_err().to_string();
        assert!(e.contains("not a NanoTrack config"), "{e}");
    }
}
