#!/usr/bin/env python3
"""Instructions and estimated time per tracking step on a Cortex-A78-class core, from two counts
of the same `prl bench` run under qemu (scripts/qemu-insn-count.c) that differ only in the
number of steps: the difference divided by the difference in steps is one step (with its
template run; see scripts/orin-estimate.sh).

Cycles: every hot translated block (the blocks that together execute 90% of the step's
instructions) is run through llvm-mca as a loop of itself (`-iterations=200`; a block ends at a
branch, so the hot ones are inner-loop bodies), with the scheduling model named by --mcpu; the
rest of the instructions run at the hot blocks' mean IPC. llvm-mca assumes every load hits the
L1 cache and every branch is predicted: the estimate is optimistic for memory-bound layers.

Usage: orin_estimate.py BINARY LOW.txt HIGH.txt STEPS [--mcpu neoverse-n1] [--json OUT]
"""

import argparse
import json
import re
import subprocess
import sys
from collections import Counter

# qemu-user maps a position-independent aarch64 executable here (checked: a block of
# `ycc_rgb_convert` ran at 0x550032af30, the symbol is at 0x32abe0 in the file).
LOAD_BASE = 0x5500000000


def read_counts(path):
    total, blocks = 0, {}
    with open(path) as f:
        for line in f:
            parts = line.split(" ", 4)
            if parts[0] == "instructions":
                total = int(parts[1])
            elif parts[0] == "tb":
                vaddr, insns, execs = int(parts[1], 16), int(parts[2]), int(parts[3])
                sym = parts[4].strip() if len(parts) > 4 else "(other)"
                blocks[(vaddr, insns)] = (execs, sym)
    return total, blocks


def block_asm(binary, vaddr, insns):
    """The block's instructions as llvm-mca input (branch targets replaced by a local label)."""
    start = vaddr - LOAD_BASE
    if start < 0:
        return None
    out = subprocess.run(
        ["aarch64-linux-gnu-objdump", "-d", "--no-show-raw-insn", f"--start-address={start}",
         f"--stop-address={start + 4 * insns}", binary],
        capture_output=True, text=True, check=True).stdout
    lines = []
    for line in out.splitlines():
        m = re.match(r"\s*[0-9a-f]+:\s+(\S.*)$", line)
        if not m:
            continue
        ins = m.group(1).split("//")[0].split(";")[0].strip()
        ins = re.sub(r"<[^>]*>", "", ins)
        op = ins.split()[0]
        if op.startswith("b") or op in ("cbz", "cbnz", "tbz", "tbnz", "adr", "adrp", "bl", "blr", "ret"):
            if op in ("ret", "blr", "br"):
                continue
            ins = re.sub(r"\b[0-9a-f]{3,}\s*$", ".Lt", ins)  # the target address
        if ins.startswith(".inst") or ins.startswith("udf"):
            return None
        lines.append(ins)
    if len(lines) < insns // 2:
        return None  # not in the executable (a shared library's block)
    return ".Lt:\n" + "\n".join(lines) + "\n"


def mca_cycles(asm, mcpu, iterations=200):
    # -dispatch=4: the A78 decodes 4 instructions a cycle (its macro-op cache delivers up to 6).
    r = subprocess.run(["llvm-mca-19", "-mtriple=aarch64", f"-mcpu={mcpu}", "-dispatch=4", f"-iterations={iterations}"],
                       input=asm, capture_output=True, text=True)
    m = re.search(r"Total Cycles:\s+(\d+)", r.stdout)
    return int(m.group(1)) / iterations if m else None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("binary")
    ap.add_argument("low")
    ap.add_argument("high")
    ap.add_argument("steps", type=float)
    ap.add_argument("--mcpu", default="neoverse-n1")
    ap.add_argument("--json")
    a = ap.parse_args()
    lo_total, lo = read_counts(a.low)
    hi_total, hi = read_counts(a.high)
    step = (hi_total - lo_total) / a.steps
    delta = {}
    for key, (execs, sym) in hi.items():
        d = (execs - lo.get(key, (0, sym))[0]) / a.steps
        if d > 0:
            delta[key] = (d, sym)
    hot = sorted(delta.items(), key=lambda kv: -kv[1][0] * kv[0][1])
    covered_insns = covered_cycles = 0.0
    by_sym = Counter()
    unmodelled = 0.0
    for (vaddr, insns), (execs, sym) in hot:
        if covered_insns + unmodelled >= 0.9 * step:
            break
        asm = block_asm(a.binary, vaddr, insns)
        cyc = mca_cycles(asm, a.mcpu) if asm else None
        if cyc is None:
            unmodelled += execs * insns
            continue
        covered_insns += execs * insns
        covered_cycles += execs * cyc
        by_sym[sym] += execs * cyc
    ipc = covered_insns / covered_cycles if covered_cycles else 1.0
    cycles = covered_cycles + (step - covered_insns) / ipc
    report = {
        "instructions_per_step": step,
        "modelled_share": covered_insns / step if step else 0.0,
        "ipc_modelled": ipc,
        "cycles_per_step": cycles,
        "mcpu": a.mcpu,
        "top_cycles": [{"symbol": s, "cycles": c} for s, c in by_sym.most_common(8)],
    }
    if a.json:
        with open(a.json, "w") as f:
            json.dump(report, f, indent=2)
    print(f"{step / 1e6:.1f} M instructions per step; {100 * report['modelled_share']:.0f}% in blocks "
          f"modelled by llvm-mca -mcpu={a.mcpu} at IPC {ipc:.2f}; {cycles / 1e6:.1f} M cycles "
          f"= {cycles / 2.0e6:.1f} ms at 2.0 GHz on one core")


if __name__ == "__main__":
    sys.exit(main())
