//! Crafted checkpoints that try to run code, confuse the interpreter, or exhaust memory, time or
//! stack. Each must load with the bad value opaque (never called, an error only when a weight
//! needs it) or fail with a one-line error naming the file; none may crash, run anything, or
//! take long.

mod common;

use std::path::Path;
use std::time::{Duration, Instant};

use common::{f32_bytes, torch_zip, Pickle};
use prl_compiler::checkpoint::{Checkpoint, Entry};
use prl_compiler::{Error, Init, Weights};

const ANY: Init = Init::Normal { mean: 0.0, std: 1.0 };

fn load(bytes: &[u8]) -> Result<Checkpoint, Error> {
    let t = Instant::now();
    let r = Checkpoint::from_bytes(Path::new("evil.pth"), bytes);
    assert!(t.elapsed() < Duration::from_secs(5), "loading took {:?}", t.elapsed());
    r
}

/// `{"bad": <value pushed by f>, "good": tensor [3.0]}` as a torch archive.
fn with_bad(f: impl FnOnce(&mut Pickle)) -> Vec<u8> {
    let mut p = Pickle::new();
    p.op(b'}').mark().str("bad");
    f(&mut p);
    p.str("good").tensor("FloatStorage", "0", 1, 0, &[1], &[1]).op(b'u');
    torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[3.]))])
}

/// The checkpoint loads; `bad` is opaque and its description names `what`; `good` is intact
/// and asking for `bad` as a weight is an error naming it.
fn opaque(bytes: &[u8], what: &str) {
    let c = load(bytes).unwrap_or_else(|e| panic!("refused instead of kept opaque: {e}"));
    match &c.entries["bad"] {
        Entry::Other(w) => assert!(w.contains(what), "`{w}` does not name {what}"),
        Entry::Tensor { .. } => panic!("a tensor was made of {what}"),
    }
    let w = Weights::from_checkpoint(c);
    assert_eq!(w.root().get("good", &[1], ANY).unwrap().data, [3.]);
    let err = w.root().get("bad", &[1], ANY).unwrap_err().to_string();
    assert!(err.contains("bad") && !err.contains('\n'), "{err}");
}

/// Loading fails with one line that names the file and contains `what`.
fn refused(bytes: &[u8], what: &str) {
    let err = load(bytes).map(|c| c.entries.len()).expect_err("loaded").to_string();
    assert!(err.starts_with("evil.pth: ") && !err.contains('\n'), "{err}");
    assert!(err.contains(what), "`{err}` does not say {what}");
}

/// A marker file a payload would create if it ran.
fn marker(tag: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("prl-evil-{tag}-{}", std::process::id()))
}

const CALLABLES: [(&str, &str); 14] = [
    ("os", "system"),
    ("posix", "system"),
    ("nt", "system"),
    ("subprocess", "Popen"),
    ("subprocess", "check_output"),
    ("builtins", "eval"),
    ("builtins", "exec"),
    ("builtins", "getattr"),
    ("builtins", "__import__"),
    ("__builtin__", "eval"),
    ("runpy", "_run_code"),
    ("runpy", "run_path"),
    ("webbrowser", "open"),
    ("shutil", "rmtree"),
];

#[test]
fn global_and_stack_global_reduce_are_never_called() {
    for (m, n) in CALLABLES {
        let mark = marker(n);
        let cmd = format!("touch {}", mark.display());
        // GLOBAL + REDUCE
        opaque(
            &with_bad(|p| {
                p.global(m, n).mark().str(&cmd).op(b't').op(b'R');
            }),
            &format!("{m}.{n}"),
        );
        // STACK_GLOBAL + REDUCE, and NEWOBJ
        opaque(
            &with_bad(|p| {
                p.str(m).str(n).op(0x93).mark().str(&cmd).op(b't').op(b'R');
            }),
            n,
        );
        opaque(
            &with_bad(|p| {
                p.str(m).str(n).op(0x93).mark().str(&cmd).op(b't').op(0x81);
            }),
            n,
        );
        assert!(!mark.exists(), "{m}.{n} ran");
    }
}

#[test]
fn indirection_gadgets_stay_opaque() {
    // A gadget returns a callable, which is then called: both calls are only recorded.
    let gadgets = [
        ("importlib", "import_module", "os"),
        ("pkgutil", "resolve_name", "os:system"),
        ("operator", "attrgetter", "system"),
        ("operator", "methodcaller", "system"),
        ("pickle", "loads", "cos\nsystem\n."),
        ("torch", "load", "/tmp/x.pth"),
        ("torch.storage", "_load_from_bytes", "\u{80}"),
        ("numpy.testing._private.utils", "runstring", "import os"),
        ("numpy.core.multiarray", "_reconstruct", "x"),
    ];
    for (m, n, arg) in gadgets {
        let payload = |p: &mut Pickle| {
            p.global(m, n).mark().str(arg).op(b't').op(b'R'); // f = gadget(arg)
            p.mark().str("id").op(b't').op(b'R'); // f("id")
        };
        opaque(&with_bad(payload), &format!("{m}.{n}"));
        // As a tensor's storage: the tensor is not made, the entry names the gadget.
        let as_storage = |p: &mut Pickle| {
            p.global("torch._utils", "_rebuild_tensor_v2").mark();
            p.global(m, n).mark().str(arg).op(b't').op(b'R');
            p.int(0).tuple_of_ints(&[1]).tuple_of_ints(&[1]).op(0x89).op(b't').op(b'R');
        };
        opaque(&with_bad(as_storage), &format!("{m}.{n}"));
    }
}

#[test]
fn inst_and_obj_are_refused() {
    // INST: `i module\nname\n` after a mark; OBJ: mark, class, args, `o`.
    refused(
        &with_bad(|p| {
            p.mark().str("id").op(b'i').op(b'o').op(b's');
        }),
        "unsupported pickle opcode 0x69",
    );
    let obj = |p: &mut Pickle| {
        p.mark().global("os", "system").str("id").op(b'o');
    };
    refused(&with_bad(obj), "unsupported pickle opcode 0x6f");
}

#[test]
fn build_never_sets_attributes() {
    // BUILD on a recorded call, on a global, and on a tensor: nothing is set that changes what
    // is loaded.
    let on_call = |p: &mut Pickle| {
        p.global("os", "system").mark().str("id").op(b't').op(b'R');
        p.op(b'}').mark().str("__reduce__").global("os", "system").op(b'u').op(b'b');
    };
    opaque(&with_bad(on_call), "os.system");
    let on_global = |p: &mut Pickle| {
        p.global("os", "system").op(b'}').op(b'b');
    };
    opaque(&with_bad(on_global), "a plain global");
    let mut p = Pickle::new();
    p.op(b'}').mark().str("good").tensor("FloatStorage", "0", 1, 0, &[1], &[1]);
    p.op(b'}').mark().str("data").global("os", "system").op(b'u').op(b'b').op(b'u');
    let c = load(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[3.]))])).unwrap();
    assert!(matches!(&c.entries["good"], Entry::Tensor { tensor, .. } if tensor.data == [3.]));
}

#[test]
fn memo_confusion() {
    // MEMOIZE (slot 0), BINPUT 0 over it, PUT 0 over that: GET 0 is the last one put.
    let mut p = Pickle::new();
    p.op(b'}').mark().str("good").tensor("FloatStorage", "0", 1, 0, &[1], &[1]);
    p.global("os", "system").op(0x94).op(b'0');
    p.str("x").op(b'q').op(0).op(b'0');
    p.int(5).op(b'p').out.extend(b"0\n");
    p.op(b'0').str("alias").op(b'h').op(0);
    p.op(b'u');
    let c = load(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[3.]))])).unwrap();
    assert!(matches!(&c.entries["alias"], Entry::Other(w) if w.contains("int")), "{:?}", c.entries["alias"]);
    assert!(matches!(&c.entries["good"], Entry::Tensor { tensor, .. } if tensor.data == [3.]));
    // A GET of a slot never set, in each of its three forms.
    refused(
        &with_bad(|p| {
            p.op(b'h').op(7);
        }),
        "unknown memo key",
    );
    refused(&with_bad(|p| p.op(b'j').out.extend(9u32.to_le_bytes())), "unknown memo key");
    refused(&with_bad(|p| p.op(b'g').out.extend(b"12\n")), "unknown memo key");
}

#[test]
fn setitems_on_a_non_dict_is_an_error() {
    refused(
        &with_bad(|p| {
            p.op(b']').str("k").str("v").op(b's');
        }),
        "SETITEM on non-dict",
    );
    refused(
        &with_bad(|p| {
            p.op(b')').mark().str("k").str("v").op(b'u');
        }),
        "SETITEMS on non-dict",
    );
    refused(
        &with_bad(|p| {
            p.str("s").str("v").op(b'a');
        }),
        "APPEND on non-list",
    );
}

#[test]
fn storages_that_disagree_with_their_tensor() {
    let one = |numel: usize, offset: usize, size: &[usize], stride: &[usize], bytes: Vec<u8>| {
        let mut p = Pickle::new();
        p.op(b'}').mark().str("a").tensor("FloatStorage", "0", numel, offset, size, stride).op(b'u');
        torch_zip(Some(&p.finish()), &[("0", bytes)])
    };
    let six = || f32_bytes(&[0., 1., 2., 3., 4., 5.]);
    refused(&one(8, 0, &[8], &[1], six()), "truncated");
    refused(&one(6, 5, &[2], &[1], six()), "reaches past its storage");
    refused(&one(6, 0, &[2, 3], &[3, 2], six()), "reaches past its storage");
    refused(&one(6, 0, &[2], &[i32::MAX as usize], six()), "reaches past its storage");
    // Stride 0 expands one value: fine when small, refused when it asks for billions.
    let c = load(&one(1, 0, &[4], &[0], f32_bytes(&[7.]))).unwrap();
    assert!(matches!(&c.entries["a"], Entry::Tensor { tensor, .. } if tensor.data == [7.; 4]));
    refused(&one(1, 0, &[1 << 20, 1 << 20], &[0, 0], f32_bytes(&[7.])), "more values than a checkpoint may hold");
    refused(&one(1, 0, &[1 << 30, 1 << 30, 1 << 30], &[0, 0, 0], f32_bytes(&[7.])), "more values");
    // Many stride-0 views of one storage are counted together.
    let mut p = Pickle::new();
    p.op(b'}').mark();
    for i in 0..3 {
        p.str(&format!("v{i}")).tensor("FloatStorage", "0", 1, 0, &[1 << 26], &[0]);
    }
    p.op(b'u');
    refused(&torch_zip(Some(&p.finish()), &[("0", f32_bytes(&[7.]))]), "more values");
    // A negative size or offset.
    let mut p = Pickle::new();
    p.op(b'}').mark().str("a").tensor("FloatStorage", "0", 1, 0, &[1], &[1]).op(b'u');
    let bytes = p.finish();
    let neg = |from: i32| {
        let mut b = bytes.clone();
        let at = b.windows(5).rposition(|w| w == [b'J', 1, 0, 0, 0]).unwrap();
        b[at + 1..at + 5].copy_from_slice(&from.to_le_bytes());
        torch_zip(Some(&b), &[("0", f32_bytes(&[7.]))])
    };
    assert!(matches!(&load(&neg(-1)).unwrap().entries["a"], Entry::Other(w) if w.contains("stride")));
}

#[test]
fn zip_members_duplicate_absent_corrupt_or_escaping() {
    let mut p = Pickle::new();
    p.op(b'}').mark().str("a").tensor("FloatStorage", "0", 1, 0, &[1], &[1]).op(b'u');
    let pkl = p.finish();
    // The same storage twice, with different contents (ZipWriter refuses to write that, so the
    // second member is renamed in place).
    let mut dup = torch_zip(Some(&pkl), &[("0", f32_bytes(&[1.])), ("1", f32_bytes(&[2.]))]);
    let (from, to) = (b"archive/data/1", b"archive/data/0");
    while let Some(i) = dup.windows(from.len()).position(|w| w == from) {
        dup[i..i + from.len()].copy_from_slice(to);
    }
    refused(&dup, "appears twice");
    // Absent storage.
    refused(&torch_zip(Some(&pkl), &[]), "storage archive/data/0");
    // A storage key that climbs out of the archive: looked up inside the zip only.
    let mut p = Pickle::new();
    let key = "../../../../etc/passwd";
    p.op(b'}').mark().str("a").tensor("FloatStorage", key, 1, 0, &[1], &[1]).op(b'u');
    refused(&torch_zip(Some(&p.finish()), &[]), "storage archive/data/../../../../etc/passwd");
    let c = load(&torch_zip(Some(&pkl), &[("0", f32_bytes(&[1.])), ("../../x", f32_bytes(&[2.]))])).unwrap();
    assert!(matches!(&c.entries["a"], Entry::Tensor { tensor, .. } if tensor.data == [1.]));
    // A flipped byte in a storage: its CRC fails.
    let mut bad = torch_zip(Some(&pkl), &[("0", f32_bytes(&[1.5]))]);
    let at = bad.windows(4).position(|w| w == 1.5f32.to_le_bytes()).unwrap();
    bad[at] ^= 0x55;
    refused(&bad, "tensor `a`");
    // A member whose headers declare 4 GB: read up to what is there, then refused.
    let mut huge = torch_zip(Some(&pkl), &[("0", f32_bytes(&[1.]))]);
    let name = b"archive/data/0";
    for sig in [&b"PK\x03\x04"[..], &b"PK\x01\x02"[..]] {
        let mut from = 0;
        while let Some(i) = huge[from..].windows(4).position(|w| w == sig).map(|i| i + from) {
            let (size_at, name_at) = if sig[2] == 3 { (i + 22, i + 30) } else { (i + 24, i + 46) };
            if huge[name_at..].starts_with(name) {
                huge[size_at..size_at + 4].copy_from_slice(&0xffff_fff0u32.to_le_bytes());
            }
            from = i + 4;
        }
    }
    assert!(load(&huge).is_err());
}

#[test]
fn deep_nesting_and_cycles_do_not_overflow_the_stack() {
    // A tuple a million deep (EMPTY_TUPLE, then TUPLE1 again and again).
    opaque(&with_bad(|p| p.op(b')').out.extend(std::iter::repeat_n(0x85, 1_000_000))), "tuple");
    // Lists half a million deep: that many EMPTY_LISTs, then APPEND each into the one below.
    let lists = |p: &mut Pickle| {
        p.out.extend(std::iter::repeat_n(b']', 500_000));
        p.out.extend(std::iter::repeat_n(b'a', 499_999));
    };
    opaque(&with_bad(lists), "list");
    // A call chain a million deep: `os.system()()()...`.
    let calls = |p: &mut Pickle| {
        p.global("os", "system");
        for _ in 0..1_000_000 {
            p.op(b')').op(b'R');
        }
    };
    opaque(&with_bad(calls), "os.system");
    // A list that holds itself, and a parameter whose data is itself: refused (reference counts
    // would never free them: the pickle fuzz target ran out of memory after 7.5 million such
    // streams), everything the stream made freed (src/checkpoint/cycles.rs tests that).
    refused(
        &with_bad(|p| {
            p.op(b']').op(b'q').op(1).op(b'h').op(1).op(b'a');
        }),
        "holds itself",
    );
    let param = |p: &mut Pickle| {
        p.global("torch._utils", "_rebuild_parameter").op(b']').op(b'q').op(1).op(b'R').op(b'q').op(2);
        p.op(b'h').op(1).op(b'h').op(2).op(b'a').op(b'0');
    };
    refused(&with_bad(param), "holds itself");
    // One held only by the memo, not by the result, is refused as well.
    refused(
        &with_bad(|p| {
            p.op(b']').op(b'q').op(3).op(b'h').op(3).op(b'a').op(b'0').op(b'N');
        }),
        "holds itself",
    );
}

#[test]
fn huge_declared_lengths_and_copy_bombs() {
    // Lengths far past the end: BINUNICODE8, BINBYTES8, BINUNICODE, LONG4, FRAME.
    refused(&with_bad(|p| p.op(0x8d).out.extend(u64::MAX.to_le_bytes())), "ends early");
    refused(&with_bad(|p| p.op(0x8e).out.extend((1u64 << 62).to_le_bytes())), "ends early");
    refused(&with_bad(|p| p.op(b'X').out.extend(u32::MAX.to_le_bytes())), "ends early");
    refused(&with_bad(|p| p.op(0x8b).out.extend(u32::MAX.to_le_bytes())), "ends early");
    let c = load(&with_bad(|p| p.int(1).op(0x95).out.extend(u64::MAX.to_le_bytes()))).unwrap();
    assert!(matches!(&c.entries["good"], Entry::Tensor { .. }));
    // DUP and GET of a large string: shared, not copied.
    let big = "x".repeat(1 << 20);
    let dups = |p: &mut Pickle| {
        p.mark().str(&big).op(b'q').op(0);
        for _ in 0..200_000 {
            p.op(b'2').op(b'h').op(0);
        }
        p.op(b'l');
    };
    opaque(&with_bad(dups), "list");
    // Doubling: (DUP, TUPLE2) 64 times is 2^64 leaves if copied.
    opaque(&with_bad(|p| p.op(b')').out.extend([b'2', 0x86].repeat(64))), "tuple");
    // One dict of 20k items merged into another 50k times by BUILD: quadratic if allowed.
    let builds = |p: &mut Pickle| {
        p.op(b'}').mark();
        for i in 0..20_000 {
            p.int(i).op(b'N');
        }
        p.op(b'u').op(b'q').op(3).op(b'0').op(b'}');
        for _ in 0..50_000 {
            p.op(b'h').op(3).op(b'b');
        }
    };
    refused(&with_bad(builds), "too many items copied");
}
