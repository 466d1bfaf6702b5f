//! Latency of the per-frame work around the network on a real 1280x720 frame: crop + resize,
//! the official post-processing, and the whole tracking step (fp32 plan, one thread: tract's
//! default).
//! `cargo bench --bench pipeline`.

use criterion::{criterion_group, criterion_main, Criterion};
use prl_runtime::{crop_to_tensor, get_subwindow, Plan, Tracker, TrackerConfig};
use prl_track::{init_box_from_groundtruth, load_frame, Sequence};

fn shared() -> std::path::PathBuf {
    concat!(env!("CARGO_MANIFEST_DIR"), "/../shared").into()
}

fn pipeline(c: &mut Criterion) {
    let seq = Sequence::open(&shared().join("data/uav123_10fps/building4")).expect("building4");
    let frame = load_frame(&seq.frames[0]).expect("frame");
    let init = init_box_from_groundtruth(seq.groundtruth().expect("ground truth")[0]);
    let checkpoint = std::env::var_os("PRL_GOLDEN_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| shared().join("fixtures/prl-golden-v1"))
        .join("checkpoint.pth");
    let model = prl_compiler::build_model(&prl_compiler::WeightsSource::Checkpoint(checkpoint)).expect("build");
    let compiled = prl_compiler::compile(&model, &TrackerConfig::default()).expect("compile");
    let dir = std::env::temp_dir().join(format!("prl-bench-plan-{}", std::process::id()));
    compiled.write(&dir).expect("write plan");
    let plan = Plan::load(&dir).expect("plan");
    let _ = std::fs::remove_dir_all(&dir);

    let center = (init.x + (init.w - 1.0) / 2.0, init.y + (init.h - 1.0) / 2.0);
    let avg = frame.channel_mean();
    let mut g = c.benchmark_group("per frame");
    g.bench_function("crop + resize (search, 1280x720 frame)", |b| {
        b.iter(|| crop_to_tensor(&get_subwindow(&frame, center, 287, 200, avg), 287))
    });
    let x = crop_to_tensor(&get_subwindow(&frame, center, 287, 200, avg), 287);
    let zf = plan.template(&crop_to_tensor(&get_subwindow(&frame, center, 127, 88, avg), 127)).expect("template");
    let out = plan.search(&x, &zf).expect("search");
    let mut tracker = Tracker::new(plan, TrackerConfig::default());
    tracker.init(&frame, init).expect("init");
    // Each call also moves the target; the work per call is the same.
    g.bench_function("post-processing", |b| {
        b.iter(|| tracker.update(frame.width(), frame.height(), &out).expect("update"))
    });
    g.sample_size(10);
    g.bench_function("tracking step (crop, network, post)", |b| b.iter(|| tracker.track(&frame).expect("track")));
    g.finish();
}

criterion_group!(benches, pipeline);
criterion_main!(benches);
