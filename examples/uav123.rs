//! Track the three UAV123@10fps sequences of `../shared/data/uav123_10fps` from start to end with
//! a plan, and print per sequence: frames, FPS, median network time and mean IoU with the ground
//! truth.
//!
//! `cargo run --release --example uav123 -- [PLAN_DIR]` (default `models/prl-track/plan`, made
//! with `prl compile`).

use std::time::Instant;

use prl_runtime::{set_threads, Plan, Tracker};
use prl_track::{init_box_from_groundtruth, iou, load_frame, Sequence};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let plan_dir = std::env::args().nth(1).unwrap_or_else(|| "models/prl-track/plan".into());
    let root = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/uav123_10fps"));
    set_threads(std::thread::available_parallelism().map_or(1, |n| n.get()));
    for name in ["wakeboard7", "building4", "wakeboard10"] {
        let seq = Sequence::open(&root.join(name))?;
        let gt = seq.groundtruth.clone().ok_or("no ground truth")?;
        let plan = Plan::load(&plan_dir)?;
        let config = plan.manifest().tracker.clone();
        let mut tracker = Tracker::new(plan, config);
        let start = Instant::now();
        let mut ious = Vec::new();
        let mut network = Vec::new();
        for (i, path) in seq.frames.iter().enumerate() {
            let frame = load_frame(path)?;
            let b = if i == 0 {
                let b = init_box_from_groundtruth(gt[0]);
                tracker.init(&frame, b)?;
                b
            } else {
                let p = tracker.track(&frame)?;
                network.push(tracker.last_timings().network.as_secs_f64() * 1e3);
                p.bbox
            };
            let g = gt[i];
            if g[2] > 0.0 && g[3] > 0.0 {
                ious.push(iou([b.x, b.y, b.w, b.h], g));
            }
        }
        network.sort_by(f64::total_cmp);
        let secs = start.elapsed().as_secs_f64();
        println!(
            "{name:<12} {:>4} frames  {:>5.1} FPS  network {:>6.1} ms (median)  mean IoU {:.3}",
            seq.frames.len(),
            seq.frames.len() as f64 / secs,
            network[network.len() / 2],
            ious.iter().sum::<f64>() / ious.len() as f64
        );
    }
    Ok(())
}
