//! `prl compare`'s report as Markdown tables (printed, and written with `--markdown`).

use std::fmt::Write as _;

use super::compare::{Report, Stat};

fn stat(s: &Stat) -> String {
    format!("{:.1} / {:.1}", s.median, s.p90)
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("-".into(), |v| format!("{v:.digits$}"))
}

/// The report as Markdown: latency, output fidelity, tracking.
pub fn markdown(r: &Report) -> String {
    let mut s = String::new();
    let reference = &r.plans[0];
    let _ = writeln!(s, "### Latency ({} thread(s), median / p90 ms over {} interleaved runs)\n", r.threads, r.runs);
    let _ = writeln!(
        s,
        "| plan | precision | template | search | search vs first | tracking step | size (MB) | load (ms) | peak RSS (MB) |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
    for p in &r.plans {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {:.2}x | {} | {:.1} | {:.0} | {} |",
            p.path,
            p.precision,
            stat(&p.template_ms),
            stat(&p.search_ms),
            p.search_ms.median / reference.search_ms.median,
            stat(&p.step_ms),
            p.size_mb,
            p.load_ms,
            opt(p.peak_rss_mb, 0)
        );
    }
    if !r.fidelity.is_empty() {
        let _ = writeln!(s, "\n### Output fidelity against {} (held-out search crops)\n", reference.path);
        let names: Vec<&str> = r.fidelity[0].errors.iter().map(|(n, _)| n.as_str()).collect();
        let heads: String = names.iter().map(|n| format!(" {n} rel. error |")).collect();
        let _ = writeln!(s, "| plan | crops |{heads} same best cell | calibrated on |");
        let _ = writeln!(s, "|---|---|{}---|---|", "---|".repeat(names.len()));
        for (f, p) in r.fidelity.iter().zip(&r.plans[1..]) {
            let calib =
                if p.calibration_sequences.is_empty() { "-".into() } else { p.calibration_sequences.join(", ") };
            let errs: String = f.errors.iter().map(|(_, e)| format!(" {e:.4} |")).collect();
            let _ = writeln!(s, "| {} | {} |{errs} {:.1}% | {calib} |", f.plan, f.crops, 100.0 * f.best_cell_agreement);
        }
    }
    let _ = writeln!(s, "\n### Tracking (OPE; IoU to the first plan's boxes, frames after the first)\n");
    let _ = writeln!(
        s,
        "| sequence | frames | plan | success AUC | precision@20 | ΔAUC | Δprecision | mean IoU to first | IoU > 0.5 | IoU > 0.9 |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for q in &r.sequences {
        let first = &q.plans[0];
        for p in &q.plans {
            let delta = |a: Option<f64>, b: Option<f64>| opt(a.zip(b).map(|(a, b)| a - b), 3);
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {:.3} | {:.1}% | {:.1}% |",
                q.sequence,
                q.frames,
                p.plan,
                opt(p.auc, 3),
                opt(p.precision, 3),
                delta(p.auc, first.auc),
                delta(p.precision, first.precision),
                p.mean_iou_to_ref,
                100.0 * p.over_05,
                100.0 * p.over_09
            );
        }
    }
    let calibrated: Vec<&str> =
        r.plans.iter().flat_map(|p| p.calibration_sequences.iter().map(String::as_str)).collect();
    let overlap: Vec<&str> =
        r.sequences.iter().map(|q| q.sequence.as_str()).filter(|n| calibrated.contains(n)).collect();
    if !overlap.is_empty() {
        let _ =
            writeln!(s, "\nNote: {} also served for calibration; its numbers are not held out.", overlap.join(", "));
    }
    s
}
