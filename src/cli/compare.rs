//! `prl compare`: plans side by side (typically fp32 and int8 of one checkpoint): latency run
//! interleaved in one process, output fidelity on held-out crops, tracking agreement and OPE
//! scores on sequences, plan size and peak memory.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;
use prl_runtime::{set_threads, Plan, SearchOutput, Tracker};
use prl_track::{init_box_from_groundtruth, iou, load_frame, ope, CalibrationSpec, Sequence};
use serde::Serialize;

use super::compare_report::markdown;

#[derive(Args)]
pub struct CompareArgs {
    /// Plan directories; the first is the reference the others are measured against.
    #[arg(long = "plan", value_name = "DIR", num_args = 1, required = true)]
    plans: Vec<PathBuf>,
    /// Sequences (OTB/UAV123 layout) for latency, fidelity crops and tracking; keep them apart
    /// from the calibration sequences.
    #[arg(long = "sequence", value_name = "DIR", num_args = 1.., required = true)]
    sequences: Vec<PathBuf>,
    /// Held-out search crops per sequence for the output fidelity.
    #[arg(long, default_value_t = 16, value_name = "N")]
    crops_per_seq: usize,
    /// Timed runs per plan (interleaved) for latency.
    #[arg(long, default_value_t = 20, value_name = "N")]
    runs: usize,
    /// Track at most this many frames of each sequence (default: all).
    #[arg(long, value_name = "N")]
    max_frames: Option<usize>,
    /// Threads for the networks (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Write the report as JSON here.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Write the report as Markdown tables here.
    #[arg(long, value_name = "FILE")]
    markdown: Option<PathBuf>,
}

/// Median and 90th percentile, in milliseconds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Stat {
    /// Median.
    pub median: f64,
    /// 90th percentile.
    pub p90: f64,
}

impl Stat {
    fn of(ms: &[f64]) -> Stat {
        let (median, p90) = super::median_p90(ms);
        Stat { median, p90 }
    }
}

/// One plan: what it is and how fast it runs.
#[derive(Debug, Serialize)]
pub struct PlanReport {
    /// Plan directory as given.
    pub path: String,
    /// `fp32` or `int8`.
    pub precision: String,
    /// Size of the plan's files on disk.
    pub size_mb: f64,
    /// Time `Plan::load` took (read, check, optimise).
    pub load_ms: f64,
    /// Peak resident memory of `prl track` with this plan (10 frames, own process).
    pub peak_rss_mb: Option<f64>,
    /// Sequences the plan was calibrated on (int8 plans).
    pub calibration_sequences: Vec<String>,
    /// Template network per run.
    pub template_ms: Stat,
    /// Search network per run.
    pub search_ms: Stat,
    /// Whole tracking step (crop, search network, post-processing).
    pub step_ms: Stat,
}

/// Outputs of a plan against the reference plan's on the same held-out crops.
#[derive(Debug, Serialize)]
pub struct Fidelity {
    /// Plan directory as given.
    pub plan: String,
    /// Held-out search crops compared.
    pub crops: usize,
    /// Per search output (PRL-Track: loc, cls1, cls2; NanoTrack: cls, loc), its name and
    /// ‖out − ref‖ / ‖ref‖ over all crops.
    pub errors: Vec<(String, f64)>,
    /// Share of crops where the best cell (argmax of the penalised score) is the same.
    pub best_cell_agreement: f64,
}

/// One plan's tracking of one sequence.
#[derive(Debug, Serialize)]
pub struct PlanTrack {
    /// Plan directory as given.
    pub plan: String,
    /// OPE success AUC (when the sequence has ground truth).
    pub auc: Option<f64>,
    /// OPE precision at 20 px.
    pub precision: Option<f64>,
    /// Mean per-frame IoU with the reference plan's boxes (frames after the first).
    pub mean_iou_to_ref: f64,
    /// Share of those frames with IoU over 0.5.
    pub over_05: f64,
    /// Share of those frames with IoU over 0.9.
    pub over_09: f64,
}

/// Every plan's tracking of one sequence.
#[derive(Debug, Serialize)]
pub struct SequenceReport {
    /// Sequence name.
    pub sequence: String,
    /// Frames tracked.
    pub frames: usize,
    /// One entry per plan, the reference first.
    pub plans: Vec<PlanTrack>,
}

/// The whole comparison (`--json` writes it).
#[derive(Debug, Serialize)]
pub struct Report {
    /// Threads the networks ran on.
    pub threads: usize,
    /// Timed runs per plan.
    pub runs: usize,
    /// The plans, the reference first.
    pub plans: Vec<PlanReport>,
    /// Every plan but the first against the first.
    pub fidelity: Vec<Fidelity>,
    /// Tracking, per sequence.
    pub sequences: Vec<SequenceReport>,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn plan_size_mb(dir: &std::path::Path) -> anyhow::Result<f64> {
    let mut bytes = 0;
    for e in std::fs::read_dir(dir).with_context(|| format!("{}: cannot read", dir.display()))? {
        let e = e?;
        if e.file_type()?.is_file() {
            bytes += e.metadata()?.len();
        }
    }
    Ok(bytes as f64 / 1e6)
}

/// Peak resident memory of `prl track` with `plan` on a few frames, in a child process of its
/// own, read from the summary it writes as JSON (`prl track --json`).
fn peak_rss(plan: &std::path::Path, seq: &std::path::Path, threads: usize) -> Option<f64> {
    let exe = std::env::current_exe().ok()?;
    let tmp = tempfile_path("compare-rss");
    let status = std::process::Command::new(exe)
        .args(["track", "--max-frames", "10", "--threads", &threads.to_string(), "--plan"])
        .arg(plan)
        .arg("--sequence")
        .arg(seq)
        .arg("--json")
        .arg(&tmp)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .ok()?;
    let text = std::fs::read_to_string(&tmp).ok();
    let _ = std::fs::remove_file(&tmp);
    if !status.success() {
        return None;
    }
    serde_json::from_str::<super::track::Summary>(&text?).ok()?.peak_rss_mb
}

/// A fresh path in the system's temporary folder.
fn tempfile_path(what: &str) -> std::path::PathBuf {
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
    std::env::temp_dir().join(format!("prl-{what}-{}-{nanos}.json", std::process::id()))
}

pub fn run(a: CompareArgs) -> anyhow::Result<()> {
    if a.runs == 0 || a.crops_per_seq == 0 {
        bail!("--runs and --crops-per-seq must be at least 1");
    }
    let threads = a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    set_threads(threads);
    let seqs = a.sequences.iter().map(|d| Sequence::open(d)).collect::<Result<Vec<_>, _>>()?;
    let first = &seqs[0];
    let gt0 = first.groundtruth().with_context(|| format!("{}: no ground truth", a.sequences[0].display()))?;
    if first.frames.len() < 2 {
        bail!("{}: at least two frames are needed", a.sequences[0].display());
    }
    let mut trackers = vec![];
    let mut reports = vec![];
    for p in &a.plans {
        let t = Instant::now();
        let plan = Plan::load(p)?;
        let load_ms = ms(t);
        let m = plan.manifest().clone();
        if let Some(first) = trackers.first().map(|t: &Tracker| &t.plan().manifest().weights) {
            if (&first.sha256, first.seed) != (&m.weights.sha256, m.weights.seed) {
                eprintln!(
                    "note: {} holds other weights than {}: its differences are not quantisation's",
                    p.display(),
                    a.plans[0].display()
                );
            }
        }
        let calibration_sequences =
            m.quantization.as_ref().map(|q| q.calibration.sequences.clone()).unwrap_or_default();
        trackers.push(Tracker::new(plan, m.tracker.clone()));
        reports.push((p.display().to_string(), m.precision, plan_size_mb(p)?, load_ms, calibration_sequences));
    }
    // Latency: every plan on the same crops, one run of each in turn.
    let (f0, f1) = (load_frame(&first.frames[0])?, load_frame(&first.frames[1])?);
    let init = init_box_from_groundtruth(gt0[0]);
    let mut crops = vec![];
    for t in trackers.iter_mut() {
        t.init(&f0, init)?;
        crops.push((t.exemplar_crop(&f0, init)?, t.search_crop(&f1)?));
    }
    let n = trackers.len();
    let (mut tm, mut sm, mut st) = (vec![vec![]; n], vec![vec![]; n], vec![vec![]; n]);
    let bar = super::progress_bar((a.runs + 2) as u64, "latency (interleaved)");
    for r in 0..a.runs + 2 {
        for (i, t) in trackers.iter_mut().enumerate() {
            let c = Instant::now();
            t.plan().template(&crops[i].0)?;
            let tms = ms(c);
            let feats = t.features().expect("initialised").clone();
            let c = Instant::now();
            t.plan().search(&crops[i].1, &feats)?;
            let sms = ms(c);
            let c = Instant::now();
            t.track(&f1)?;
            let stms = ms(c);
            if r >= 2 {
                tm[i].push(tms);
                sm[i].push(sms);
                st[i].push(stms);
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let fidelity = fidelity(&a, &seqs, &mut trackers)?;
    let sequences = tracking(&a, &seqs, &mut trackers)?;
    let plans = reports
        .into_iter()
        .enumerate()
        .map(|(i, (path, precision, size_mb, load_ms, calibration_sequences))| PlanReport {
            peak_rss_mb: peak_rss(&a.plans[i], &a.sequences[0], threads),
            path,
            precision,
            size_mb,
            load_ms,
            calibration_sequences,
            template_ms: Stat::of(&tm[i]),
            search_ms: Stat::of(&sm[i]),
            step_ms: Stat::of(&st[i]),
        })
        .collect();
    let report = Report { threads, runs: a.runs, plans, fidelity, sequences };
    print!("{}", markdown(&report));
    if let Some(p) = &a.json {
        super::write_atomically(p, serde_json::to_string_pretty(&report)?.as_bytes())?;
    }
    if let Some(p) = &a.markdown {
        super::write_atomically(p, markdown(&report).as_bytes())?;
    }
    Ok(())
}

/// Output fidelity of every plan against the first on held-out search crops.
fn fidelity(a: &CompareArgs, seqs: &[Sequence], trackers: &mut [Tracker]) -> anyhow::Result<Vec<Fidelity>> {
    let config = trackers[0].plan().manifest().tracker.clone();
    let spec = CalibrationSpec {
        sequences: a.sequences.clone(),
        frames_per_sequence: a.crops_per_seq,
        // What tracking sees: the trackers start on each sequence's first frame.
        templates_per_sequence: 1,
        seed: 1,
        held_out: true,
    };
    let crops = super::crops_with_progress(&spec, &config, "cutting held-out crops")?;
    let n = trackers.len();
    let mut outs: Vec<Vec<SearchOutput>> = vec![vec![]; n];
    let mut cells: Vec<Vec<usize>> = vec![vec![]; n];
    let bar = super::progress_bar(crops.searches.len() as u64, "output fidelity");
    let mut current = usize::MAX;
    let mut size = (0, 0);
    for (t, x) in &crops.searches {
        if *t != current {
            // Trackers start on this crop's sequence, as tracking would.
            current = *t;
            let seq = &seqs[*t];
            let f0 = load_frame(&seq.frames[0])?;
            size = (f0.width(), f0.height());
            let init = init_box_from_groundtruth(seq.groundtruth().expect("crops need ground truth")[0]);
            for tr in trackers.iter_mut() {
                tr.init(&f0, init)?;
            }
        }
        for (i, tr) in trackers.iter().enumerate() {
            let out = tr.plan().search(&x.data, tr.features().expect("initialised"))?;
            cells[i].push(tr.best_cell(size.0, size.1, &out)?);
            outs[i].push(out);
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let flat = |i: usize, k: usize| -> Vec<f32> { outs[i].iter().flat_map(|o| &o.outputs[k]).copied().collect() };
    let names: Vec<String> = trackers[0].plan().manifest().search.outputs.iter().map(|o| o.name.clone()).collect();
    Ok((1..n)
        .map(|i| {
            let same = cells[i].iter().zip(&cells[0]).filter(|(a, b)| a == b).count();
            Fidelity {
                plan: a.plans[i].display().to_string(),
                crops: outs[i].len(),
                errors: (names.iter().enumerate())
                    .map(|(k, name)| (name.clone(), prl_compiler::relative_error(&flat(i, k), &flat(0, k)).0))
                    .collect(),
                best_cell_agreement: same as f64 / cells[0].len().max(1) as f64,
            }
        })
        .collect())
}

/// Track each sequence with every plan; agreement with the first plan and OPE scores.
fn tracking(a: &CompareArgs, seqs: &[Sequence], trackers: &mut [Tracker]) -> anyhow::Result<Vec<SequenceReport>> {
    let mut out = vec![];
    for (dir, seq) in a.sequences.iter().zip(seqs) {
        let gt = seq.groundtruth().with_context(|| format!("{}: no ground truth", dir.display()))?;
        let count = a.max_frames.map_or(seq.frames.len(), |m| m.min(seq.frames.len()));
        let init = init_box_from_groundtruth(gt[0]);
        let mut boxes: Vec<Vec<[f64; 4]>> = vec![];
        for (i, tr) in trackers.iter_mut().enumerate() {
            let msg = format!("tracking {} with {}", seq.name, a.plans[i].display());
            let run = super::track::track_with_progress(tr, &seq.frames[..count], init, |_, _, _| Ok(()));
            boxes.push(run.with_context(|| msg)?.xywh());
        }
        let plans = boxes
            .iter()
            .enumerate()
            .map(|(i, b)| {
                let ious: Vec<f64> = b.iter().zip(&boxes[0]).skip(1).map(|(x, y)| iou(*x, *y)).collect();
                let share = |t: f64| ious.iter().filter(|&&v| v > t).count() as f64 / ious.len().max(1) as f64;
                let curves = ope::evaluate(&gt[..count], b).ok();
                PlanTrack {
                    plan: a.plans[i].display().to_string(),
                    auc: curves.as_ref().map(|c| c.auc()),
                    precision: curves.as_ref().map(|c| c.precision_at_20()),
                    mean_iou_to_ref: ope::mean(&ious),
                    over_05: share(0.5),
                    over_09: share(0.9),
                }
            })
            .collect();
        out.push(SequenceReport { sequence: seq.name.clone(), frames: count, plans });
    }
    Ok(out)
}
