//! The pickle interpreter alone (inside a checkpoint it sits behind the zip reader).
#![no_main]

#[global_allocator]
static ALLOC: prl_fuzz::Capped = prl_fuzz::Capped;

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Ok(v) = prl_compiler::checkpoint::parse_pickle(data) {
        // What the torch reader asks of a value: none of it may recurse without bound.
        let _ = (v.global_name(), v.dict_items().map(|d| d.len()), v.items().map(|i| i.len()), format!("{v:?}"));
    }
});
