//! `prl eval`: score trackers' result folders on a dataset as pysot-toolkit does (OPE), and with
//! VOT-LT's long-term figures where the target is absent on some frames.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use prl_track::longterm;
use prl_track::ope::{evaluate, summarise, Curves, Summary};
use prl_track::{parse_boxes, Dataset, Format};
use serde::Serialize;

use super::plots::{plot, Curve, Kind};
use super::write_atomically;

#[derive(Args)]
pub struct EvalArgs {
    /// Dataset folder.
    #[arg(long, value_name = "ROOT")]
    dataset: PathBuf,
    /// Dataset layout.
    #[arg(long, value_enum, default_value = "auto")]
    format: Format,
    /// Results folder: `<tracker>/<video>.txt` in it, or in its `<dataset name>/` subfolder.
    #[arg(long, value_name = "DIR")]
    results: PathBuf,
    /// Trackers to score (default: every folder of results).
    #[arg(long, num_args = 1.., value_name = "NAME")]
    trackers: Vec<String>,
    /// Also print one table per attribute of the dataset.
    #[arg(long)]
    attributes: bool,
    /// Also print the per-video table.
    #[arg(long)]
    per_video: bool,
    /// Write success and precision plots (PNG and SVG) to DIR, per attribute too with
    /// `--attributes`.
    #[arg(long, value_name = "DIR")]
    plots: Option<PathBuf>,
    /// Also write every figure and curve as JSON.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
}

/// One tracker's scores.
#[derive(Serialize)]
struct TrackerReport {
    name: String,
    success: f64,
    norm_precision: f64,
    precision: f64,
    success_curve: Vec<f64>,
    precision_curve: Vec<f64>,
    norm_precision_curve: Vec<f64>,
    videos: BTreeMap<String, Scores>,
    attributes: BTreeMap<String, Scores>,
    #[serde(skip)]
    attribute_curves: BTreeMap<String, Summary>,
    /// VOT-LT figures, where the dataset has frames without the target and the results have
    /// confidences.
    #[serde(skip_serializing_if = "Option::is_none")]
    long_term: Option<LongTerm>,
}

/// A tracker's long-term figures at its best threshold, and the curves over every threshold.
#[derive(Serialize)]
struct LongTerm {
    precision: f64,
    recall: f64,
    f_score: f64,
    threshold: f64,
    thresholds: Vec<f64>,
    precision_curve: Vec<f64>,
    recall_curve: Vec<f64>,
}

/// The long-term figures of the results in `dir` (`None`, with a note, when a video has no
/// confidences file).
/// `results` are the boxes [`score`] read, by video.
fn long_term(
    dataset: &Dataset,
    dir: &Path,
    name: &str,
    results: &BTreeMap<String, Vec<[f64; 4]>>,
) -> anyhow::Result<Option<LongTerm>> {
    let mut per_video = vec![];
    for v in &dataset.videos {
        let boxes = dir.join(format!("{}.txt", v.name));
        let path = longterm::confidence_path(&boxes);
        if !path.is_file() {
            println!("{name}: no {} (results without confidences): no long-term figures", path.display());
            return Ok(None);
        }
        let n = v.groundtruth.len();
        let text = prl_track::read_text_bounded(&path, prl_track::box_file_limit(n), "a confidences file")?;
        let mut conf = longterm::parse_confidences(&text, n).map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
        // pysot reads the init frame's confidence as NaN.
        if let Some(c) = conf.first_mut() {
            *c = f64::NAN;
        }
        let first = v.frames.first().ok_or_else(|| anyhow::anyhow!("video {}: no frames", v.name))?;
        let (w, h) = image::image_dimensions(first)
            .with_context(|| format!("{}: cannot read the frame's size", first.display()))?;
        per_video.push((&results[&v.name], conf, (f64::from(w), f64::from(h)), v));
    }
    let all: Vec<f64> = per_video.iter().flat_map(|p| p.1.iter().copied()).collect();
    let thresholds = longterm::thresholds(&all);
    let curves = per_video
        .iter()
        .map(|(pred, conf, bounds, v)| {
            longterm::video_curves(&v.groundtruth, pred, conf, *bounds, &thresholds)
                .map_err(|m| anyhow::anyhow!("{}: {m}", dir.join(format!("{}.txt", v.name)).display()))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let s = longterm::summarise(thresholds, &curves);
    let (precision, recall, f_score, threshold) = s.at_best();
    Ok(Some(LongTerm {
        precision,
        recall,
        f_score,
        threshold,
        thresholds: s.thresholds,
        precision_curve: s.precision,
        recall_curve: s.recall,
    }))
}

#[derive(Serialize, Clone, Copy)]
struct Scores {
    success: f64,
    norm_precision: f64,
    precision: f64,
}

impl From<&Summary> for Scores {
    fn from(s: &Summary) -> Self {
        Scores { success: s.auc, norm_precision: s.norm_precision_at_02, precision: s.precision_at_20 }
    }
}

#[derive(Serialize)]
struct Report {
    dataset: String,
    videos: usize,
    trackers: Vec<TrackerReport>,
}

/// The folder holding the trackers' result folders.
fn results_root(results: &Path, dataset: &str) -> PathBuf {
    let nested = results.join(dataset);
    if nested.is_dir() {
        nested
    } else {
        results.to_path_buf()
    }
}

fn tracker_names(root: &Path) -> anyhow::Result<Vec<String>> {
    let rd = std::fs::read_dir(root).with_context(|| format!("{}: cannot read the results folder", root.display()))?;
    let mut names: Vec<String> = rd
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    anyhow::ensure!(!names.is_empty(), "{}: no tracker result folders in it", root.display());
    Ok(names)
}

/// Score one tracker: its curves per video, and the boxes read, per video.
type Scored = (BTreeMap<String, Curves>, BTreeMap<String, Vec<[f64; 4]>>);
fn score(dataset: &Dataset, dir: &Path) -> anyhow::Result<Scored> {
    let (mut out, mut results) = (BTreeMap::new(), BTreeMap::new());
    for v in &dataset.videos {
        let path = dir.join(format!("{}.txt", v.name));
        anyhow::ensure!(path.is_file(), "{}: missing (video {} of {})", path.display(), v.name, dataset.name);
        let result = parse_boxes(&path, v.groundtruth.len())?;
        let curves = evaluate(&v.groundtruth, &result).map_err(|m| anyhow::anyhow!("{}: {m}", path.display()))?;
        out.insert(v.name.clone(), curves);
        results.insert(v.name.clone(), result);
    }
    Ok((out, results))
}

fn table(title: &str, rows: &[(String, Scores)]) {
    let w = rows.iter().map(|r| r.0.len()).max().unwrap_or(0).max(12) + 2;
    let header = format!("|{:^w$}|{:^9}|{:^16}|{:^11}|", "Tracker name", "Success", "Norm Precision", "Precision");
    if !title.is_empty() {
        println!("{title}");
    }
    println!("{}\n{header}\n{}", "-".repeat(header.len()), "-".repeat(header.len()));
    for (name, s) in rows {
        println!("|{:^w$}|{:^9.3}|{:^16.3}|{:^11.3}|", name, s.success, s.norm_precision, s.precision);
    }
    println!("{}", "-".repeat(header.len()));
}

/// VOT-LT's table: precision, recall and F-score at each tracker's best threshold, best first.
fn long_term_table(reports: &[TrackerReport]) {
    let mut rows: Vec<(&str, &LongTerm)> =
        reports.iter().filter_map(|r| r.long_term.as_ref().map(|l| (r.name.as_str(), l))).collect();
    rows.sort_by(|x, y| y.1.f_score.total_cmp(&x.1.f_score));
    let w = rows.iter().map(|r| r.0.len()).max().unwrap_or(0).max(12) + 2;
    let header = format!("|{:^w$}|{:^11}|{:^8}|{:^7}|{:^11}|", "Tracker name", "Precision", "Recall", "F", "threshold");
    println!("\nlong-term (VOT-LT: precision, recall and F-score at the threshold of the best F; frames without the target count)");
    println!("{}\n{header}\n{}", "-".repeat(header.len()), "-".repeat(header.len()));
    for (name, l) in rows {
        println!("|{:^w$}|{:^11.3}|{:^8.3}|{:^7.3}|{:^11.4}|", name, l.precision, l.recall, l.f_score, l.threshold);
    }
    println!("{}", "-".repeat(header.len()));
}

pub fn run(a: EvalArgs) -> anyhow::Result<()> {
    let dataset = Dataset::open(&a.dataset, a.format)?;
    let root = results_root(&a.results, &dataset.name);
    let names = if a.trackers.is_empty() { tracker_names(&root)? } else { a.trackers.clone() };
    let attrs = dataset.attributes();
    // Long-term figures where the target leaves the view on some frame (NaN ground truth).
    let absent = dataset.videos.iter().any(|v| v.groundtruth.iter().any(|g| !longterm::present(*g)));
    let mut reports = vec![];
    for name in &names {
        let (per_video, results) = score(&dataset, &root.join(name))?;
        let all = summarise(per_video.values());
        let videos = per_video.iter().map(|(v, c)| (v.clone(), Scores::from(&summarise([c])))).collect();
        let attribute_curves: BTreeMap<String, Summary> =
            attrs.iter().map(|(attr, vids)| (attr.clone(), summarise(vids.iter().map(|v| &per_video[v])))).collect();
        let attributes = attribute_curves.iter().map(|(a, s)| (a.clone(), Scores::from(s))).collect();
        reports.push(TrackerReport {
            name: name.clone(),
            success: all.auc,
            norm_precision: all.norm_precision_at_02,
            precision: all.precision_at_20,
            success_curve: all.success.clone(),
            precision_curve: all.precision.clone(),
            norm_precision_curve: all.norm_precision.clone(),
            videos,
            attributes,
            attribute_curves,
            long_term: if absent { long_term(&dataset, &root.join(name), name, &results)? } else { None },
        });
    }
    // pysot's order: success, best first.
    reports.sort_by(|x, y| y.success.total_cmp(&x.success));
    println!(
        "{}: {} videos, {} tracker(s) (OPE, pysot-toolkit definitions)",
        dataset.name,
        dataset.videos.len(),
        reports.len()
    );
    let rows: Vec<(String, Scores)> = reports
        .iter()
        .map(|r| {
            (r.name.clone(), Scores { success: r.success, norm_precision: r.norm_precision, precision: r.precision })
        })
        .collect();
    table("", &rows);
    if absent {
        long_term_table(&reports);
    }
    if a.attributes {
        for (attr, vids) in &attrs {
            let mut rows: Vec<(String, Scores)> =
                reports.iter().map(|r| (r.name.clone(), r.attributes[attr])).collect();
            rows.sort_by(|x, y| y.1.success.total_cmp(&x.1.success));
            table(&format!("\n{attr} ({} videos)", vids.len()), &rows);
        }
        if attrs.is_empty() {
            println!("\n{} gives no attributes", dataset.name);
        }
    }
    if a.per_video {
        println!("\n{:<24}{}", "video", reports.iter().map(|r| format!("{:>22}", r.name)).collect::<String>());
        println!(
            "{:<24}{}",
            "",
            reports.iter().map(|_| format!("{:>11}{:>11}", "success", "prec@20")).collect::<String>()
        );
        for v in &dataset.videos {
            let cells: String = reports
                .iter()
                .map(|r| format!("{:>11.3}{:>11.3}", r.videos[&v.name].success, r.videos[&v.name].precision))
                .collect();
            println!("{:<24}{cells}", v.name);
        }
    }
    if let Some(dir) = &a.plots {
        write_plots(dir, &dataset.name, &reports, a.attributes.then_some(&attrs))?;
        println!("plots: {}", dir.display());
    }
    if let Some(path) = &a.json {
        let report = Report { dataset: dataset.name.clone(), videos: dataset.videos.len(), trackers: reports };
        write_atomically(path, &serde_json::to_vec_pretty(&report)?)?;
    }
    Ok(())
}

/// A tracker's name, score and curve in a plot.
type Series = (String, f64, Vec<f64>);

/// A tracker's score and curve for one plot, where its report has them.
type Plotted<'a> = dyn Fn(&TrackerReport) -> Option<(f64, Vec<f64>)> + 'a;

/// Success, precision and normalised precision plots of the whole dataset (and of each attribute).
fn write_plots(
    dir: &Path,
    dataset: &str,
    reports: &[TrackerReport],
    attrs: Option<&BTreeMap<String, Vec<String>>>,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let sets =
        [(Kind::Success, "success", "Success plots of OPE"), (Kind::Precision, "precision", "Precision plots of OPE")];
    let curves = |s: &Plotted<'_>| -> Vec<Series> {
        reports.iter().filter_map(|r| s(r).map(|(score, v)| (r.name.clone(), score, v))).collect()
    };
    let draw = |stem: String, title: String, kind: Kind, data: Vec<Series>| -> anyhow::Result<()> {
        let mut c: Vec<Curve> = data.iter().map(|(n, s, v)| Curve { name: n, score: *s, values: v }).collect();
        plot(&dir.join(stem), &title, kind, &mut c)
    };
    for (kind, file, title) in sets {
        let pick = |r: &TrackerReport| -> Option<(f64, Vec<f64>)> {
            Some(match kind {
                Kind::Success => (r.success, r.success_curve.clone()),
                _ => (r.precision, r.precision_curve.clone()),
            })
        };
        draw(format!("{dataset}_{file}"), format!("{title} on {dataset}"), kind, curves(&pick))?;
        for attr in attrs.into_iter().flat_map(|a| a.keys()) {
            let pick = |r: &TrackerReport| -> Option<(f64, Vec<f64>)> {
                let s = r.attribute_curves.get(attr)?;
                Some(match kind {
                    Kind::Success => (s.auc, s.success.clone()),
                    _ => (s.precision_at_20, s.precision.clone()),
                })
            };
            let slug: String =
                attr.chars().map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '_' }).collect();
            draw(format!("{dataset}_{file}_{slug}"), format!("{title} - {attr}"), kind, curves(&pick))?;
        }
    }
    let norm: Vec<Series> =
        reports.iter().map(|r| (r.name.clone(), r.norm_precision, r.norm_precision_curve.clone())).collect();
    draw(
        format!("{dataset}_norm_precision"),
        format!("Normalized precision plots of OPE on {dataset}"),
        Kind::NormPrecision,
        norm,
    )
}
