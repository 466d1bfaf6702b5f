//! Compiled plans: a directory with `plan.json` and the template and search graphs as
//! decluttered NNEF (uncompressed tar: gzip would make them 28% smaller but add about 0.4 s of
//! decompression to every load), checked against the manifest's hashes and optimised when
//! loaded.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use sha2::{Digest, Sha256};
use tract_nnef::prelude::*;
use tract_nnef::tract_core::knobs::KnobScope;

use crate::{nnef, Error, PlanManifest, Result, Winograd, PLAN_FORMAT_VERSION, PLAN_MANIFEST};

/// An optimised graph, and whether it runs on the calling thread whatever the thread setting.
#[derive(Clone)]
struct Runnable {
    plan: Arc<TypedSimplePlan>,
    serial: bool,
}

/// A graph none of whose operators reaches this many multiply-adds runs on the calling thread
/// whatever [`set_threads`] says: splitting its layers costs more than it saves. (NanoTrack's
/// largest layer has 7 M; on a 2-vCPU VM each hand-over to the pool cost 20-100 µs, and two
/// threads took its search step from 1.9 to 4.3 ms. PRL-Track's layers have 10 to 1000 times
/// more and keep their threads.)
const SPLIT_MACS: f64 = (1 << 24) as f64;

impl Runnable {
    fn new(plan: Arc<TypedSimplePlan>) -> Runnable {
        let model = plan.model();
        let largest = model.nodes().iter().map(|n| node_flop(model, n) / 2.0).fold(0.0, f64::max);
        Runnable { serial: largest < SPLIT_MACS, plan }
    }

    /// `f` with tract's executor for this graph: the calling thread alone when `serial`; else
    /// split over the pool's threads ([`crate::threads::split_run`]).
    fn scope<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        use tract_linalg::multithread::{multithread_tract_scope, Executor};
        if self.serial {
            return multithread_tract_scope(Executor::SingleThread, f);
        }
        crate::threads::split_run(f)
    }

    fn run(&self, inputs: TVec<TValue>) -> TractResult<TVec<TValue>> {
        self.scope(|| self.plan.run(inputs))
    }

    fn model(&self) -> &TypedModel {
        self.plan.model()
    }
}

/// A loaded, optimised plan. Cloning it is cheap (the optimised graphs are shared), so that
/// several trackers (targets) can run one plan, on several threads at once.
#[derive(Clone)]
pub struct Plan {
    dir: PathBuf,
    manifest: PlanManifest,
    /// The convolutions that run as Winograd's: the manifest's choice, or `PRL_WINOGRAD`'s.
    winograd: Winograd,
    /// Whether `PRL_WINOGRAD` made that choice rather than the manifest.
    winograd_from_env: bool,
    template: Runnable,
    search: Runnable,
}

/// The template graph's outputs for one target (`zf1..zf5`), kept as tract values.
#[derive(Clone)]
pub struct TemplateFeatures(TVec<TValue>);

impl TemplateFeatures {
    /// Each feature tensor flattened row-major, in the search graph's input order.
    pub fn to_vecs(&self) -> Result<Vec<Vec<f32>>> {
        self.0.iter().map(|v| to_vec(v, "template")).collect()
    }
}

/// A graph's f32 value flattened row-major.
fn to_vec(v: &TValue, graph: &'static str) -> Result<Vec<f32>> {
    let flat = v.try_as_plain_ram().and_then(|v| v.as_slice::<f32>().map(<[f32]>::to_vec));
    flat.map_err(|e| run_err(graph, e))
}

/// The search graph's outputs, flattened row-major, in the graph's (and the manifest's) order:
/// PRL-Track `loc`, `cls1`, `cls2`; NanoTrack `cls`, `loc` ([`crate::Family::search_outputs`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SearchOutput {
    /// One flattened tensor per output.
    pub outputs: Vec<Vec<f32>>,
}

impl Plan {
    /// Load the plan in directory `dir`: read `plan.json`, check the format and each graph's
    /// SHA-256, load the NNEF graphs and optimise them.
    pub fn load(dir: impl AsRef<Path>) -> Result<Plan> {
        let dir = dir.as_ref().to_path_buf();
        let mpath = dir.join(PLAN_MANIFEST);
        let bytes = std::fs::read(&mpath).map_err(|e| Error::Io { path: mpath.clone(), err: e })?;
        let bad = |path: &Path, msg: String| Error::Plan { path: path.to_path_buf(), msg };
        let manifest: PlanManifest =
            serde_json::from_slice(&bytes).map_err(|e| bad(&mpath, format!("not a plan manifest: {e}")))?;
        if manifest.format_version != PLAN_FORMAT_VERSION {
            return Err(bad(
                &mpath,
                format!(
                    "plan format {} of model `{}`; this runtime reads format {PLAN_FORMAT_VERSION}",
                    manifest.format_version, manifest.model
                ),
            ));
        }
        manifest.check().map_err(|msg| bad(&mpath, msg))?;
        let knobs = manifest.optimizer_knobs.iter().map(|(k, v)| (k.as_str(), v.as_str()));
        let knobs = KnobScope::new(knobs).map_err(|e| bad(&mpath, format!("optimizer_knobs: {e}")))?;
        // (None with tract's operators alone: `WinogradConv` is one of the runtime's.)
        let (winograd, winograd_from_env) = match (crate::ops::own_operators(), Winograd::from_env()) {
            (true, Some(forced)) => (forced, true),
            (true, None) => (manifest.winograd, false),
            (false, _) => (Winograd::Off, false),
        };
        // The two graphs load and optimise independently: side by side.
        let (template, search) = std::thread::scope(|s| {
            let t = s.spawn(|| load_graph(&dir, &manifest.template, &knobs, winograd));
            let search = load_graph(&dir, &manifest.search, &knobs, winograd);
            (t.join().expect("template loader panicked"), search)
        });
        let (template, search) = (template?, search?);
        Ok(Plan { dir, manifest, winograd, winograd_from_env, template, search })
    }

    /// The plan's manifest.
    pub fn manifest(&self) -> &PlanManifest {
        &self.manifest
    }

    /// The convolutions that run as Winograd's: the plan's choice (`plan.json`'s `winograd`),
    /// or `PRL_WINOGRAD`'s where it is set ([`Winograd::from_env`]); none with tract's
    /// operators alone (`PRL_OPS=tract`).
    pub fn winograd(&self) -> Winograd {
        self.winograd
    }

    /// Whether [`Self::winograd`] is `PRL_WINOGRAD`'s choice rather than the plan's.
    pub fn winograd_from_env(&self) -> bool {
        self.winograd_from_env
    }

    /// The directory the plan was loaded from.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Run the template graph on a float NCHW BGR crop (`[1,3,127,127]`, row-major): the
    /// target's features, in the search graph's input order after the crop.
    pub fn template(&self, z: &[f32]) -> Result<TemplateFeatures> {
        let input = tensor("template", &self.manifest.template.inputs[0].shape, z)?;
        let outs = self.template.run(tvec![input.into()]).map_err(|e| run_err("template", e))?;
        Ok(TemplateFeatures(outs))
    }

    /// Template features from flattened tensors (in the search graph's input order, as
    /// [`TemplateFeatures::to_vecs`] gives them), checked against the manifest's shapes: to run
    /// the search graph on features recorded elsewhere.
    pub fn template_features(&self, vecs: Vec<Vec<f32>>) -> Result<TemplateFeatures> {
        let outs = &self.manifest.template.outputs;
        if vecs.len() != outs.len() {
            return Err(Error::Input(format!("{} template feature tensors; the plan has {}", vecs.len(), outs.len())));
        }
        let values = outs
            .iter()
            .zip(vecs)
            .map(|(t, v)| tensor("template", &t.shape, &v).map(TValue::from))
            .collect::<Result<TVec<_>>>()?;
        Ok(TemplateFeatures(values))
    }

    /// Run the search graph on a float NCHW BGR crop (`[1,3,instance,instance]`) with a target's
    /// features.
    pub fn search(&self, x: &[f32], zf: &TemplateFeatures) -> Result<SearchOutput> {
        self.search_input(tensor("search", &self.manifest.search.inputs[0].shape, x)?, zf)
    }

    /// [`Self::search`] on the input as a tensor of the graph's input shape (the tracker's
    /// crop, written there directly: no copy).
    pub(crate) fn search_input(&self, input: Tensor, zf: &TemplateFeatures) -> Result<SearchOutput> {
        let want = &self.manifest.search.inputs[0].shape;
        if input.shape() != want.as_slice() {
            let msg = format!("input of shape {:?} for {want:?}", input.shape());
            return Err(Error::Run { graph: "search", msg });
        }
        let mut inputs: TVec<TValue> = tvec![input.into()];
        inputs.extend(zf.0.iter().cloned());
        let outs = self.search.run(inputs).map_err(|e| run_err("search", e))?;
        let outputs = outs.iter().map(|o| to_vec(o, "search")).collect::<Result<_>>()?;
        Ok(SearchOutput { outputs })
    }
}

/// Time spent in one node of an optimised graph, averaged over the profiled runs.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeTime {
    /// Node name (names follow the network's modules: `backbone.layer2.conv`, `s1`, `hmg...`).
    pub name: String,
    /// tract operator after optimisation.
    pub op: String,
    /// Mean time per run.
    pub time: std::time::Duration,
    /// Floating-point operations per run as tract counts them (2 per multiply-accumulate).
    pub flop: f64,
    /// The kernel it runs: the runtime's path for its own operators (`avx512`, `avx2+fma`,
    /// `neon`, `portable`, `vnni`, `amx`), tract's matrix kernel for its products
    /// (`avx512_mmm_f32_32x12`, `arm64simd_mmm_i32_8x8_dot`, ...), empty otherwise.
    pub kernel: String,
}

/// One operator of an optimised graph, as tract describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeInfo {
    /// Node name.
    pub name: String,
    /// tract operator after optimisation (`OptMatMul`, `Im2col`, ...).
    pub op: String,
    /// tract's own description of it (for matrix products: shapes and the kernel chosen, such
    /// as `avx512vnni_mmm_i32_16x16` for an int8 product).
    pub info: String,
    /// The kernel it runs, as [`NodeTime::kernel`] names it.
    pub kernel: String,
}

impl Plan {
    /// Every operator of the optimised search graph: what really runs.
    pub fn search_nodes(&self) -> Vec<NodeInfo> {
        let model = self.search.model();
        model
            .nodes()
            .iter()
            .map(|n| {
                let (op, info) = (n.op().name().to_string(), n.op().info().map(|v| v.join("; ")).unwrap_or_default());
                NodeInfo { name: n.name.clone(), kernel: crate::ops::kernel_name(&op, &info), op, info }
            })
            .collect()
    }

    /// Nodes of the optimised search graph that multiply on integers: tract's i32 matrix
    /// kernels (`mmm_i32` in their description: `avx512vnni_mmm_i32_16x16`,
    /// `arm64simd_mmm_i32_8x8_dot`, ...) or the runtime's u8 x i8 convolutions (depthwise ones too). Empty for an fp32
    /// plan; an int8 plan's integer layers where the machine runs them as integers.
    pub fn integer_nodes(&self) -> Vec<NodeInfo> {
        self.search_nodes()
            .into_iter()
            .filter(|n| {
                (n.op == "OptMatMul" && n.info.contains("mmm_i32")) || n.op == "PackedQConv" || n.op == "DepthwiseQConv"
            })
            .collect()
    }

    /// Whether the template and the search graph run on the calling thread whatever the thread
    /// setting (none of their operators is large enough to split over threads).
    pub fn single_threaded(&self) -> (bool, bool) {
        (self.template.serial, self.search.serial)
    }

    /// tract's per-node profile of the search graph: each node timed over `runs` runs, slowest
    /// first.
    pub fn profile_search(&self, x: &[f32], zf: &TemplateFeatures, runs: usize) -> Result<Vec<NodeTime>> {
        profile(&self.search, "search", runs, || {
            let input = tensor("search", &self.manifest.search.inputs[0].shape, x)?;
            let mut inputs: TVec<TValue> = tvec![input.into()];
            inputs.extend(zf.0.iter().cloned());
            Ok(inputs)
        })
    }

    /// tract's per-node profile of the template graph on the exemplar crop `z` (as
    /// [`Plan::profile_search`]).
    pub fn profile_template(&self, z: &[f32], runs: usize) -> Result<Vec<NodeTime>> {
        profile(&self.template, "template", runs, || {
            Ok(tvec![tensor("template", &self.manifest.template.inputs[0].shape, z)?.into()])
        })
    }
}

/// Each node of `plan` timed over `runs` runs on `inputs()`, slowest first.
fn profile(
    plan: &Runnable,
    graph: &'static str,
    runs: usize,
    inputs: impl Fn() -> Result<TVec<TValue>>,
) -> Result<Vec<NodeTime>> {
    let runs = runs.max(1);
    let model = plan.model();
    let mut totals = vec![std::time::Duration::ZERO; model.nodes().len()];
    let mut state = TypedSimpleState::new(&plan.plan).map_err(|e| run_err(graph, e))?;
    for _ in 0..runs {
        let inputs = inputs()?;
        plan.scope(|| {
            state.run_plan_with_eval(inputs, |ctx, st, node, inputs| {
                let t = std::time::Instant::now();
                let r = tract_nnef::tract_core::plan::eval(ctx, st, node, inputs);
                totals[node.id] += t.elapsed();
                r
            })
        })
        .map_err(|e| run_err(graph, e))?;
    }
    let mut out: Vec<NodeTime> = model
        .nodes()
        .iter()
        .map(|n| NodeTime {
            name: n.name.clone(),
            op: n.op().name().to_string(),
            time: totals[n.id] / runs as u32,
            flop: node_flop(model, n),
            kernel: crate::ops::kernel_name(n.op().name().as_ref(), &n.op().info().unwrap_or_default().join("; ")),
        })
        .collect();
    out.sort_by_key(|n| std::cmp::Reverse(n.time));
    Ok(out)
}

/// 2 x the multiply-accumulates tract's cost model gives a node (0 when it has none).
fn node_flop(model: &TypedModel, node: &TypedNode) -> f64 {
    let facts = model.node_input_facts(node.id).unwrap_or_default();
    let cost = node.op.cost(&facts).unwrap_or_default();
    cost.iter()
        .filter(|(c, _)| matches!(c, tract_nnef::tract_core::ops::Cost::FMA(_)))
        .filter_map(|(_, n)| n.to_i64().ok())
        .map(|n| 2.0 * n as f64)
        .sum()
}

fn tensor(graph: &'static str, shape: &[usize], data: &[f32]) -> Result<Tensor> {
    Tensor::from_shape(shape, data)
        .map_err(|e| Error::Run { graph, msg: format!("input of {} values for shape {shape:?}: {e}", data.len()) })
}

fn run_err(graph: &'static str, e: TractError) -> Error {
    Error::Run { graph, msg: format!("{e:#}").replace('\n', " ") }
}

fn load_graph(dir: &Path, info: &crate::GraphInfo, knobs: &KnobScope, winograd: Winograd) -> Result<Runnable> {
    let path = dir.join(&info.file);
    let bytes = std::fs::read(&path).map_err(|e| Error::Io { path: path.clone(), err: e })?;
    let bad = |msg: String| Error::Plan { path: path.clone(), msg };
    let tract_err = |e: TractError| bad(format!("{e:#}").replace('\n', " "));
    // The digest is computed while the graph is parsed; a mismatch is reported first.
    // tract-nnef can panic on a malformed archive (an out-of-range reshape slice; found by
    // fuzzing): a panic there is an error naming the file, not an abort.
    let (digest, model) = std::thread::scope(|s| {
        let digest = s.spawn(|| Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect::<String>());
        // Its parser takes time exponential in an expression's nesting (fuzzing found a plan
        // that parsed for ever): it reads only an archive holding what a plan holds, nested no
        // deeper than plans are.
        let parse = || crate::check_graph_archive(&bytes).map(|()| nnef().model_for_read(&mut &*bytes));
        let model = crate::catch_quietly(parse);
        (digest.join().expect("hashing does not panic"), model)
    });
    if digest != info.sha256 {
        return Err(bad(format!(
            "sha256 {digest} does not match the manifest's {} (corrupt or replaced file)",
            info.sha256
        )));
    }
    let model = model.ok_or_else(|| bad("tract-nnef cannot read it: the graph is malformed".into()))?;
    let model = model.map_err(bad)?.map_err(tract_err)?;
    if model.inputs.len() != info.inputs.len() || model.outputs.len() != info.outputs.len() {
        return Err(bad(format!(
            "graph has {} inputs and {} outputs, the manifest says {} and {}",
            model.inputs.len(),
            model.outputs.len(),
            info.inputs.len(),
            info.outputs.len()
        )));
    }
    // The tracker indexes the outputs by the manifest's shapes (checked against its settings):
    // a graph that takes or gives other shapes is refused here, not found out mid-track.
    let inputs = info.inputs.iter().enumerate().map(|(i, t)| ("input", t, model.input_fact(i)));
    let outputs = info.outputs.iter().enumerate().map(|(i, t)| ("output", t, model.output_fact(i)));
    for (what, t, fact) in inputs.chain(outputs) {
        let fact = fact.map_err(tract_err)?;
        if fact.shape.as_concrete() != Some(&t.shape[..]) {
            return Err(bad(format!(
                "{what} `{}` has shape {:?} in the graph, {:?} in the manifest",
                t.name, fact.shape, t.shape
            )));
        }
    }
    // A graph that parses and has the manifest's shapes can still be malformed inside (a crafted
    // plan carries its own digest): a panic in tract's declutter or codegen, as in its parse, is
    // an error naming the file.
    let optimise = || {
        knobs.enter(|| {
            // Declutter first: constants reach the convolutions' weight and bias inputs (the
            // graph read from NNEF is not in the form the runtime's operators match).
            let mut model = model.into_decluttered()?;
            if crate::ops::own_operators() {
                crate::accelerate_with(&mut model, winograd)?;
            }
            model.optimize()?; // codegen only: the model is decluttered already
            TypedSimplePlan::new(model).map(Runnable::new)
        })
    };
    crate::catch_quietly(optimise)
        .ok_or_else(|| bad("tract cannot optimise it: the graph is malformed".into()))?
        .map_err(tract_err)
}
