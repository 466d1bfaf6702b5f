//! The runtime that ships on the camera stays slim: no tract-onnx, no protobuf, no CLI parser in
//! its dependency tree (read from Cargo.lock, the resolved graph `cargo tree` shows).

use std::collections::{BTreeMap, BTreeSet};

#[test]
fn runtime_depends_on_no_onnx_protobuf_or_cli_crates() {
    let lock = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/Cargo.lock")).unwrap();
    let lock: toml::Value = toml::from_str(&lock).unwrap();
    let mut deps: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for p in lock["package"].as_array().unwrap() {
        let name = p["name"].as_str().unwrap().to_string();
        let d: Vec<String> = p
            .get("dependencies")
            .and_then(|d| d.as_array())
            .map(|d| d.iter().map(|s| s.as_str().unwrap().split(' ').next().unwrap().to_string()).collect())
            .unwrap_or_default();
        deps.entry(name).or_default().extend(d);
    }
    let mut seen = BTreeSet::new();
    let mut stack = vec!["prl-runtime".to_string()];
    while let Some(n) = stack.pop() {
        if seen.insert(n.clone()) {
            stack.extend(deps.get(&n).cloned().unwrap_or_default());
        }
    }
    assert!(seen.contains("tract-nnef") && seen.contains("image"), "{seen:?}");
    for banned in ["tract-onnx", "tract-hir", "prost", "protobuf", "clap", "prl-compiler"] {
        assert!(!seen.contains(banned), "prl-runtime depends on {banned}");
    }
}
