//! `prl demo`: the whole pipeline on nothing but the program itself: a seeded network, compiled
//! to a plan, tracking a textured target over a textured background in a generated video.

use std::path::PathBuf;

use clap::Args;
use prl_compiler::{build_model, compile, WeightsSource};
use prl_runtime::{set_threads, BBox, Frame, PixelLayout, Plan, Tracker};

use super::compile::{tracker_config, DEFAULT_TRACKER_TOML};
use super::track::{results_text, track_frames};
use super::{spinner, write_atomically, WeightsArgs};

#[derive(Args)]
pub struct DemoArgs {
    #[command(flatten)]
    weights: WeightsArgs,
    /// Frames to generate.
    #[arg(long, default_value_t = 30)]
    frames: usize,
    /// Where the plan and the results go.
    #[arg(long, default_value = "models/prl-track/demo")]
    out: PathBuf,
    /// Threads for the network (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

const W: usize = 320;
const H: usize = 240;
const TW: f64 = 40.0;
const TH: f64 = 28.0;

/// Deterministic texture noise in 0..1.
fn noise(x: usize, y: usize, salt: u64) -> f64 {
    let mut h = (x as u64).wrapping_mul(0x9e3779b97f4a7c15) ^ (y as u64).wrapping_mul(0xc2b2ae3d27d4eb4f) ^ salt;
    h ^= h >> 31;
    h = h.wrapping_mul(0xbf58476d1ce4e5b9);
    h ^= h >> 29;
    (h & 0xffff) as f64 / 65535.0
}

/// The target's true box in frame `i`: a Lissajous path.
fn truth(i: usize) -> [f64; 4] {
    let t = i as f64 * 0.12;
    [140.0 + 90.0 * t.sin() - TW / 2.0, 120.0 + 60.0 * (1.7 * t).sin() - TH / 2.0, TW, TH]
}

/// Frame `i`: smooth textured background, a checkered orange-and-blue target at `truth(i)`.
fn frame(i: usize) -> Frame {
    let [bx, by, bw, bh] = truth(i);
    let mut rgb = Vec::with_capacity(W * H * 3);
    for y in 0..H {
        for x in 0..W {
            let (fx, fy) = (x as f64, y as f64);
            let inside = fx >= bx && fx < bx + bw && fy >= by && fy < by + bh;
            let px = if inside {
                let check = ((fx - bx) as usize / 7 + (fy - by) as usize / 7) % 2 == 0;
                if check {
                    [240.0, 120.0, 30.0]
                } else {
                    [30.0, 60.0, 200.0]
                }
            } else {
                let base = 90.0 + 40.0 * ((fx * 0.05).sin() + (fy * 0.07).cos());
                let n = 50.0 * noise(x / 3, y / 3, 7);
                [base + n, base * 0.9 + n, base * 0.7 + n]
            };
            rgb.extend(px.map(|v: f64| v.clamp(0.0, 255.0) as u8));
        }
    }
    Frame::from_raw(W, H, &rgb, PixelLayout::Rgb).expect("generated frame size")
}

pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.frames >= 2, "--frames must be at least 2");
    set_threads(a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())));
    let source = a.weights.source_or(|| WeightsSource::Random(0));
    let pb = spinner("building the network and compiling a plan");
    let plan_dir = a.out.join("plan");
    let built = build_model(&source)
        .and_then(|m| compile(&m, &tracker_config(std::path::Path::new(DEFAULT_TRACKER_TOML)).unwrap_or_default()));
    let written = built.and_then(|p| p.write(&plan_dir).map(|_| p));
    pb.finish_and_clear();
    let plan = written?;
    println!("plan: {} ({})", plan_dir.display(), plan.manifest.weights.note);
    let plan = Plan::load(&plan_dir)?;
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    let gt: Vec<[f64; 4]> = (0..a.frames).map(truth).collect();
    let init = prl_track::init_box_from_groundtruth(gt[0]);
    println!(
        "tracking a generated {W}x{H} video of {} frames, target {TW}x{TH} starting at ({:.0}, {:.0})",
        a.frames, gt[0][0], gt[0][1]
    );
    let (boxes, summary) = track_frames(
        &mut tracker,
        a.frames,
        |i| Ok(frame(i)),
        |i| format!("generated frame {}", i + 1),
        init,
        Some(&gt),
        |_, _, _| Ok(()),
    )?;
    let results = a.out.join("results.txt");
    write_atomically(&results, results_text(&boxes).as_bytes())?;
    println!("results: {}", results.display());
    summary.print();
    let last: &BBox = boxes.last().expect("frames >= 2");
    println!(
        "last box: {:.1},{:.1},{:.1},{:.1}   truth: {:.1},{:.1},{:.1},{:.1}",
        last.x,
        last.y,
        last.w,
        last.h,
        gt[gt.len() - 1][0],
        gt[gt.len() - 1][1],
        TW,
        TH
    );
    if matches!(source, WeightsSource::Random(_)) {
        println!("note: these are RANDOM weights. Everything ran end to end (build, compile, plan, crops, network, tracker), but an untrained network cannot track: the boxes drift. Give --checkpoint with the authors' trained weights to see it track.");
    }
    Ok(())
}
