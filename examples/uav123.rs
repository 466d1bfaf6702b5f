//! Track the three UAV123@10fps sequences of `../shared/data/uav123_10fps` from start to end with
//! a plan, and print per sequence: frames, FPS, median network time and mean IoU with the ground
//! truth.
//!
//! `cargo run --release --example uav123 -- [PLAN_DIR]` (default `models/prl-track/plan`, made
//! with `prl compile`; a NanoTrack plan from `prl import nanotrack` + `prl compile` works too).

use prl_runtime::{set_threads, Plan, Tracker};
use prl_track::{init_box_from_groundtruth, tracking, Sequence};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let plan_dir = std::env::args().nth(1).unwrap_or_else(|| "models/prl-track/plan".into());
    let root = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/uav123_10fps"));
    set_threads(std::thread::available_parallelism().map_or(1, |n| n.get()));
    for name in ["wakeboard7", "building4", "wakeboard10"] {
        let seq = Sequence::open(&root.join(name))?;
        let gt = seq.groundtruth().cloned().ok_or("no ground truth")?;
        let plan = Plan::load(&plan_dir)?;
        let config = plan.manifest().tracker.clone();
        let mut tracker = Tracker::new(plan, config);
        let init = init_box_from_groundtruth(gt[0]);
        let run = tracking::track(&mut tracker, seq.frames.as_slice(), init, |_, _, _| Ok(()))?;
        println!(
            "{name:<12} {:>4} frames  {:>5.1} FPS  network {:>6.1} ms (median)  mean IoU {:.3}",
            run.boxes.len(),
            run.boxes.len() as f64 / run.total.as_secs_f64(),
            run.median_ms(|t| t.network),
            run.mean_iou(&gt).unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
