//! Frame sequences: OTB / UAV123 style folders (`img/`, `groundtruth_rect.txt`) or bare frame
//! folders, and box files.

use std::path::{Path, PathBuf};

use prl_runtime::BBox;

/// Bad input, naming the file.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {msg}")]
pub struct InputError {
    /// The offending file or folder.
    pub path: PathBuf,
    /// What is wrong.
    pub msg: String,
}

impl InputError {
    /// An error about `path`.
    pub fn new(path: &Path, msg: impl Into<String>) -> Self {
        InputError { path: path.to_path_buf(), msg: msg.into() }
    }
}

/// Read all of `path`, refusing a file longer than `limit` bytes before its contents are
/// allocated (the length is checked from the file system first, then the read stops one byte
/// past the limit, for files whose length the file system does not know, such as pipes).
pub fn read_bounded(path: &Path, limit: u64, what: &str) -> Result<Vec<u8>, InputError> {
    use std::io::Read;
    let too_long = |n: u64| InputError::new(path, format!("{n} bytes: too long for {what} (at most {limit})"));
    let file = std::fs::File::open(path).map_err(|e| InputError::new(path, format!("cannot read: {e}")))?;
    let declared = file.metadata().map(|m| m.len()).unwrap_or(0);
    if declared > limit {
        return Err(too_long(declared));
    }
    let mut bytes = Vec::with_capacity(declared as usize);
    file.take(limit + 1).read_to_end(&mut bytes).map_err(|e| InputError::new(path, format!("cannot read: {e}")))?;
    if bytes.len() as u64 > limit {
        return Err(too_long(bytes.len() as u64));
    }
    Ok(bytes)
}

/// [`read_bounded`] as UTF-8 text.
pub fn read_text_bounded(path: &Path, limit: u64, what: &str) -> Result<String, InputError> {
    String::from_utf8(read_bounded(path, limit, what)?)
        .map_err(|e| InputError::new(path, format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to())))
}

/// The longest box file taken for `frames` frames: 1 MiB plus 1 KiB a frame (a box line is
/// about 40 bytes; ground truth may run past the frames it describes).
pub fn box_file_limit(frames: usize) -> u64 {
    (1 << 20) + 1024 * frames as u64
}

/// A sequence: its frames in order and, when known, one ground-truth box per frame for each
/// of its targets.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Folder name.
    pub name: String,
    /// Frame files, sorted by name.
    pub frames: Vec<PathBuf>,
    /// The ground truth of each target, in the order of their files' numbers; empty when the
    /// folder has none.
    pub targets: Vec<GroundTruth>,
}

/// One target's ground truth in a sequence folder.
#[derive(Debug, Clone)]
pub struct GroundTruth {
    /// The file it was read from.
    pub file: PathBuf,
    /// The number in an OTB-style `groundtruth_rect.<N>.txt` name (`None` for
    /// `groundtruth_rect.txt` or `groundtruth.txt`).
    pub number: Option<u32>,
    /// `x,y,w,h` per frame (NaN rows where the target is absent).
    pub boxes: Vec<[f64; 4]>,
}

/// Most ground-truth files one sequence folder may hold (one per target).
pub const MAX_GROUNDTRUTH_FILES: usize = 64;

const FRAME_EXTENSIONS: [&str; 5] = ["jpg", "jpeg", "png", "bmp", "webp"];

impl Sequence {
    /// An OTB/UAV123-style folder: frames in `img/` (or the folder itself), ground truth in
    /// `groundtruth_rect.txt` (or `groundtruth.txt`); a folder with several targets, as OTB's
    /// `Jogging` and `Skating2`, has one `groundtruth_rect.<N>.txt` per target instead.
    pub fn open(dir: &Path) -> Result<Sequence, InputError> {
        let img = dir.join("img");
        let frames = Self::list_frames(if img.is_dir() { &img } else { dir })?;
        let mut targets = vec![];
        for (file, number) in Self::groundtruth_files(dir)? {
            let boxes = parse_boxes(&file, frames.len())?;
            if boxes.len() < frames.len() {
                return Err(InputError::new(&file, format!("{} boxes for {} frames", boxes.len(), frames.len())));
            }
            targets.push(GroundTruth { file, number, boxes });
        }
        let name =
            dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| dir.display().to_string());
        Ok(Sequence { name, frames, targets })
    }

    /// The first target's boxes, if the sequence has ground truth.
    pub fn groundtruth(&self) -> Option<&Vec<[f64; 4]>> {
        self.targets.first().map(|t| &t.boxes)
    }

    /// The ground-truth files of the sequence folder `dir`, each with its number:
    /// `groundtruth_rect.txt` or `groundtruth.txt` where there is one, else every
    /// `groundtruth_rect.<N>.txt` in the order of N (empty when there is none).
    pub fn groundtruth_files(dir: &Path) -> Result<Vec<(PathBuf, Option<u32>)>, InputError> {
        if let Some(p) = ["groundtruth_rect.txt", "groundtruth.txt"].iter().map(|n| dir.join(n)).find(|p| p.is_file()) {
            return Ok(vec![(p, None)]);
        }
        let entries = std::fs::read_dir(dir).map_err(|e| InputError::new(dir, format!("cannot list: {e}")))?;
        let mut numbered: Vec<(u32, PathBuf)> = vec![];
        for path in entries.filter_map(|e| e.ok().map(|e| e.path())) {
            let number = path
                .file_name()
                .and_then(|n| n.to_str())
                .and_then(|n| n.strip_prefix("groundtruth_rect.")?.strip_suffix(".txt")?.parse::<u32>().ok());
            if let Some(n) = number.filter(|_| path.is_file()) {
                if numbered.len() == MAX_GROUNDTRUTH_FILES {
                    return Err(InputError::new(
                        dir,
                        format!("more than {MAX_GROUNDTRUTH_FILES} groundtruth_rect.<N>.txt files (one per target)"),
                    ));
                }
                numbered.push((n, path));
            }
        }
        numbered.sort_by_key(|(n, _)| *n);
        if let Some(w) = numbered.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err(InputError::new(&w[1].1, format!("a second ground-truth file of target {}", w[1].0)));
        }
        Ok(numbered.into_iter().map(|(n, path)| (path, Some(n))).collect())
    }

    /// The image files of a folder, sorted by name.
    pub fn list_frames(dir: &Path) -> Result<Vec<PathBuf>, InputError> {
        let entries = std::fs::read_dir(dir).map_err(|e| InputError::new(dir, format!("cannot list frames: {e}")))?;
        let mut frames: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| FRAME_EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
            })
            .collect();
        frames.sort();
        if frames.is_empty() {
            return Err(InputError::new(dir, "no frames (jpg, png, bmp, webp) in this folder"));
        }
        Ok(frames)
    }
}

/// Parse a box file describing `frames` frames (a longer file than [`box_file_limit`] allows
/// is refused before it is read): one `x,y,w,h` per line, separated by commas, tabs or spaces;
/// integers or floats; `NaN` rows kept. Blank lines are skipped; anything else malformed is an
/// error naming the file and line.
pub fn parse_boxes(path: &Path, frames: usize) -> Result<Vec<[f64; 4]>, InputError> {
    let text = read_text_bounded(path, box_file_limit(frames), &format!("a box file of {frames} frames"))?;
    parse_boxes_text(path, &text)
}

/// [`parse_boxes`] on text already read; `path` names it in errors.
pub fn parse_boxes_text(path: &Path, text: &str) -> Result<Vec<[f64; 4]>, InputError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        out.push(parse_box(line).map_err(|m| InputError::new(path, format!("line {}: {m}", i + 1)))?);
    }
    Ok(out)
}

/// Parse one `x,y,w,h` box (commas, tabs or spaces).
pub fn parse_box(line: &str) -> Result<[f64; 4], String> {
    let fields: Vec<&str> = line.split([',', '\t', ' ']).map(str::trim).filter(|f| !f.is_empty()).collect();
    if fields.len() != 4 {
        return Err(format!("expected 4 numbers x,y,w,h, found {:?}", line.trim()));
    }
    let mut b = [0f64; 4];
    for (slot, f) in b.iter_mut().zip(&fields) {
        *slot = f.parse().map_err(|_| format!("`{f}` is not a number"))?;
    }
    Ok(b)
}

/// The box the official `tools/test.py` hands to `init` for a ground-truth `x,y,w,h`:
/// `[cx - (w-1)/2, cy - (h-1)/2, w, h]` with `cx = x + w/2`, `cy = y + h/2`.
pub fn init_box_from_groundtruth(gt: [f64; 4]) -> BBox {
    let [x, y, w, h] = gt;
    let (cx, cy) = (x + w / 2.0, y + h / 2.0);
    BBox { x: cx - (w - 1.0) / 2.0, y: cy - (h - 1.0) / 2.0, w, h }
}
