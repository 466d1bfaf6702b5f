//! Real footage end to end: UAV123@10fps JPEG frames (1280x720), decoded as OpenCV decodes them,
//! through the plan and the tracker. (The reference weights are random, so this checks the path,
//! not accuracy; `examples/uav123.rs` runs the whole sequences.)

mod common;

use prl_runtime::{Plan, Tracker};
use prl_track::{init_box_from_groundtruth, load_frame, Sequence};

const FRAMES: usize = 4;

#[test]
fn real_sequences_run_end_to_end() {
    let root = common::golden_dir().join("../../data/uav123_10fps");
    for name in ["wakeboard7", "building4", "wakeboard10"] {
        let seq = Sequence::open(&root.join(name)).unwrap();
        let gt = seq.groundtruth.as_ref().unwrap();
        assert_eq!(gt.len(), seq.frames.len());
        let plan = Plan::load(common::reference_plan()).unwrap();
        let config = plan.manifest().tracker.clone();
        let mut tracker = Tracker::new(plan, config);
        let first = load_frame(&seq.frames[0]).unwrap();
        assert_eq!((first.width(), first.height()), (1280, 720));
        tracker.init(&first, init_box_from_groundtruth(gt[0])).unwrap();
        for path in &seq.frames[1..FRAMES] {
            let p = tracker.track(&load_frame(path).unwrap()).unwrap();
            let b = p.bbox;
            assert!([b.x, b.y, b.w, b.h, p.score].iter().all(|v| v.is_finite()), "{name}: {p:?}");
            assert!(b.w >= 10.0 && b.h >= 10.0 && b.w <= 1280.0 && b.h <= 720.0, "{name}: {p:?}");
            let (cx, cy) = (b.x + b.w / 2.0, b.y + b.h / 2.0);
            assert!((0.0..=1280.0).contains(&cx) && (0.0..=720.0).contains(&cy), "{name}: {p:?}");
        }
    }
}
