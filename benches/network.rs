//! Latency of the emitted graphs under tract (fp32, and the search graph in int8 after
//! calibrating on 8 frames of the shared `wakeboard10`; default threads), on the reference
//! fixture's golden inputs. `cargo bench --bench network`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use prl_compiler::checkpoint::Checkpoint;
use prl_compiler::{net, read_golden, NetworkRunner, OnnxRunner, Weights};

/// Multiply-accumulates of each graph, counted from its convolutions and matmuls.
const TEMPLATE_GMAC: f64 = 0.71;
const SEARCH_GMAC: f64 = 6.95;

fn fixture() -> std::path::PathBuf {
    std::env::var_os("PRL_GOLDEN_DIR")
        .map(Into::into)
        .unwrap_or_else(|| concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/fixtures/prl-golden-v1").into())
}

fn graphs(c: &mut Criterion) {
    let dir = fixture();
    let weights = Weights::from_checkpoint(Checkpoint::load(dir.join("checkpoint.pth")).expect("checkpoint"));
    let golden = read_golden(&dir.join("golden.safetensors")).expect("golden");
    let network = net::build_network(&weights).expect("network");
    let runner = NetworkRunner::new(&network, None).unwrap();
    let zf = runner.template(&golden["z"]).unwrap();

    let mut g = c.benchmark_group("fp32");
    g.sample_size(10);
    g.throughput(Throughput::Elements((2.0 * TEMPLATE_GMAC * 1e9) as u64));
    g.bench_function("template graph (FLOP)", |b| b.iter(|| runner.template(&golden["z"]).unwrap()));
    g.throughput(Throughput::Elements((2.0 * SEARCH_GMAC * 1e9) as u64));
    g.bench_function("search graph (FLOP)", |b| b.iter(|| runner.search(&golden["x"], &zf).unwrap()));
    g.finish();

    let model =
        prl_compiler::build_model(&prl_compiler::WeightsSource::Checkpoint(dir.join("checkpoint.pth"))).expect("model");
    let spec = prl_track::CalibrationSpec {
        sequences: vec![concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/uav123_10fps/wakeboard10").into()],
        frames_per_sequence: 8,
        templates_per_sequence: 4,
        seed: 0,
        held_out: false,
    };
    let config = prl_runtime::TrackerConfig::default();
    let calib = prl_track::calibration_crops(&spec, &config, &mut |_, _| {}).expect("calibration crops");
    let opts = prl_compiler::QuantizeOptions::default();
    let (int8, _) = prl_compiler::quantize(&model, &calib, &opts, &mut |_, _, _| {}).expect("quantize");
    let search = OnnxRunner::new(&int8.search, "int8 search graph", &net::search_inputs(), None).unwrap();
    let args: Vec<&prl_compiler::Tensor> = std::iter::once(&golden["x"]).chain(&zf).collect();
    let mut g = c.benchmark_group("int8");
    g.sample_size(10);
    g.throughput(Throughput::Elements((2.0 * SEARCH_GMAC * 1e9) as u64));
    g.bench_function("search graph (FLOP)", |b| b.iter(|| search.run(&args).unwrap()));
    g.finish();
}

criterion_group!(benches, graphs);
criterion_main!(benches);
