//! `Plan::load`: `plan.json`, and the NNEF graph archives through tract-nnef. The first byte
//! says what the rest is: even, the manifest (with no graph files beside it); odd, the search
//! graph's archive beside the seed plan's manifest and template graph (`$PRL_FUZZ_PLAN`, a plan
//! directory; `scripts/fuzz.sh` compiles one).
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

struct Seed {
    manifest: Vec<u8>,
    template: (String, Vec<u8>),
    search: String,
}

fn seed() -> &'static Seed {
    static SEED: OnceLock<Seed> = OnceLock::new();
    SEED.get_or_init(|| {
        let dir = PathBuf::from(std::env::var_os("PRL_FUZZ_PLAN").expect("PRL_FUZZ_PLAN: a plan directory"));
        let manifest = std::fs::read(dir.join("plan.json")).expect("plan.json");
        let m: prl_runtime::PlanManifest = serde_json::from_slice(&manifest).expect("a plan manifest");
        let template = std::fs::read(dir.join(&m.template.file)).expect("template graph");
        Seed { manifest, template: (m.template.file.clone(), template), search: m.search.file.clone() }
    })
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    // `Plan::load` catches the panics tract-nnef raises on malformed archives and returns an
    // error; libFuzzer's hook would abort on them even so. A silent hook lets a caught panic
    // pass; one that escapes `Plan::load` still aborts (libfuzzer-sys aborts on any panic that
    // reaches it), so it is still found.
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| std::panic::set_hook(Box::new(|_| {})));
    let Some((&which, bytes)) = data.split_first() else { return };
    let dir = prl_fuzz::scratch("plan");
    let s = seed();
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch");
    if which % 2 == 0 {
        std::fs::write(dir.join("plan.json"), bytes).expect("write");
    } else {
        std::fs::write(dir.join("plan.json"), &s.manifest).expect("write");
        std::fs::write(dir.join(&s.template.0), &s.template.1).expect("write");
        std::fs::write(dir.join(&s.search), bytes).expect("write");
    }
    let _ = prl_runtime::Plan::load(&dir);
});
