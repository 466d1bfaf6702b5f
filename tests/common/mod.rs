//! Helpers shared by the integration tests: where the reference fixture lives, and a small
//! pickle writer that makes `torch.save`-style archives without Python.

#![allow(dead_code)]

use std::io::Write;
use std::path::PathBuf;
use std::process::{Command, Output};

/// The reference fixture directory: `$PRL_GOLDEN_DIR`, else `../shared/fixtures/prl-golden-v1`.
pub fn golden_dir() -> PathBuf {
    let dir = std::env::var_os("PRL_GOLDEN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/fixtures/prl-golden-v1"));
    assert!(
        dir.join("checkpoint.pth").exists(),
        "reference fixture not found at {} (set PRL_GOLDEN_DIR)",
        dir.display()
    );
    dir
}

/// A pickle stream written opcode by opcode (protocol 2, as `torch.save` writes).
#[derive(Default)]
pub struct Pickle {
    pub out: Vec<u8>,
}

impl Pickle {
    pub fn new() -> Self {
        Pickle { out: vec![0x80, 2] }
    }
    pub fn op(&mut self, b: u8) -> &mut Self {
        self.out.push(b);
        self
    }
    pub fn mark(&mut self) -> &mut Self {
        self.op(b'(')
    }
    pub fn str(&mut self, s: &str) -> &mut Self {
        self.op(b'X');
        self.out.extend((s.len() as u32).to_le_bytes());
        self.out.extend(s.as_bytes());
        self
    }
    pub fn int(&mut self, i: i32) -> &mut Self {
        self.op(b'J');
        self.out.extend(i.to_le_bytes());
        self
    }
    pub fn float(&mut self, f: f64) -> &mut Self {
        self.op(b'G');
        self.out.extend(f.to_be_bytes());
        self
    }
    pub fn bytes(&mut self, b: &[u8]) -> &mut Self {
        self.op(b'C');
        self.out.push(b.len() as u8);
        self.out.extend(b);
        self
    }
    pub fn global(&mut self, module: &str, name: &str) -> &mut Self {
        self.op(b'c');
        self.out.extend(format!("{module}\n{name}\n").as_bytes());
        self
    }
    pub fn tuple_of_ints(&mut self, v: &[usize]) -> &mut Self {
        self.mark();
        for &x in v {
            self.int(x as i32);
        }
        self.op(b't')
    }
    /// `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, False, OrderedDict())`.
    pub fn tensor(
        &mut self,
        storage_type: &str,
        key: &str,
        numel: usize,
        offset: usize,
        size: &[usize],
        stride: &[usize],
    ) -> &mut Self {
        self.global("torch._utils", "_rebuild_tensor_v2").mark();
        self.mark()
            .str("storage")
            .global("torch", storage_type)
            .str(key)
            .str("cpu")
            .int(numel as i32)
            .op(b't')
            .op(b'Q');
        self.int(offset as i32).tuple_of_ints(size).tuple_of_ints(stride).op(0x89);
        self.global("collections", "OrderedDict").op(b')').op(b'R');
        self.op(b't').op(b'R')
    }
    pub fn finish(&mut self) -> Vec<u8> {
        self.op(b'.');
        std::mem::take(&mut self.out)
    }
}

/// A zip archive laid out as `torch.save` does: `archive/data.pkl`, `archive/data/<key>`...
pub fn torch_zip(pkl: Option<&[u8]>, storages: &[(&str, Vec<u8>)]) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    {
        let mut z = zip::ZipWriter::new(&mut buf);
        let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
        if let Some(pkl) = pkl {
            z.start_file("archive/data.pkl", opts).unwrap();
            z.write_all(pkl).unwrap();
        }
        z.start_file("archive/byteorder", opts).unwrap();
        z.write_all(b"little").unwrap();
        for (key, bytes) in storages {
            z.start_file(format!("archive/data/{key}"), opts).unwrap();
            z.write_all(bytes).unwrap();
        }
        z.start_file("archive/version", opts).unwrap();
        z.write_all(b"3\n").unwrap();
        z.finish().unwrap();
    }
    buf.into_inner()
}

/// Little-endian f32 bytes.
pub fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// A plan compiled from the reference checkpoint, once per test process (kept for its lifetime);
/// `$PRL_REFERENCE_PLAN` names one compiled elsewhere instead (the aarch64 check under qemu runs
/// the goldens on the plan compiled on x86: plans are portable).
pub fn reference_plan() -> PathBuf {
    static PLAN: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    PLAN.get_or_init(|| {
        if let Some(dir) = std::env::var_os("PRL_REFERENCE_PLAN") {
            eprintln!("NOTE: the reference plan is $PRL_REFERENCE_PLAN = {}", PathBuf::from(&dir).display());
            return PathBuf::from(dir);
        }
        let source = prl_compiler::WeightsSource::Checkpoint(golden_dir().join("checkpoint.pth"));
        let model = prl_compiler::build_model(&source).expect("build");
        let plan = prl_compiler::compile(&model, &prl_runtime::TrackerConfig::default()).expect("compile");
        let dir = tempfile::tempdir().expect("tempdir").keep();
        plan.write(&dir).expect("write plan");
        dir
    })
    .clone()
}

/// Run the `prl` binary with `args` from the repository root.
pub fn prl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_prl")).args(args).current_dir(env!("CARGO_MANIFEST_DIR")).output().unwrap()
}

/// The standard output of a run that must have succeeded (its standard error otherwise).
pub fn ok(o: &Output) -> String {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The shared UAV123@10fps sequence `name`, beside the reference fixture.
pub fn sequence(name: &str) -> PathBuf {
    golden_dir().join("../../data/uav123_10fps").join(name)
}

/// The NanoTrack v2 files shipped in the repository (`models/nanotrack-v2`).
pub fn nanotrack_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/nanotrack-v2")
}

/// The official NanoTrack loop's boxes (`../shared/fixtures/nanotrack-v2-ref`, beside the PRL
/// fixture; `$NANOTRACK_REF_DIR` points elsewhere).
pub fn nanotrack_ref_dir() -> PathBuf {
    let dir = std::env::var_os("NANOTRACK_REF_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| golden_dir().join("../nanotrack-v2-ref"));
    assert!(
        dir.join("building4.txt").exists(),
        "NanoTrack reference not found at {} (set NANOTRACK_REF_DIR)",
        dir.display()
    );
    dir
}

/// NanoTrack v2 imported from the shipped files and compiled into an fp32 plan in `dir`.
pub fn nanotrack_plan(dir: &std::path::Path) -> PathBuf {
    let n = nanotrack_dir();
    let model = prl_compiler::import_nanotrack(
        &n.join("nanotrack_backbone_sim.onnx"),
        &n.join("nanotrack_head_sim.onnx"),
        Some(&n.join("configv2.yaml")),
    )
    .expect("import");
    let tracker = model.manifest.tracker.clone().expect("imported models carry their settings");
    let plan = prl_compiler::compile(&model, &tracker).expect("compile");
    let out = dir.join("nanotrack-plan");
    plan.write(&out).expect("write plan");
    out
}

/// Nodes of a plan's optimised search graph that multiply on integers (see
/// [`prl_runtime::Plan::integer_nodes`]).
pub fn int8_kernel_nodes(plan: &prl_runtime::Plan) -> Vec<String> {
    plan.integer_nodes().into_iter().map(|n| n.name).collect()
}
