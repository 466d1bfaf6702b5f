//! The `prl` command line: what a user runs, its outputs, its errors and exit codes.

mod common;

use common::prl;

use std::process::Output;

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).trim().to_string()
}

#[test]
fn build_with_random_weights_writes_graphs_and_manifest() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("model");
    let o = prl(&["build", "--random-seed", "5", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["weights"]["kind"], "random");
    assert_eq!(manifest["weights"]["seed"], 5);
    assert_eq!(manifest["search"]["outputs"][0]["name"], "loc");
    assert_eq!(manifest["preprocessing"]["channels"], "BGR");
    for f in ["template.onnx", "search.onnx"] {
        assert!(std::fs::metadata(out.join(f)).unwrap().len() > 1_000_000, "{f}");
    }
    let leftovers: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .filter(|n| n.to_string_lossy().contains(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn build_from_the_checkpoint_lists_unused_keys_with_verbose() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = common::golden_dir().join("checkpoint.pth");
    let o = prl(&["build", "--checkpoint", ckpt.to_str().unwrap(), "--out", dir.path().to_str().unwrap(), "--verbose"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("backbone.layer1.1.num_batches_tracked"), "{stdout}");
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["weights"]["kind"], "checkpoint");
    assert_eq!(manifest["weights"]["sha256"].as_str().unwrap().len(), 64);
}

#[test]
fn bad_checkpoints_give_one_line_errors_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("broken.pth");
    std::fs::write(&bad, b"PK\x03\x04 truncated").unwrap();
    let out = dir.path().join("out");
    for path in [bad.to_str().unwrap(), "/nonexistent/model.pth"] {
        let o = prl(&["build", "--checkpoint", path, "--out", out.to_str().unwrap()]);
        assert!(!o.status.success());
        let err = stderr(&o);
        assert_eq!(err.lines().count(), 1, "{err}");
        assert!(err.starts_with("error: ") && err.contains(path), "{err}");
    }
    assert!(!out.exists(), "nothing written after a failed build");
}

#[test]
fn verify_passes_on_the_reference_and_fails_below_its_error() {
    let o = prl(&["verify", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["stages"].as_array().unwrap().len(), 22);
    assert_eq!(report["passed"], true);

    let o = prl(&["verify", "--tolerance", "1e-12"]);
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(err.contains("exceed the tolerance") && err.contains("golden.safetensors"), "{err}");

    let o = prl(&["verify", "--random-seed", "1"]);
    assert!(!o.status.success(), "random weights cannot match the golden tensors");
}
