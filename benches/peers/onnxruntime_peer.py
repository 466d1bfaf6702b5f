"""ONNX Runtime against prl on the same template.onnx / search.onnx, interleaved in one run.

For each thread count, rounds alternate between `prl bench` (the compiled plan of the same
model, through the tracker) and ONNX Runtime's CPU provider on the ONNX files the plan was
compiled from, fed the very tensors prl used (`prl bench --save-tensors`). The report gives the
medians over all rounds and the ratio prl / ONNX Runtime (below 1.0: prl is faster).
Run it through run.sh, which sets ONNX Runtime up in a virtual environment.
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import onnxruntime as ort


def sh(cmd):
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if r.returncode != 0:
        sys.exit(f"error: {' '.join(cmd)} failed:\n{r.stderr.strip()}")
    return r.stdout


def weights_sha(path):
    with open(path) as f:
        return json.load(f).get("weights", {}).get("sha256")


def model_and_plan(args, work):
    """The ONNX model directory and the plan compiled from it (built fresh unless given)."""
    model, plan = args.model, args.plan
    if model is None:
        model = os.path.join(work, "build")
        sh([args.prl, "build", "--out", model] + args.build_args)
    if plan is None:
        plan = os.path.join(work, "plan")
        sh([args.prl, "compile", "--model", model, "--out", plan])
    a = weights_sha(os.path.join(model, "manifest.json"))
    b = weights_sha(os.path.join(plan, "plan.json"))
    if a != b:
        sys.exit(f"error: {model} (weights {a}) and {plan} (weights {b}) are not the same model")
    return model, plan


def load_tensors(d):
    with open(os.path.join(d, "tensors.json")) as f:
        shapes = json.load(f)
    return {n: np.fromfile(os.path.join(d, n + ".f32"), dtype="<f4").reshape(s) for n, s in shapes.items()}


def session(path, threads):
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def feeds(sess, tensors):
    return {i.name: tensors[i.name] for i in sess.get_inputs()}


def timed(sess, feed, runs):
    out = []
    for _ in range(runs):
        t = time.perf_counter()
        sess.run(None, feed)
        out.append((time.perf_counter() - t) * 1e3)
    return out


def agreement(sess, feed, tensors):
    """Largest difference between ONNX Runtime's and prl's outputs, relative to their range."""
    worst = 0.0
    for o, v in zip(sess.get_outputs(), sess.run(None, feed)):
        ref = tensors[o.name]
        worst = max(worst, float(np.abs(v - ref).max() / max(np.abs(ref).max(), 1e-12)))
    return worst


def median(v):
    return statistics.median(v)


def ort_int8(search_onnx, feed, out, weights="s8"):
    """ONNX Runtime's own int8 of the search graph: quantize_static, QDQ, per-channel weights
    (i8, or u8 with `weights="u8"`), u8 activations, calibrated on the crop prl benchmarked
    (ranges do not change the latency). Biases stay float: with one calibration crop ORT finds
    no valid scale for some of them."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.items = [feed]

        def get_next(self):
            return self.items.pop() if self.items else None

    quantize_static(search_onnx, out, Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QUInt8,
                    weight_type=QuantType.QUInt8 if weights == "u8" else QuantType.QInt8,
                    extra_options={"QuantizeBias": False})
    return out


def relative_error(got, ref):
    """‖got − ref‖ / ‖ref‖ over every output (`prl compare`'s measure)."""
    num = sum(float(np.sum((got[n] - ref[n]) ** 2)) for n in ref)
    den = sum(float(np.sum(ref[n] ** 2)) for n in ref)
    return (num / max(den, 1e-30)) ** 0.5


def ort_int8_exactness():
    """Whether ONNX Runtime's int8 convolution is exact on this CPU: a 1x1 QLinearConv of 64 u8
    channels at 255 against i8 weights of 127 (the extremes of the u8 x s8 products its QDQ
    models run), scaled so the exact sum, 64·255·127, requantises to 200. Where the CPU has no
    VNNI, MLAS multiplies u8 by s8 with `vpmaddubsw`, whose pairs of products saturate at
    32767, and gives about half of it (ONNX Runtime's quantisation docs name `reduce_range`,
    7-bit weights, for this). Returns the exact result, the one of 16-bit pair sums stopped at
    32767, and ONNX Runtime's."""
    from onnx import TensorProto, helper, numpy_helper

    ci, exact = 64, 200
    scale = 64 * 255 * 127 / exact
    consts = {"xs": np.float32(1), "xz": np.uint8(0), "w": np.full((1, ci, 1, 1), 127, np.int8),
              "ws": np.array([1], np.float32), "wz": np.array([0], np.int8), "ys": np.float32(scale),
              "yz": np.uint8(0)}
    inits = [numpy_helper.from_array(np.asarray(v), n) for n, v in consts.items()]
    node = helper.make_node("QLinearConv", ["x", "xs", "xz", "w", "ws", "wz", "ys", "yz"], ["y"])
    graph = helper.make_graph([node], "probe", [helper.make_tensor_value_info("x", TensorProto.UINT8, [1, ci, 8, 8])],
                              [helper.make_tensor_value_info("y", TensorProto.UINT8, [1, 1, 8, 8])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 14)])
    so = ort.SessionOptions()
    so.log_severity_level = 3
    sess = ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
    y = sess.run(None, {"x": np.full((1, ci, 8, 8), 255, np.uint8)})[0]
    saturated = round((ci // 2) * 32767 / scale)
    return exact, saturated, int(y.ravel()[0])


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--prl", required=True, help="the prl binary")
    p.add_argument("--model", help="model directory from `prl build` (default: build one)")
    p.add_argument("--plan", help="plan compiled from --model (default: compile one)")
    p.add_argument("--threads", default="1,2", help="comma-separated thread counts")
    p.add_argument("--rounds", type=int, default=5, help="interleaved rounds per thread count")
    p.add_argument("--runs", type=int, default=10, help="timed runs per round and runtime")
    p.add_argument("--int8-plan", help="an int8 plan of the same model (`prl quantize`): also time its search "
                   "network against ONNX Runtime's own int8 (quantize_static, QDQ, per-channel) of search.onnx")
    p.add_argument("--json", help="also write the report here")
    p.add_argument("--keep-work", action="store_true",
                   help="keep the work directory under target/ (the model and plan built here, the tensors, "
                        "each round's `prl bench` report); removed at the end otherwise")
    p.add_argument("--build-arg", dest="build_args", action="append", default=[],
                   help="passed to `prl build` when the model is built here (e.g. --build-arg=--random-seed=0)")
    args = p.parse_args()

    work = tempfile.mkdtemp(prefix="prl-peer-", dir="target" if os.path.isdir("target") else None)
    try:
        run(args, work)
    finally:
        # The model, plan, tensors and reports made here (27 MB for PRL-Track) go, unless asked.
        if args.keep_work:
            print(f"kept {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


def cpu_facts():
    """The CPU's model name and whether it has AMX (Linux's /proc/cpuinfo; empty elsewhere)."""
    name, amx = "unknown CPU", False
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and name == "unknown CPU":
                    name = value.strip()
                elif key.strip() == "flags":
                    amx = amx or "amx_int8" in value.split()
    except OSError:
        pass
    return name, amx


def kernels(args, plan, work, tag):
    """Which kernel each replaced operator of `plan` runs (`prl bench`'s per-node profiles of
    both graphs), grouped by operator, and what the runtime may use."""
    j = os.path.join(work, f"kernels-{tag}.json")
    sh([args.prl, "bench", "--plan", plan, "--runs", "1", "--warm-up", "0", "--top", "100000", "--json", j])
    with open(j) as f:
        r = json.load(f)
    counts = {}
    for o in r["top_ops"] + r["template_ops"]:
        if o["kernel"] and o["kernel"] != "-":
            by_op = counts.setdefault(o["op"], {})
            by_op[o["kernel"]] = by_op.get(o["kernel"], 0) + 1
    return r["isa"], counts


def print_kernels(args, plan, work, report):
    name, cpu_amx = cpu_facts()
    plans = [(plan, "fp32")] + ([(args.int8_plan, "int8")] if args.int8_plan else [])
    found = {tag: kernels(args, p, work, tag) for p, tag in plans}
    isa = next(iter(found.values()))[0]
    used = any("amx" in k for _, c in found.values() for by_op in c.values() for k in by_op)
    tract = os.environ.get("TRACT_CPU_ISA", "")
    amx = ("on" if used else "off") + (" (the CPU has it" if cpu_amx else " (the CPU has none") + (
        f"; TRACT_CPU_ISA={tract})" if tract else ")")
    print(f"CPU: {name}; runtime kernels may use: {isa}; AMX: {amx}")
    report["cpu"], report["isa"], report["amx"] = name, isa, amx
    report["kernels"] = {}
    for tag, (_, counts) in found.items():
        line = "; ".join(f"{op} " + ", ".join(f"{k} x{n}" for k, n in sorted(by.items()))
                         for op, by in sorted(counts.items()))
        print(f"  {tag} plan, kernel per replaced operator: {line}")
        report["kernels"][tag] = counts


def int8_peers(args, model, work, tensors, report):
    """ONNX Runtime's int8 forms of `search.onnx` (`ort_int8`: i8 weights, and u8 weights, which
    MLAS multiplies exactly on 16-bit products where the i8 form saturates: the exact peer on AVX2
    without VNNI), made once for every thread count. Before the timing, says whether ONNX
    Runtime's int8 convolution is exact on this CPU (`ort_int8_exactness`) and how far each int8
    search is from fp32 on the benchmarked crop (prl's plan as `prl quantize` calibrated it, ONNX
    Runtime's on this one crop), into `report` too. Returns the two models' paths."""
    exact, saturated, got = ort_int8_exactness()
    verdict = ("exact" if got == exact else
               "saturates: its u8 x s8 pairs of products stop at 32767 (vpmaddubsw)" if got == saturated else
               "not exact")
    print(f"ONNX Runtime's int8 convolution on this CPU: {got} where the exact result is {exact} ({verdict}); "
          "prl's int8 kernels are exact on every path")
    report["onnxruntime_int8_probe"] = {"exact": exact, "onnxruntime": got}
    t8 = os.path.join(work, "tensors-int8")
    sh([args.prl, "bench", "--plan", args.int8_plan, "--runs", "1", "--top", "0", "--save-tensors", t8])
    ours = load_tensors(t8)
    search_onnx = os.path.join(model, "search.onnx")
    search = session(search_onnx, 1)
    sf = feeds(search, tensors)
    q, qu = os.path.join(work, "search-int8.onnx"), os.path.join(work, "search-int8-u8w.onnx")
    ort_int8(search_onnx, sf, q)
    ort_int8(search_onnx, sf, qu, weights="u8")
    names = [o.name for o in search.get_outputs()]
    ref = {n: tensors[n] for n in names}
    # ONNX Runtime's QDQ model as written (no graph optimisation: each quantise and dequantise in
    # float, the convolutions f32): what its quantisation alone costs.
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    so.log_severity_level = 3
    written = ort.InferenceSession(q, so, providers=["CPUExecutionProvider"])

    def outputs(sess):
        return dict(zip(names, sess.run(names, sf)))

    err = {"prl": relative_error({n: ours[n] for n in names}, ref),
           "onnxruntime": relative_error(outputs(session(q, 1)), ref),
           "onnxruntime_qdq_in_float": relative_error(outputs(written), ref),
           "onnxruntime_u8_weights": relative_error(outputs(session(qu, 1)), ref)}
    report["int8_output_error"] = err
    print(f"int8 search outputs against fp32 on this crop, ‖int8 − fp32‖ / ‖fp32‖: prl {err['prl']:.4f}, "
          f"ONNX Runtime {err['onnxruntime']:.4f} (its QDQ model computed in float: "
          f"{err['onnxruntime_qdq_in_float']:.4f}; with u8 weights: {err['onnxruntime_u8_weights']:.4f})")
    return q, qu


def run(args, work):
    model, plan = model_and_plan(args, work)
    tdir = os.path.join(work, "tensors")
    sh([args.prl, "bench", "--plan", plan, "--runs", "1", "--top", "0", "--save-tensors", tdir])
    tensors = load_tensors(tdir)
    if args.int8_plan and weights_sha(os.path.join(args.int8_plan, "plan.json")) != weights_sha(
            os.path.join(plan, "plan.json")):
        sys.exit(f"error: {args.int8_plan} does not hold the weights of {plan}")
    print(f"model {model}, plan {plan}; onnxruntime {ort.__version__}; {args.rounds} rounds x {args.runs} runs")

    report = {"model": model, "plan": plan, "onnxruntime": ort.__version__, "rounds": args.rounds,
              "runs": args.runs, "results": []}
    print_kernels(args, plan, work, report)
    q, qu = int8_peers(args, model, work, tensors, report) if args.int8_plan else (None, None)
    rows = []
    for threads in [int(t) for t in args.threads.split(",")]:
        search = session(os.path.join(model, "search.onnx"), threads)
        template = session(os.path.join(model, "template.onnx"), threads)
        sf, tf = feeds(search, tensors), feeds(template, tensors)
        diff = max(agreement(search, sf, tensors), agreement(template, tf, tensors))
        timed(search, sf, 2)
        timed(template, tf, 2)
        U8W = "search network int8, ORT u8 weights"
        prl = {"template network": [], "search network": [], "search network int8": []}
        peer = {"template network": [], "search network": [], "search network int8": [], U8W: []}
        if args.int8_plan:
            search8, search8u = session(q, threads), session(qu, threads)
            timed(search8, sf, 2)
            timed(search8u, sf, 2)
        for r in range(args.rounds):
            plans = [(plan, "")] + ([(args.int8_plan, " int8")] if args.int8_plan else [])
            for pl, suffix in plans:
                j = os.path.join(work, f"bench-{threads}-{r}{suffix.strip()}.json")
                sh([args.prl, "bench", "--plan", pl, "--threads", str(threads), "--runs", str(args.runs),
                    "--top", "0", "--json", j])
                with open(j) as f:
                    for s in json.load(f)["stages"]:
                        if s["stage"] + suffix in prl and (suffix == "" or s["stage"] == "search network"):
                            prl[s["stage"] + suffix] += s["samples_ms"]
            peer["template network"] += timed(template, tf, args.runs)
            peer["search network"] += timed(search, sf, args.runs)
            if args.int8_plan:
                peer["search network int8"] += timed(search8, sf, args.runs)
                peer[U8W] += timed(search8u, sf, args.runs)
        stages = ("search network", "template network") + (("search network int8", U8W) if args.int8_plan else ())
        for stage in stages:
            mine = prl["search network int8"] if stage == U8W else prl[stage]
            a, b = median(mine), median(peer[stage])
            rows.append((stage, threads, a, b, a / b))
            report["results"].append({"stage": stage, "threads": threads, "prl_median_ms": a,
                                      "onnxruntime_median_ms": b, "ratio": a / b,
                                      "prl_samples_ms": mine, "onnxruntime_samples_ms": peer[stage],
                                      "max_relative_output_difference": diff})
        print(f"{threads} thread(s): outputs agree within {diff:.1e} of their range")

    print(f"\n{'graph':<36} {'threads':>7} {'prl ms':>9} {'ORT ms':>9} {'prl/ORT':>8}")
    for stage, threads, a, b, ratio in rows:
        print(f"{stage:<36} {threads:>7} {a:>9.1f} {b:>9.1f} {ratio:>8.2f}")
    if args.json:
        tmp = args.json + ".tmp"
        with open(tmp, "w") as f:
            json.dump(report, f, indent=2)
        os.replace(tmp, args.json)


if __name__ == "__main__":
    main()
