//! `Plan::load`: `plan.json`, and the NNEF graph archives through tract-nnef. The first byte
//! says what the rest is: even, the manifest (with no graph files beside it); odd, the search
//! graph's archive under the seed plan's manifest (`$PRL_FUZZ_PLAN`, a plan directory;
//! `scripts/fuzz.sh` compiles one) with the archive's own SHA-256 written into it, as a crafted
//! plan would carry: whatever tract-nnef parses goes on through the shape checks, declutter,
//! the runtime's operator rewrites and optimisation. The template graph is left out (its load
//! fails at once, beside the search graph's): a valid graph loaded in full on every execution
//! only cost time.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

struct Seed {
    manifest: serde_json::Value,
    search: String,
}

fn seed() -> &'static Seed {
    static SEED: OnceLock<Seed> = OnceLock::new();
    SEED.get_or_init(|| {
        let dir = PathBuf::from(std::env::var_os("PRL_FUZZ_PLAN").expect("PRL_FUZZ_PLAN: a plan directory"));
        let manifest = std::fs::read(dir.join("plan.json")).expect("plan.json");
        let m: prl_runtime::PlanManifest = serde_json::from_slice(&manifest).expect("a plan manifest");
        Seed { manifest: serde_json::from_slice(&manifest).expect("JSON"), search: m.search.file.clone() }
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
        use sha2::Digest;
        let digest: String = sha2::Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect();
        let mut manifest = s.manifest.clone();
        manifest["search"]["sha256"] = digest.into();
        std::fs::write(dir.join("plan.json"), serde_json::to_vec(&manifest).expect("JSON")).expect("write");
        std::fs::write(dir.join(&s.search), bytes).expect("write");
    }
    let _ = prl_runtime::Plan::load(&dir);
});
