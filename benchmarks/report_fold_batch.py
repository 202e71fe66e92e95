"""BENCHMARKS.md: the folds of a cross-validation batched in one process, measured without a GPU, from
results/fold_batch.json (bench_fold_batch.py); used by report.py."""

from __future__ import annotations

from typing import Any

H100_DENSE_FP16_TFLOPS = 989  # NVIDIA's H100 SXM data sheet, dense float16/bfloat16 tensor cores
FOLDS = 8


def whole_run(r: dict[str, Any]) -> dict[str, float]:
    """The Suturing-sized 8-fold run at the defaults, from the per-step figures: operators issued by 8
    processes and by one batched process, the arithmetic, and the host's floor: the batched process's, and
    one process's of eight running alone."""
    separate = batched = flops = floor = floor_alone = 0.0
    for m in r["members"].values():
        steps = m["steps_per_fold"] * m["count_in_ensemble"]
        widest = m["batched"][str(max(r["ks"]))]["kernels"]
        separate += FOLDS * steps * m["alone"]["kernels"]
        batched += steps * widest
        flops += FOLDS * steps * m["alone"]["flops"]
        floor += steps * widest * m["floor"]["batched_us_per_operator"] * 1e-6
        floor_alone += steps * m["alone"]["kernels"] * m["floor"]["alone_us_per_operator"] * 1e-6
    return {"separate": separate, "batched": batched, "tflop": flops / 1e12, "floor_s": floor, "floor_alone_s": floor_alone}


def fold_batch_section(r: dict[str, Any]) -> list[str]:
    ks = [str(k) for k in r["ks"]]
    widest = ks[-1]
    smoke = " (smoke run: short trials, not for reading)" if r.get("quick") else ""
    out = [f"### Folds batched in one process, measured without a GPU (`bench_fold_batch.py`){smoke}", "",
           f"Issue 27: on one GPU, all the folds of a cross-validation are trained by one process, batched "
           f"(`--accelerator cuda`: `--fold-batch auto` turns it on; `models/fold_batch.py`, K copies of a network "
           f"under `torch.vmap`). This measures the design without a GPU (none was lent when it was written): "
           f"per training step of each ensemble member at its recipe, the operators torch dispatches (each a kernel "
           f"launch on a GPU, whatever its size; views apart), for one fold trained alone (`fit`'s step) and for K "
           f"folds batched (`fit_stacked`'s step, `StackedStep`), the arithmetic of one fold's step, and the CPU time. Shapes of "
           f"the Suturing-sized LOUO ({r['frames']:,} frames a trial at 10 Hz, {r['inputs']} inputs, "
           f"{r['classes']} classes, ~{r['train_trials']} training trials a fold). {r['machine']['cpu_model']}, "
           f"one torch thread, torch {r['torch']}, {r['machine']['date_utc'][:16]}, load "
           f"{r['load_1min'][0]:g}–{r['load_1min'][1]:g} (shared: the CPU seconds move with it; the operator "
           "counts do not).", "",
           f"| network | batch | operators a step, one fold alone | batched, K = {' / '.join(ks)} | {FOLDS} processes "
           f"(sum) | GFLOP a step, a fold | CPU s a step: alone / K = {widest} batched | K = {widest} against "
           f"{widest} alone | host µs an operator: alone / batched |",
           "|---|---|---|---|---|---|---|---|---|"]
    for name, m in r["members"].items():
        a, b, f = m["alone"], m["batched"], m["floor"]
        counts = " / ".join(f"{b[k]['kernels']:,}" for k in ks)
        out.append(f"| {name} | {m['batch_size']} | {a['kernels']:,} | {counts} | "
                   f"{FOLDS * a['kernels']:,} | {a['flops'] / 1e9:.1f} | {a['cpu_s']:.2f} / {b[widest]['cpu_s']:.2f} | "
                   f"{b[widest]['cpu_s'] / (int(widest) * a['cpu_s']):.2f}x | "
                   f"{f['alone_us_per_operator']:.0f} / {f['batched_us_per_operator']:.0f} |")
    w = whole_run(r)
    grows = {name: m["operators_growing_with_k"] for name, m in r["members"].items() if m["operators_growing_with_k"]}
    growth = "; ".join(f"{name}: {', '.join(f'{op} ' + ' / '.join(str(v) for v in counts.values()) for op, counts in g.items())}"
                       for name, g in grows.items())
    steps = ", ".join(f"{m['count_in_ensemble']} x {name}, {m['steps_per_fold']} steps a fold" for name, m in r["members"].items())
    fewer = w["separate"] / w["batched"]
    vmap = " and ".join(f"{m['floor']['batched_us_per_operator'] / m['floor']['alone_us_per_operator']:.1f}x ({name})"
                        for name, m in r["members"].items())
    return out + [
        "",
        f"* **Batched, the operators a step do not grow with the folds**: one stacked step issues what one fold "
        f"issues (plus the stacked Adam step's few), where {FOLDS} processes issue {FOLDS} times as many and "
        f"time-slice the device. " + (f"Operators that grow from K = 1 to K = 2 and then stay ({growth}): vmap's "
                                      "layout copies, not a loop over folds." if grows else ""),
        f"* **The whole run** (the default ensemble: {steps}): {w['separate'] / 1e6:.1f} M operators from "
        f"{FOLDS} processes against **{w['batched'] / 1e6:.2f} M from one batched process**; the arithmetic is "
        f"{w['tflop']:.0f} TFLOP, {w['tflop'] / H100_DENSE_FP16_TFLOPS:.2f} s of an H100's dense float16 peak "
        f"({H100_DENSE_FP16_TFLOPS} TFLOP/s): a few seconds even at a tenth of it.",
        f"* **So on a GPU the run is bound by issuing operators, not by arithmetic.** At this host's cost an "
        f"operator under vmap (the last column: a forward and backward pass on {r['floor_frames']}-frame trials, "
        f"where the arithmetic is next to nothing), the batched run's operators take **~{w['floor_s']:.0f} s** "
        f"of one host core: about the least the GPU run can take from a CPU like this one, against issue 27's "
        f"120 s, before building the dataset and evaluating. {FOLDS} processes would issue theirs side by side "
        f"from {FOLDS} cores at the cost alone (~{w['floor_alone_s']:.0f} s each), but their kernels time-slice "
        f"the one GPU (the issue's {FOLDS} contexts: no fold finished in 240 s); batched, {fewer:.0f}x fewer "
        f"operators, each costing {vmap} as much under vmap. The GPU run itself is measured by "
        f"`benchmarks/gpu_check.sh` on a lent GPU (benchmarks/README.md; the louo-all table's GPU rows).",
        "* On the CPU batching gains nothing (the CPU time of K folds batched is about K folds alone: the CPU is "
        "busy with arithmetic, not with issuing operators), which is why `--fold-batch auto` is off there.",
        "* Not built: capturing a step as a CUDA graph would take the host's share away (the shapes change from "
        "step to step, so batches would be padded to a few lengths, one graph each); it cannot be tested without "
        "a GPU.", ""]
