//! The tracker settings file is the official configuration, and the runtime's defaults agree.

use prl_runtime::TrackerConfig;

#[test]
fn tracker_toml_is_the_official_configuration() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/models/prl-track/tracker.toml");
    let cfg: TrackerConfig = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    assert_eq!(cfg, TrackerConfig::default());
    assert_eq!((cfg.exemplar_size, cfg.instance_size, cfg.stride, cfg.score_size), (127, 287, 16, 11));
    assert_eq!((cfg.context_amount, cfg.penalty_k, cfg.window_influence, cfg.lr), (0.5, 0.08, 0.42, 0.30));
    assert_eq!((cfg.w2, cfg.w3), (1.0, 1.0));
}
