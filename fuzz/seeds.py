"""Seed corpora for the fuzz targets, made from the shared fixtures (nothing is copied into the
repository): `python3 fuzz/seeds.py SHARED OUT PRL` writes OUT/<target>/<seed> files.

Seeds are kept small (libFuzzer mutates faster on small inputs): a torch-style archive written
by Python's own pickler, the golden checkpoint's real data.pkl, shrunken frames, the first lines
of real annotation files, a pysot JSON of a real sequence, the smallest ONNX backbone and head
that fit NanoTrack's contract (also written to OUT/tiny/) beside the shipped NanoTrack files,
and the manifest and search graph of the plan compiled from that tiny pair by PRL (the `prl`
binary) into OUT/tiny/plan, which the plan target loads beside its input.
"""
import collections
import io
import json
import os
import pickle
import struct
import subprocess
import sys
import types
import zipfile

shared, out, prl = sys.argv[1], sys.argv[2], sys.argv[3]


def put(target, name, data):
    d = os.path.join(out, target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


# A torch.save-style archive written by Python's pickler: fake `torch` modules so that the
# globals and persistent ids are the real names, with nothing of torch imported.
torch = types.ModuleType("torch")
utils = types.ModuleType("torch._utils")
sys.modules["torch"], sys.modules["torch._utils"] = torch, utils


def _rebuild_tensor_v2(*a):
    pass


def _rebuild_parameter(*a):
    pass


_rebuild_tensor_v2.__module__ = _rebuild_parameter.__module__ = "torch._utils"
utils._rebuild_tensor_v2, utils._rebuild_parameter = _rebuild_tensor_v2, _rebuild_parameter
for n in ["FloatStorage", "HalfStorage", "LongStorage"]:
    setattr(torch, n, type(n, (), {"__module__": "torch"}))


class Storage:
    def __init__(self, key, kind, data):
        self.key, self.kind, self.data = key, kind, data


class Tensor:
    def __init__(self, storage, size, stride, offset=0, param=False):
        self.args = (storage, offset, size, stride, False, collections.OrderedDict())
        self.param = param

    def __reduce__(self):
        if self.param:
            return (_rebuild_parameter, (Tensor(*self.args[:1], self.args[2], self.args[3]), True, collections.OrderedDict()))
        return (_rebuild_tensor_v2, self.args)


class Pickler(pickle.Pickler):
    def persistent_id(self, obj):
        if isinstance(obj, Storage):
            return ("storage", getattr(torch, obj.kind), obj.key, "cpu", len(obj.data) // {"FloatStorage": 4, "HalfStorage": 2, "LongStorage": 8}[obj.kind])
        return None


w = Storage("0", "FloatStorage", struct.pack("<6f", 0, 1, 2, 3, 4, 5))
h = Storage("1", "HalfStorage", struct.pack("<2e", 1.5, -2.0))
n = Storage("2", "LongStorage", struct.pack("<q", 7))
state = collections.OrderedDict(
    [
        ("a.weight", Tensor(w, (2, 3), (3, 1))),
        ("a.t", Tensor(w, (3, 2), (1, 3))),
        ("a.bias", Tensor(h, (2,), (1,), param=True)),
        ("a.n", Tensor(n, (), ())),
        ("a.e", Tensor(w, (4,), (0,), offset=5)),
    ]
)
for proto in [2, 4]:
    buf = io.BytesIO()
    Pickler(buf, protocol=proto).dump({"state_dict": state, "epoch": 3})
    pkl = buf.getvalue()
    put("pickle", f"mini-p{proto}.pkl", pkl)
    z = io.BytesIO()
    with zipfile.ZipFile(z, "w", zipfile.ZIP_STORED) as a:
        a.writestr("archive/data.pkl", pkl)
        a.writestr("archive/byteorder", "little")
        for s in [w, h, n]:
            a.writestr(f"archive/data/{s.key}", s.data)
        a.writestr("archive/version", "3\n")
    put("checkpoint", f"mini-p{proto}.pth", z.getvalue())

# The golden checkpoint's real pickle.
with zipfile.ZipFile(os.path.join(shared, "fixtures/prl-golden-v1/checkpoint.pth")) as z:
    put("pickle", "golden-data.pkl", z.read("checkpoint/data.pkl"))

# safetensors: F32 and F16 tensors, with metadata.
def safetensors(tensors, meta):
    header, blob = {"__metadata__": meta}, b""
    for name, (dtype, shape, data) in tensors.items():
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [len(blob), len(blob) + len(data)]}
        blob += data
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    return struct.pack("<Q", len(h)) + h + blob


put("checkpoint", "mini.safetensors", safetensors(
    {"x.weight": ("F32", [2, 2], struct.pack("<4f", 1, 2, 3, 4)), "x.bias": ("F16", [2], struct.pack("<2e", 0.5, 8))},
    {"format": "pt"},
))

# Annotation and result files: real lines.
seqs = os.path.join(shared, "data/uav123_10fps")
for seq in sorted(d for d in os.listdir(seqs) if os.path.isdir(os.path.join(seqs, d))):
    with open(os.path.join(seqs, seq, "groundtruth_rect.txt"), "rb") as f:
        put("boxes", f"{seq}.txt", b"".join(f.readlines()[:40]))
with open(os.path.join(shared, "fixtures/nanotrack-v2-ref/building4.txt"), "rb") as f:
    put("boxes", "nanotrack-building4.txt", b"".join(f.readlines()[:40]))
put("boxes", "tabs-nan.txt", b"1\t2\t3\t4\nNaN,NaN,NaN,NaN\n\n5 6 7.5 8e1\n")

# A pysot dataset JSON of a real sequence (its first 20 frames), absent boxes as NaN.
seq = "building4"
imgs = sorted(os.listdir(os.path.join(seqs, seq, "img")))[:20]
with open(os.path.join(seqs, seq, "groundtruth_rect.txt")) as f:
    gt = [[float(v) for v in l.replace("\t", ",").split(",")] for l in f.read().split("\n")[:20] if l]
gt[3] = [float("nan")] * 4
doc = {seq: {"video_dir": seq, "init_rect": gt[0], "img_names": [f"{seq}/img/{i}" for i in imgs], "gt_rect": gt, "attr": ["Scale Variation", "Camera Motion"]}}
put("pysot_json", "UAV123.json", json.dumps(doc).encode())

# Frames: a real frame shrunk (JPEG, PNG, BMP, WebP), and the JPEG cut short.
frame = os.path.join(seqs, seq, "img", imgs[0])
for ext in ["jpg", "png", "bmp", "webp"]:
    path = os.path.join(out, f"small.{ext}")
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", frame, "-vf", "scale=80:45", path], check=True)
    with open(path, "rb") as f:
        data = f.read()
    os.remove(path)
    put("frame", f"small.{ext}", data)
    if ext == "jpg":
        put("frame", "cut.jpg", data[: len(data) // 2])

# ONNX. A hand-written protobuf encoder (no `onnx` package needed) for the smallest pair that
# fits NanoTrack's contract: a backbone of one 1x1 convolution at stride 16 (255 -> 16, 127 -> 8,
# 48 channels) and a head that adds the template's mean to the search features and gives cls
# (2 channels) and loc (4) by 1x1 convolutions. libFuzzer mutates these a thousand times faster
# than the shipped files, which are seeds too.
def varint(v):
    out = b""
    v &= (1 << 64) - 1
    while True:
        b, v = v & 0x7F, v >> 7
        out += bytes([b | (0x80 if v else 0)])
        if not v:
            return out


def field(num, value):
    if isinstance(value, int):
        return varint(num << 3) + varint(value)
    if isinstance(value, str):
        value = value.encode()
    return varint(num << 3 | 2) + varint(len(value)) + value


def value_info(name, dims):
    shape = b"".join(field(1, field(1, d)) for d in dims)
    return field(1, name) + field(2, field(1, field(1, 1) + field(2, shape)))


def initializer(name, dims, seed):
    n = 1
    for d in dims:
        n *= d
    data = struct.pack(f"<{n}f", *[((i * 37 + seed) % 17 - 8) / 64 for i in range(n)])
    return b"".join(field(1, d) for d in dims) + field(2, 1) + field(8, name) + field(9, data)


def ints_attr(name, values):
    return field(1, name) + b"".join(field(8, v) for v in values) + field(20, 7)


def node(op, inputs, outputs, name, attrs=()):
    return (b"".join(field(1, i) for i in inputs) + b"".join(field(2, o) for o in outputs)
            + field(3, name) + field(4, op) + b"".join(field(5, a) for a in attrs))


def model(nodes, inits, inputs, outputs):
    graph = (b"".join(field(1, n) for n in nodes) + field(2, "tiny")
             + b"".join(field(5, t) for t in inits)
             + b"".join(field(11, v) for v in inputs) + b"".join(field(12, v) for v in outputs))
    return field(1, 7) + field(2, "prl-fuzz-seeds") + field(7, graph) + field(8, field(2, 14))


tiny_backbone = model(
    [node("Conv", ["input", "w"], ["output"], "conv", [ints_attr("kernel_shape", [1, 1]), ints_attr("strides", [16, 16])])],
    [initializer("w", [48, 3, 1, 1], 1)],
    [value_info("input", [1, 3, 255, 255])],
    [value_info("output", [1, 48, 16, 16])],
)
tiny_head = model(
    [
        node("ReduceMean", ["input1"], ["zmean"], "mean", [ints_attr("axes", [2, 3])]),
        node("Add", ["input2", "zmean"], ["x"], "add"),
        node("Conv", ["x", "wc"], ["output1"], "cls", [ints_attr("kernel_shape", [1, 1])]),
        node("Conv", ["x", "wl"], ["output2"], "loc", [ints_attr("kernel_shape", [1, 1])]),
    ],
    [initializer("wc", [2, 48, 1, 1], 2), initializer("wl", [4, 48, 1, 1], 3)],
    [value_info("input1", [1, 48, 8, 8]), value_info("input2", [1, 48, 16, 16])],
    [value_info("output1", [1, 2, 16, 16]), value_info("output2", [1, 4, 16, 16])],
)
tiny = os.path.join(out, "tiny")
os.makedirs(tiny, exist_ok=True)
for name, data in [("backbone.onnx", tiny_backbone), ("head.onnx", tiny_head)]:
    with open(os.path.join(tiny, name), "wb") as f:
        f.write(data)


# The onnx_import target's input: the backbone's length (4 bytes, little-endian), the backbone,
# the head.
def pair(backbone, head):
    return struct.pack("<I", len(backbone)) + backbone + head


put("onnx_import", "tiny-pair", pair(tiny_backbone, tiny_head))
nano = os.path.join(shared, "models/nanotrack-v2")
with open(os.path.join(nano, "nanotrack_backbone_sim.onnx"), "rb") as f:
    shipped_backbone = f.read()
with open(os.path.join(nano, "nanotrack_head_sim.onnx"), "rb") as f:
    shipped_head = f.read()
put("onnx_import", "tiny-backbone-shipped-head", pair(tiny_backbone, shipped_head))
put("onnx_import", "shipped-pair", pair(shipped_backbone, shipped_head))

# The plan: the tiny pair imported and compiled; its manifest (first byte 0) and its search graph
# (first byte 1).
plan_dir = os.path.join(tiny, "plan")
for args in [
    ["import", "nanotrack", "--backbone", os.path.join(tiny, "backbone.onnx"), "--head", os.path.join(tiny, "head.onnx"),
     "--out", os.path.join(tiny, "model")],
    ["compile", "--model", os.path.join(tiny, "model"), "--out", plan_dir],
]:
    subprocess.run([prl] + args, check=True, stdout=subprocess.DEVNULL)
with open(os.path.join(plan_dir, "plan.json"), "rb") as f:
    manifest = f.read()
put("plan", "plan.json", b"\x00" + manifest)
with open(os.path.join(plan_dir, json.loads(manifest)["search"]["file"]), "rb") as f:
    put("plan", "search-graph", b"\x01" + f.read())
