//! `prl demo`: the whole pipeline on nothing but the program itself: a trained tracker
//! (NanoTrack v2, shipped in `models/nanotrack-v2`) imported and compiled to a plan, tracking a
//! textured target over a textured background in a generated video; or PRL-Track from a
//! checkpoint or seeded weights.

use std::path::PathBuf;

use clap::Args;
use prl_compiler::{build_model, compile, WeightsSource};
use prl_runtime::{set_threads, Family, Frame, PixelLayout, Plan, Tracker};
use prl_track::tracking::MadeFrames;

use super::compile::settings_for;
use super::track::{track_with_progress, Summary};
use super::{spinner, write_atomically, WeightsArgs};

#[derive(Args)]
pub struct DemoArgs {
    /// The tracker: `nanotrack` (trained weights shipped with the toolchain) or `prl-track`
    /// (needs --checkpoint for trained weights; seeded random weights otherwise). Default:
    /// nanotrack, or prl-track when --checkpoint or --random-seed is given.
    #[arg(long, value_parser = parse_family)]
    family: Option<Family>,
    #[command(flatten)]
    weights: WeightsArgs,
    /// Frames to generate.
    #[arg(long, default_value_t = 60)]
    frames: usize,
    /// Where the plan and the results go (default: `models/<model>/demo`).
    #[arg(long)]
    out: Option<PathBuf>,
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
                let check = ((fx - bx) as usize / 7 + (fy - by) as usize / 7).is_multiple_of(2);
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

fn parse_family(s: &str) -> Result<Family, String> {
    Family::parse(s).ok_or_else(|| format!("`{s}` is not a tracker family; expected nanotrack or prl-track"))
}

pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.frames >= 2, "--frames must be at least 2");
    set_threads(a.threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())));
    let weights_given = a.weights.checkpoint.is_some() || a.weights.random_seed.is_some();
    let family = a.family.unwrap_or(if weights_given { Family::PrlTrack } else { Family::Nanotrack });
    if family == Family::Nanotrack && weights_given {
        anyhow::bail!("--checkpoint and --random-seed are for --family prl-track; NanoTrack's weights ship with it");
    }
    let (built, what) = match family {
        Family::Nanotrack => {
            let pb = spinner("importing NanoTrack v2 (models/nanotrack-v2) and compiling a plan");
            let m = super::import::import_nanotrack(None, None, None);
            pb.finish_and_clear();
            (m?, "NanoTrack v2, trained weights")
        }
        Family::PrlTrack => {
            let source = a.weights.source_or(|| WeightsSource::Random(0));
            let pb = spinner("building PRL-Track and compiling a plan");
            let m = build_model(&source);
            pb.finish_and_clear();
            let random = matches!(source, WeightsSource::Random(_));
            (m?, if random { "PRL-Track, RANDOM weights" } else { "PRL-Track, checkpoint weights" })
        }
    };
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("models").join(&built.manifest.model).join("demo"));
    let plan_dir = out.join("plan");
    let tracker_settings = settings_for(&built, None)?;
    let pb = spinner("compiling the plan");
    let written = compile(&built, &tracker_settings).and_then(|p| p.write(&plan_dir).map(|_| p));
    pb.finish_and_clear();
    let plan = written?;
    println!("plan: {} ({what}; {})", plan_dir.display(), plan.manifest.weights.note);
    let plan = Plan::load(&plan_dir)?;
    let config = plan.manifest().tracker.clone();
    let mut tracker = Tracker::new(plan, config);
    let gt: Vec<[f64; 4]> = (0..a.frames).map(truth).collect();
    let init = prl_track::init_box_from_groundtruth(gt[0]);
    println!(
        "tracking a generated {W}x{H} video of {} frames, target {TW}x{TH} starting at ({:.0}, {:.0})",
        a.frames, gt[0][0], gt[0][1]
    );
    let frames = MadeFrames { count: a.frames, what: "generated", make: frame };
    let run = track_with_progress(&mut tracker, frames, init, |_, _, _| Ok(()))?;
    let results = out.join("results.txt");
    write_atomically(&results, run.results_text().as_bytes())?;
    println!("results: {}", results.display());
    Summary::of(&run, Some(&gt)).print();
    let last = run.boxes.last().expect("frames >= 2");
    let g = gt[gt.len() - 1];
    println!(
        "last box: {:.1},{:.1},{:.1},{:.1}   truth: {:.1},{:.1},{:.1},{:.1}",
        last.x, last.y, last.w, last.h, g[0], g[1], g[2], g[3]
    );
    if tracker.plan().manifest().weights.kind == "random" {
        println!("note: these are RANDOM weights. Everything ran end to end (build, compile, plan, crops, network, tracker), but an untrained network cannot track: the boxes drift. Give --checkpoint with the authors' trained weights to see it track.");
    }
    Ok(())
}
