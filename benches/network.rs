//! Latency of the emitted graphs under tract (fp32, default threads), on the reference fixture's
//! golden inputs. `cargo bench --bench network`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use prl_compiler::checkpoint::Checkpoint;
use prl_compiler::{net, read_golden, NetworkRunner, Weights};

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
}

criterion_group!(benches, graphs);
criterion_main!(benches);
