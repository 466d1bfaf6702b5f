//! The tracker settings file is the official configuration, and the runtime's defaults agree.

use prl_runtime::{LongTermConfig, StateSignal, TrackerConfig};

#[test]
fn tracker_toml_is_the_official_configuration() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/models/prl-track/tracker.toml");
    let cfg: TrackerConfig = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    assert_eq!(cfg, TrackerConfig::default());
    assert_eq!((cfg.exemplar_size, cfg.instance_size, cfg.stride, cfg.score_size), (127, 287, 16, 11));
    assert_eq!((cfg.context_amount, cfg.penalty_k, cfg.window_influence, cfg.lr), (0.5, 0.08, 0.42, 0.30));
    assert_eq!((cfg.w2, cfg.w3), (1.0, 1.0));
}

#[test]
fn nanotrack_toml_is_configv2() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/models/nanotrack-v2/tracker.toml");
    let cfg: TrackerConfig = toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    assert_eq!(cfg, TrackerConfig::nanotrack());
    assert_eq!((cfg.exemplar_size, cfg.instance_size, cfg.stride, cfg.score_size), (127, 255, 16, 16));
    assert_eq!((cfg.context_amount, cfg.penalty_k, cfg.window_influence, cfg.lr), (0.5, 0.15, 0.49, 0.385));
    assert_eq!((cfg.grid_origin, cfg.ratio_eps, cfg.large_target_keeps_template_size), (-128.0, 0.0, false));
}

#[test]
fn settings_without_the_newer_fields_read_as_prl_track() {
    // A plan.json of the first format has no family and no PRL-Track switches.
    let old = "exemplar_size = 127\ninstance_size = 287\ncontext_amount = 0.5\npenalty_k = 0.08\n\
               window_influence = 0.42\nlr = 0.30\nw2 = 1.0\nw3 = 1.0\nstride = 16\nscore_size = 11\n";
    let cfg: TrackerConfig = toml::from_str(old).unwrap();
    let mut expected = TrackerConfig::prl_track();
    (expected.state_signal, expected.uncertain_below, expected.lost_below) = (None, None, None);
    assert_eq!(cfg, expected);
    // Nor the state rule: the family's default applies.
    assert_eq!(cfg.state_rule(), TrackerConfig::prl_track().state_rule());
    let nano = format!("family = \"nanotrack\"\n{old}");
    let cfg: TrackerConfig = toml::from_str(&nano).unwrap();
    assert_eq!(cfg.state_rule(), TrackerConfig::nanotrack().state_rule());
}

#[test]
fn state_thresholds_are_checked() {
    let mut cfg = TrackerConfig::nanotrack();
    assert_eq!(cfg.state_rule(), (StateSignal::MapFocus, 0.93, 0.92));
    assert!(cfg.check().is_ok());
    cfg.lost_below = Some(0.95);
    assert!(cfg.check().unwrap_err().contains("lost_below (0.95) must be a number at most uncertain_below (0.93)"));
    cfg.lost_below = Some(f64::NAN);
    assert!(cfg.check().is_err());
    let text = "state_signal = \"best-score\"\n";
    let base = toml::to_string(&TrackerConfig { state_signal: None, ..TrackerConfig::nanotrack() }).unwrap();
    let cfg: TrackerConfig = toml::from_str(&format!("{text}{base}")).unwrap();
    assert_eq!(cfg.state_rule().0, StateSignal::BestScore);
}

#[test]
fn long_term_settings_have_defaults_and_are_checked() {
    let mut cfg = TrackerConfig::nanotrack();
    let lt = cfg.long_term_rule();
    assert_eq!((lt.lost_below, lt.found_above, lt.tiles, lt.window_influence), (0.90, 0.94, 3, 0.001));
    let base = toml::to_string(&cfg).unwrap();
    let table = "\n[long_term]\nlost_below = 0.8\nfound_above = 0.95\ntiles = 5\nwindow_influence = 0.01\n";
    let read: TrackerConfig = toml::from_str(&format!("{base}{table}")).unwrap();
    assert_eq!(
        read.long_term_rule(),
        LongTermConfig { lost_below: 0.8, found_above: 0.95, tiles: 5, window_influence: 0.01 }
    );
    assert!(read.check().is_ok());
    cfg.long_term = Some(LongTermConfig { tiles: 4, ..lt.clone() });
    assert!(cfg.check().unwrap_err().contains("long_term.tiles must be odd"), "{:?}", cfg.check());
    cfg.long_term = Some(LongTermConfig { found_above: 0.5, ..lt });
    assert!(cfg.check().unwrap_err().contains("long_term.lost_below (0.9) must be a number at most"));
}
