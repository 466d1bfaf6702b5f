//! Tracking benchmarks on disk: the layouts of OTB / DTB70, UAV123 (raw and pysot JSON),
//! UAV123@10fps, UAV20L, UAVTrack112, UAVTrack112_L and GOT-10k. Reading a dataset lists frame
//! files and parses annotations; no image is decoded.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::sequence::{parse_boxes, read_text_bounded, InputError, Sequence};

/// The layout of a dataset folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Work it out from the files present.
    Auto,
    /// OTB / DTB70 / UAV123@10fps-as-folders: `<seq>/img/*.jpg`, `<seq>/groundtruth_rect.txt`.
    Otb,
    /// UAV123 / UAV20L raw: `anno/<SET>/<seq>.txt`, `data_seq/<SET>/<seq>/` (and `anno/<SET>/att/`).
    Uav123,
    /// UAVTrack112: `data_seq/<seq>/`, `anno/<seq>.txt`.
    Uav112,
    /// UAVTrack112_L: `data_seq/<seq>/`, `anno_l/<seq>.txt`.
    Uav112l,
    /// GOT-10k: `<seq>/*.jpg`, `<seq>/groundtruth.txt`.
    Got10k,
    /// pysot-toolkit JSON: `<root>/<NAME>.json` with `img_names`, `gt_rect`, `init_rect`, `attr`.
    PysotJson,
}

/// One video of a dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct Video {
    /// Name results are stored under (`<name>.txt`).
    pub name: String,
    /// Frame files in order.
    pub frames: Vec<PathBuf>,
    /// Ground truth `x,y,w,h` per frame (NaN where the target is absent).
    pub groundtruth: Vec<[f64; 4]>,
    /// The box tracking starts from.
    pub init: [f64; 4],
    /// Attributes the dataset gives this video.
    pub attributes: Vec<String>,
}

/// A dataset: its name and its videos, sorted by name.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// Name (the JSON file's stem, the UAV123 set, or the folder's name).
    pub name: String,
    /// Videos sorted by name.
    pub videos: Vec<Video>,
}

/// UAV123's twelve attributes, in the order of its `att/<seq>.txt` flags.
pub const UAV123_ATTRIBUTES: [&str; 12] = [
    "Scale Variation",
    "Aspect Ratio Change",
    "Low Resolution",
    "Fast Motion",
    "Full Occlusion",
    "Partial Occlusion",
    "Out-of-View",
    "Background Clutter",
    "Illumination Variation",
    "Viewpoint Change",
    "Camera Motion",
    "Similar Object",
];

fn err(path: &Path, msg: impl Into<String>) -> InputError {
    InputError::new(path, msg)
}

fn subdirs(dir: &Path) -> Result<Vec<PathBuf>, InputError> {
    let rd = std::fs::read_dir(dir).map_err(|e| err(dir, format!("cannot read folder: {e}")))?;
    let mut out: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    out.sort();
    Ok(out)
}

fn name_of(p: &Path) -> String {
    p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

fn video(name: String, frames: Vec<PathBuf>, groundtruth: Vec<[f64; 4]>, anno: &Path) -> Result<Video, InputError> {
    let init = *groundtruth.first().ok_or_else(|| err(anno, "no ground-truth box"))?;
    Ok(Video { name, frames, groundtruth, init, attributes: vec![] })
}

impl Dataset {
    /// Read the dataset at `root` in layout `format` (or the one its files show).
    pub fn open(root: &Path, format: Format) -> Result<Dataset, InputError> {
        if !root.is_dir() {
            return Err(err(root, "not a folder"));
        }
        let format = if format == Format::Auto { detect(root)? } else { format };
        let mut d = match format {
            Format::Auto => unreachable!("detected above"),
            Format::Otb | Format::Got10k => folders(root)?,
            Format::Uav123 => uav123(root)?,
            Format::Uav112 => uav112(root, "anno")?,
            Format::Uav112l => uav112(root, "anno_l")?,
            Format::PysotJson => pysot_json(root)?,
        };
        if d.videos.is_empty() {
            return Err(err(root, format!("no video found in the {format:?} layout")));
        }
        d.videos.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(d)
    }

    /// The attributes present, each with the videos that have it.
    pub fn attributes(&self) -> BTreeMap<String, Vec<String>> {
        let mut out: BTreeMap<String, Vec<String>> = BTreeMap::new();
        for v in &self.videos {
            for a in &v.attributes {
                out.entry(a.clone()).or_default().push(v.name.clone());
            }
        }
        out
    }
}

/// The layout of `root`, from the files it holds.
pub fn detect(root: &Path) -> Result<Format, InputError> {
    if json_file(root)?.is_some() {
        return Ok(Format::PysotJson);
    }
    if root.join("data_seq").is_dir() {
        let anno = root.join("anno");
        if anno.is_dir() {
            let nested = subdirs(&anno)?.iter().any(|d| name_of(d) != "att");
            return Ok(if nested { Format::Uav123 } else { Format::Uav112 });
        }
        if root.join("anno_l").is_dir() {
            return Ok(Format::Uav112l);
        }
    }
    for d in subdirs(root)? {
        if d.join("groundtruth_rect.txt").is_file()
            || d.join("groundtruth_rect.1.txt").is_file()
            || d.join("img").is_dir()
        {
            return Ok(Format::Otb);
        }
        if d.join("groundtruth.txt").is_file() {
            return Ok(Format::Got10k);
        }
    }
    Err(err(root, "unknown dataset layout: expected a pysot JSON, data_seq/ with anno/ or anno_l/, or one folder per sequence with its ground truth (pass --format)"))
}

/// OTB / DTB70 / GOT-10k: one folder per sequence. A folder with several targets (OTB's
/// `groundtruth_rect.1.txt`, `.2.txt`) gives one video per target, named as pysot-toolkit's OTB
/// names them: `Jogging-1`, `Jogging-2`.
fn folders(root: &Path) -> Result<Dataset, InputError> {
    let mut videos = vec![];
    for d in subdirs(root)? {
        let s = Sequence::open(&d)?;
        let several = s.targets.len() > 1;
        for t in s.targets {
            let name = match t.number {
                Some(n) if several => format!("{}-{n}", s.name),
                _ => s.name.clone(),
            };
            videos.push(video(name, s.frames.clone(), t.boxes, &t.file)?);
        }
    }
    Ok(Dataset { name: name_of(root), videos })
}

fn frame_files(dir: &Path) -> Result<Vec<PathBuf>, InputError> {
    Sequence::list_frames(dir)
}

/// UAV123 / UAV20L raw: `anno/<SET>/<seq>.txt` beside `data_seq/<SET>/<seq>/`.
fn uav123(root: &Path) -> Result<Dataset, InputError> {
    let sets: Vec<PathBuf> = subdirs(&root.join("anno"))?;
    let set = match sets.as_slice() {
        [one] => one.clone(),
        _ => return Err(err(&root.join("anno"), "expected exactly one set folder (UAV123, UAV20L, ...)")),
    };
    let set_name = name_of(&set);
    let mut videos = vec![];
    let mut files: Vec<PathBuf> = std::fs::read_dir(&set)
        .map_err(|e| err(&set, format!("cannot read folder: {e}")))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "txt"))
        .collect();
    files.sort();
    for anno in files {
        let name = anno.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let dir = root.join("data_seq").join(&set_name).join(&name);
        if !dir.is_dir() {
            return Err(err(
                &anno,
                format!(
                    "no frame folder {} for it: a sub-sequence's frame range cannot be known from the files; use the pysot JSON (--format pysot-json)",
                    dir.display()
                ),
            ));
        }
        let frames = frame_files(&dir)?;
        let boxes = parse_boxes(&anno, frames.len())?;
        let mut v = video(name.clone(), frames, boxes, &anno)?;
        let att = set.join("att").join(format!("{name}.txt"));
        if att.is_file() {
            v.attributes = uav123_attributes(&att)?;
        }
        videos.push(v);
    }
    Ok(Dataset { name: set_name, videos })
}

fn uav123_attributes(path: &Path) -> Result<Vec<String>, InputError> {
    let text = read_text_bounded(path, 4096, "an attribute file")?;
    let flags: Vec<&str> = text.split([',', ' ', '\t', '\n', '\r']).filter(|f| !f.is_empty()).collect();
    if flags.len() != UAV123_ATTRIBUTES.len() || flags.iter().any(|f| *f != "0" && *f != "1") {
        return Err(err(path, format!("expected {} attribute flags (0 or 1)", UAV123_ATTRIBUTES.len())));
    }
    Ok(flags.iter().zip(UAV123_ATTRIBUTES).filter(|(f, _)| **f == "1").map(|(_, a)| a.to_string()).collect())
}

/// UAVTrack112 (`anno/`) and UAVTrack112_L (`anno_l/`): `data_seq/<seq>/` frames.
fn uav112(root: &Path, anno_dir: &str) -> Result<Dataset, InputError> {
    let mut videos = vec![];
    for dir in subdirs(&root.join("data_seq"))? {
        let name = name_of(&dir);
        let anno = root.join(anno_dir).join(format!("{name}.txt"));
        if !anno.is_file() {
            continue; // UAVTrack112_L annotates only the long sequences
        }
        let frames = frame_files(&dir)?;
        let boxes = parse_boxes(&anno, frames.len())?;
        videos.push(video(name, frames, boxes, &anno)?);
    }
    let name = if anno_dir == "anno_l" { format!("{}_L", name_of(root)) } else { name_of(root) };
    Ok(Dataset { name, videos })
}

fn json_file(root: &Path) -> Result<Option<PathBuf>, InputError> {
    let rd = std::fs::read_dir(root).map_err(|e| err(root, format!("cannot read folder: {e}")))?;
    let mut jsons: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == "json"))
        .collect();
    jsons.sort();
    Ok(jsons.into_iter().next())
}

/// The largest pysot dataset JSON read: a bound far above any benchmark's, so that a huge file
/// is refused before it is read.
pub const MAX_DATASET_JSON: u64 = 512 << 20;

/// pysot-toolkit JSON: `{video: {img_names, gt_rect, init_rect, attr}}`, frames relative to root.
fn pysot_json(root: &Path) -> Result<Dataset, InputError> {
    let path = json_file(root)?.ok_or_else(|| err(root, "no .json file"))?;
    let text = read_text_bounded(&path, MAX_DATASET_JSON, "a dataset JSON")?;
    parse_pysot_json(root, &path, &text)
}

/// A pysot dataset JSON (`{video: {img_names, gt_rect, init_rect, attr}}`) already read from
/// `path`, its frames relative to `root`.
pub fn parse_pysot_json(root: &Path, path: &Path, text: &str) -> Result<Dataset, InputError> {
    // Python's json writes NaN for absent targets; JSON has no NaN.
    let text = text.replace("NaN", "null");
    let doc: BTreeMap<String, serde_json::Value> =
        serde_json::from_str(&text).map_err(|e| err(path, format!("not a pysot dataset JSON: {e}")))?;
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let boxes = |v: &serde_json::Value, what: &str| -> Result<Vec<[f64; 4]>, InputError> {
        v.as_array()
            .ok_or_else(|| err(path, format!("{what}: expected a list of boxes")))?
            .iter()
            .enumerate()
            .map(|(i, b)| match b.as_array().map(Vec::as_slice) {
                Some([x, y, w, h]) => Ok([num(x), num(y), num(w), num(h)]),
                _ => Err(err(path, format!("{what}[{i}]: expected [x, y, w, h]"))),
            })
            .collect()
    };
    let mut videos = vec![];
    for (name, v) in &doc {
        let imgs = v["img_names"].as_array().ok_or_else(|| err(path, format!("{name}: no img_names")))?;
        let frames = imgs.iter().map(|p| root.join(p.as_str().unwrap_or_default())).collect();
        let groundtruth = boxes(&v["gt_rect"], &format!("{name}.gt_rect"))?;
        let init = match v["init_rect"].as_array().map(Vec::as_slice) {
            Some([x, y, w, h]) => [num(x), num(y), num(w), num(h)],
            _ => *groundtruth.first().ok_or_else(|| err(path, format!("{name}: no boxes")))?,
        };
        let attributes = v["attr"]
            .as_array()
            .map(|a| a.iter().filter_map(|s| s.as_str().map(str::to_string)).collect())
            .unwrap_or_default();
        videos.push(Video { name: name.clone(), frames, groundtruth, init, attributes });
    }
    let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    Ok(Dataset { name, videos })
}
