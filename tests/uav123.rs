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
        let gt = seq.groundtruth().unwrap();
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

/// JPEG frames decode to exactly OpenCV's pixels: SHA-256 of `cv2.imread(path).tobytes()` (BGR,
/// opencv-python 5.0, libjpeg-turbo), computed once and written here.
#[test]
fn jpeg_frames_decode_to_opencvs_pixels() {
    use sha2::{Digest, Sha256};
    let root = common::golden_dir().join("../../data/uav123_10fps");
    for (file, opencv) in [
        ("building4/img/000001.jpg", "e02fc6e8001b79cdb8f6a7f3274b510c0449c2f45582fdaea04f09f44d6ac647"),
        ("wakeboard7/img/000030.jpg", "0ec5426061bc2eca8843bb6b1498183341c558f80bb259e69e13687c74eb4f80"),
    ] {
        let f = load_frame(&root.join(file)).unwrap();
        let ours: String = Sha256::digest(f.bgr()).iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(ours, opencv, "{file}");
    }
}
