//! Checkpoint import: torch zip archives in the shapes real files take, and the ways they break.

mod common;

use std::path::Path;

use common::{f32_bytes, torch_zip, Pickle};
use prl_compiler::checkpoint::{Checkpoint, DType, Entry};
use prl_compiler::{Error, Init, Weights};

fn load(bytes: &[u8]) -> Result<Checkpoint, Error> {
    Checkpoint::from_bytes(Path::new("test.pth"), bytes)
}

fn tensor<'a>(c: &'a Checkpoint, key: &str) -> (&'a [usize], &'a [f32], DType) {
    match &c.entries[key] {
        Entry::Tensor { dtype, tensor } => (&tensor.shape, &tensor.data, *dtype),
        Entry::Other(what) => panic!("{key} is not a tensor: {what}"),
    }
}

const ANY: Init = Init::Normal { mean: 0.0, std: 1.0 };

/// `{"a": [2,3] contiguous, "t": its transpose (strides), "off": 2 values at offset 4}`, all
/// views of one f32 storage.
fn strided_archive() -> Vec<u8> {
    let mut p = Pickle::new();
    p.op(b'}').mark();
    p.str("a").tensor("FloatStorage", "0", 6, 0, &[2, 3], &[3, 1]);
    p.str("t").tensor("FloatStorage", "0", 6, 0, &[3, 2], &[1, 3]);
    p.str("off").tensor("FloatStorage", "0", 6, 4, &[2], &[1]);
    p.op(b'u');
    torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[0., 1., 2., 3., 4., 5.]))])
}

#[test]
fn plain_state_dict_honours_strides_and_offsets() {
    let c = load(&strided_archive()).unwrap();
    assert_eq!(tensor(&c, "a"), (&[2usize, 3][..], &[0f32, 1., 2., 3., 4., 5.][..], DType::F32));
    assert_eq!(tensor(&c, "t").1, &[0f32, 3., 1., 4., 2., 5.]);
    assert_eq!(tensor(&c, "off").1, &[4f32, 5.]);
}

#[test]
fn half_bfloat_and_int64_storages() {
    let mut p = Pickle::new();
    p.op(b'}').mark();
    p.str("h").tensor("HalfStorage", "0", 2, 0, &[2], &[1]);
    p.str("b").tensor("BFloat16Storage", "1", 2, 0, &[2], &[1]);
    p.str("n").tensor("LongStorage", "2", 1, 0, &[], &[]);
    p.op(b'u');
    let h: Vec<u8> = [1.5f32, -2.25].iter().flat_map(|&x| half::f16::from_f32(x).to_le_bytes()).collect();
    let b: Vec<u8> = [0.5f32, 96.0].iter().flat_map(|&x| half::bf16::from_f32(x).to_le_bytes()).collect();
    let c = load(&torch_zip(Some(&p.finish()), &[("0", h), ("1", b), ("2", 7i64.to_le_bytes().to_vec())])).unwrap();
    assert_eq!(tensor(&c, "h"), (&[2usize][..], &[1.5f32, -2.25][..], DType::F16));
    assert_eq!(tensor(&c, "b"), (&[2usize][..], &[0.5f32, 96.0][..], DType::BF16));
    assert_eq!(tensor(&c, "n"), (&[][..], &[7f32][..], DType::I64));
}

/// `{"epoch": 7, "best_score": numpy scalar, "state_dict": {"module.a.weight": t},
///   "optimizer": {"state": {0: {"momentum_buffer": t}}, "param_groups": [{"lr": .., "params": [0]}]}}`
#[test]
fn training_snapshot_with_optimizer_state_and_numpy_scalar() {
    let mut p = Pickle::new();
    p.op(b'}').mark();
    p.str("epoch").int(7);
    p.str("best_score");
    p.global("numpy.core.multiarray", "scalar").mark();
    p.global("numpy", "dtype").mark().str("f8").op(0x89).op(0x88).op(b't').op(b'R');
    p.mark().int(3).str("<").op(b'N').op(b'N').op(b'N').int(-1).int(-1).int(0).op(b't').op(b'b');
    p.bytes(&0.75f64.to_le_bytes()).op(b't').op(b'R');
    p.str("state_dict").op(b'}').mark().str("module.a.weight").tensor("FloatStorage", "0", 2, 0, &[2], &[1]).op(b'u');
    p.str("optimizer").op(b'}').mark();
    p.str("state")
        .op(b'}')
        .mark()
        .int(0)
        .op(b'}')
        .mark()
        .str("momentum_buffer")
        .tensor("FloatStorage", "1", 2, 0, &[2], &[1])
        .op(b'u')
        .op(b'u');
    p.str("param_groups")
        .op(b']')
        .mark()
        .op(b'}')
        .mark()
        .str("lr")
        .float(0.01)
        .str("params")
        .op(b']')
        .mark()
        .int(0)
        .op(b'e')
        .op(b'u')
        .op(b'e');
    p.op(b'u');
    p.op(b'u');
    let c = load(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[1., 2.])), ("1", f32_bytes(&[9., 9.]))])).unwrap();
    assert_eq!(c.entries.keys().collect::<Vec<_>>(), ["a.weight"]);
    assert_eq!(tensor(&c, "a.weight").1, &[1f32, 2.]);
}

#[test]
fn os_system_is_opaque_and_never_runs() {
    let marker = std::env::temp_dir().join(format!("prl-pickle-ran-{}", std::process::id()));
    let mut p = Pickle::new();
    p.op(b'}').mark();
    p.str("evil.weight").global("os", "system").mark().str(&format!("touch {}", marker.display())).op(b't').op(b'R');
    p.str("good.weight").tensor("FloatStorage", "0", 1, 0, &[1], &[1]);
    p.op(b'u');
    let c = load(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[3.]))])).unwrap();
    assert!(!marker.exists(), "the pickle's os.system ran");
    assert!(matches!(&c.entries["evil.weight"], Entry::Other(w) if w.contains("os.system")));
    let w = Weights::from_checkpoint(c);
    assert_eq!(w.root().get("good.weight", &[1], ANY).unwrap().data, [3.]);
    let err = w.root().get("evil.weight", &[1], ANY).unwrap_err().to_string();
    assert!(err.contains("evil.weight") && err.contains("os.system"), "{err}");
    assert!(!marker.exists());
}

#[test]
fn missing_key_and_wrong_shape_name_the_key_and_shapes() {
    let w = Weights::from_checkpoint(load(&strided_archive()).unwrap());
    let err = w.root().pp("backbone").get("weight", &[4], ANY).unwrap_err().to_string();
    assert!(err.contains("missing weight `backbone.weight`") && err.contains("[4]"), "{err}");
    let err = w.root().get("a", &[3, 2], ANY).unwrap_err().to_string();
    assert!(err.contains("`a`") && err.contains("[2, 3]") && err.contains("[3, 2]"), "{err}");
    assert_eq!(w.unused_keys(), ["off", "t"]);
}

#[test]
fn nan_or_infinite_weights_are_refused_by_key() {
    let mut p = Pickle::new();
    p.op(b'}').mark();
    p.str("bad.weight").tensor("FloatStorage", "0", 4, 0, &[4], &[1]);
    p.op(b'u');
    let c = load(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[1., f32::NAN, f32::INFINITY, 2.]))])).unwrap();
    let err = Weights::from_checkpoint(c).root().get("bad.weight", &[4], ANY).unwrap_err().to_string();
    assert!(err.contains("`bad.weight`") && err.contains("2 NaN or infinite values"), "{err}");
}

#[test]
fn truncated_archives_are_errors_not_panics() {
    let full = strided_archive();
    for cut in (0..full.len()).step_by(7) {
        assert!(load(&full[..cut]).is_err(), "cut at {cut} of {} loaded", full.len());
    }
    let real = std::fs::read(common::golden_dir().join("checkpoint.pth")).unwrap();
    for cut in [100, real.len() / 3, real.len() - 100] {
        let err = load(&real[..cut]).unwrap_err().to_string();
        assert!(err.starts_with("test.pth: "), "{err}");
    }
}

#[test]
fn storage_shorter_than_its_tensor_is_an_error() {
    let mut p = Pickle::new();
    p.op(b'}').mark().str("a").tensor("FloatStorage", "0", 6, 0, &[2, 3], &[3, 1]).op(b'u');
    let err = load(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[1., 2.]))])).unwrap_err().to_string();
    assert!(err.contains("tensor `a`") && err.contains("truncated"), "{err}");
}

#[test]
fn zip_without_data_pkl_is_refused() {
    let err = load(&torch_zip(None, &[("0", f32_bytes(&[1.]))])).unwrap_err().to_string();
    assert!(err.contains("data.pkl"), "{err}");
    let err = load(b"hello, not a checkpoint").unwrap_err().to_string();
    assert!(err.contains("neither a torch zip archive nor a safetensors file"), "{err}");
}

#[test]
fn safetensors_files() {
    use safetensors::tensor::{serialize, Dtype, TensorView};
    let a = f32_bytes(&[1., 2., 3., 4.]);
    let h: Vec<u8> = [0.5f32, 8.0].iter().flat_map(|&x| half::f16::from_f32(x).to_le_bytes()).collect();
    let views = vec![
        ("module.x.weight", TensorView::new(Dtype::F32, vec![2, 2], &a).unwrap()),
        ("x.bias", TensorView::new(Dtype::F16, vec![2], &h).unwrap()),
    ];
    let bytes = serialize(views, None).unwrap();
    let c = load(&bytes).unwrap();
    assert_eq!(tensor(&c, "x.weight"), (&[2usize, 2][..], &[1f32, 2., 3., 4.][..], DType::F32));
    assert_eq!(tensor(&c, "x.bias").1, &[0.5f32, 8.0]);
}

#[test]
fn the_reference_checkpoint_loads_as_fp16() {
    let c = Checkpoint::load(common::golden_dir().join("checkpoint.pth")).unwrap();
    assert_eq!(c.entries.len(), 133);
    let (shape, data, dtype) = tensor(&c, "backbone.layer1.0.weight");
    assert_eq!((shape, dtype), (&[96usize, 3, 11, 11][..], DType::F16));
    assert!(data.iter().all(|v| v.is_finite()) && data.iter().any(|&v| v != 0.0));
    assert_eq!(c.sha256.len(), 64);
}
