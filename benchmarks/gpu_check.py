"""The T4 run's first check, on any CUDA GPU: the `t4` preset's shapes under a T4's software limits.

    python benchmarks/gpu_check.py --out notebooks/results/gpu-check.json   # on a GPU: 6 steps
    python benchmarks/gpu_check.py --smoke                                  # anywhere: tiny, fp32

No GPU here is a T4, so the script makes one look like a T4 as far as software can:

- fp16 autocast with fp32 master weights and accelerate's gradient scaler (the `t4` preset);
  TF32 off for matrix products and convolutions; bf16 reported unsupported, so nothing picks it;
- PyTorch's allocator capped (``torch.cuda.set_per_process_memory_fraction``) at what a T4 leaves
  it: the T4's total as CUDA reports it (course_utils.plan.T4) less what this process holds
  outside the allocator, measured here after CUDA starts;
- the `t4` preset's batch, micro-batches, completion length and gradient checkpointing, on
  Qwen2.5-0.5B-Instruct if its weights load (``--model``), else on a model of its exact shapes
  with random weights (``models.QWEN25_SHAPED``). Prompts are cut to the preset's snippet length
  inside the chat template; random weights seldom stop early, so completions run to the cap, the
  memory's worst case.

It prints, and writes with ``--out``: the allocator's peak (max_memory_reserved) and the
tensors' peak (max_memory_allocated) against the plan for the same prompt length, the memory
held outside the allocator, seconds per step by phase, non-finite skips and the gradient
scaler's scale after each step. What it cannot reproduce: a T4's speed (another GPU's kernels
and bandwidth) and the fp16 behaviour of trained weights (random weights overflow differently).
What it can: memory and the numerics of the code path under fp16.
"""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from course_utils import data, models, plan, train  # noqa: E402
from course_utils.config import load_config  # noqa: E402

GiB = plan.GiB


def emulate_t4() -> dict:
    """TF32 and bf16 off, the allocator capped at a T4's share. Returns what was set."""
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    torch.set_float32_matmul_precision("highest")
    torch.cuda.is_bf16_supported = lambda *args, **kwargs: False   # a T4 has none
    torch.cuda.init()
    torch.zeros(1, device="cuda")                                  # the context exists from here
    free, total = torch.cuda.mem_get_info()
    outside = total - free - torch.cuda.memory_reserved()          # context and libraries (if alone on the GPU)
    cap = plan.T4.total_memory_gib * GiB - outside
    fraction = min(1.0, cap / total)
    torch.cuda.set_per_process_memory_fraction(fraction)
    return dict(gpu=torch.cuda.get_device_name(0), gpu_total_gib=total / GiB,
                outside_allocator_gib_at_start=outside / GiB, allocator_cap_gib=fraction * total / GiB,
                tf32=False, bf16=False)


def probe_allocator_cap(cap_bytes: float) -> dict:
    """Does the cap bound what the allocator reserves? One block a quarter GiB past what is left
    under the cap must be refused, one a quarter GiB short of it granted."""
    def fits(nbytes: float) -> bool:
        try:
            block = torch.empty(int(nbytes), dtype=torch.uint8, device="cuda")
            del block
            return True
        except torch.OutOfMemoryError:
            return False
        finally:
            torch.cuda.empty_cache()
    left = cap_bytes - torch.cuda.memory_reserved()
    return dict(refused_past_cap=not fits(left + GiB / 4), granted_under_cap=fits(left - GiB / 4))


def probe_autocast_copies(policy) -> dict:
    """What accelerate's fp16 autocast holds during one forward of the prepared model (no_grad,
    as sampling runs) and after it. The plan counts fp16 copies of every weight, 2P bytes, alive
    for the whole forward (autocast's cast cache) and made again at every call, so a decoding
    step reads 4P and writes and reads 2P."""
    model, device = policy.model, policy.accelerator.device
    ids = torch.ones(1, 1, dtype=torch.long, device=device)
    P = sum(p.numel() for p in model.parameters())
    extra, left = [], []
    for _ in range(2):   # twice: a cache that outlived the call would show in the second
        torch.cuda.synchronize()
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        with torch.no_grad():
            out = model(input_ids=ids).logits
        del out
        torch.cuda.synchronize()
        extra.append((torch.cuda.max_memory_allocated() - base) / GiB)
        left.append((torch.cuda.memory_allocated() - base) / GiB)
    return dict(planned_copies_gib=2 * P / GiB, forward_extra_gib=extra, held_after_gib=left)


def full_length_prompts(cfg, tokenizer, count: int) -> list[data.Prompt]:
    """The preset's prompts from the offline snippets, each snippet extended with the next ones
    until it has ``cfg.prompt_tokens`` tokens (the offline snippets are shorter than the t4
    preset's openwebtext ones), then cut there, as ``data.make_prompts`` cuts."""
    snippets = data.offline_snippets()
    prompts = []
    for i in range(count):
        text, k = snippets[i % len(snippets)], i + 1
        while len(tokenizer(text, add_special_tokens=False)["input_ids"]) < cfg.prompt_tokens:
            text, k = text + " " + snippets[k % len(snippets)], k + 1
        snippet = data.chop(tokenizer, text, cfg.prompt_tokens)
        digit_sum = cfg.digit_sum_min + i % (cfg.digit_sum_max - cfg.digit_sum_min + 1)
        prompts.append(data.build_prompt(tokenizer, snippet, cfg.target_chars, digit_sum, cfg.prompt_style))
    return prompts


def config(smoke: bool, model: str, on_gpu: bool, grad_accum: int | None = None):
    if smoke:   # the same code path, shrunk to seconds on a CPU (CI)
        return load_config("t4", model=models.TINY, prompt_source="offline", precision="fp32",
                           prompt_tokens=16, target_chars=48, prompts_per_step=2, group_size=4,
                           grad_accum=2, max_new_tokens=8, train_prompts=8, eval_prompts=2,
                           out_dir="/tmp/gpu-check-unused",
                           **({} if on_gpu else dict(device="cpu")))
    return load_config("t4", model=model, prompt_source="offline", train_prompts=10 * 16,
                       eval_prompts=2, out_dir="/tmp/gpu-check-unused",
                       **({} if grad_accum is None else dict(grad_accum=grad_accum)))


def scaler_scale(policy) -> float | None:
    scaler = getattr(policy.accelerator, "scaler", None)
    return None if scaler is None else float(scaler.get_scale())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=6, help="steps measured, after one warm-up")
    parser.add_argument("--smoke", action="store_true", help="tiny model, fp32, 2 steps: runs anywhere")
    parser.add_argument("--model", default=models.QWEN25_SHAPED,
                        help="Qwen/Qwen2.5-0.5B-Instruct to use the real weights (needs the hub)")
    parser.add_argument("--grad_accum", type=int, default=None,
                        help="micro-batches per step (default: the t4 preset's), to test the plan at another point")
    parser.add_argument("--out", default=None, help="write the result as JSON here")
    args = parser.parse_args(argv)
    on_gpu = torch.cuda.is_available()
    if not on_gpu and not args.smoke:
        print("gpu_check: no CUDA GPU here; run with --smoke for the CPU check of the code path",
              file=sys.stderr)
        return 2
    steps = 2 if args.smoke else args.steps
    emulation = emulate_t4() if on_gpu else dict(gpu=None, note="CPU: no emulation, fp32")
    cfg = config(args.smoke, args.model, on_gpu, args.grad_accum)
    probes = {}
    if on_gpu:
        probes["allocator_cap"] = probe_allocator_cap(emulation["allocator_cap_gib"] * GiB)
    t0 = time.perf_counter()
    policy = train.setup(cfg)
    setup_s = time.perf_counter() - t0
    if on_gpu and cfg.precision != "fp32":
        probes["autocast_copies"] = probe_autocast_copies(policy)
    prompts = full_length_prompts(cfg, policy.tokenizer, (steps + 1) * cfg.prompts_per_step)
    records, scales = [], []
    if on_gpu:
        torch.cuda.reset_peak_memory_stats()
    for step in range(steps + 1):   # step 0 warms up (kernels, the optimizer's moments)
        m = train.grpo_step(policy, train.batch_for_step(step, prompts, cfg))
        scales.append(scaler_scale(policy))
        if step:
            records.append(m)
    prompt_len = max(r.get("prompt_len_max", 0) for r in records)
    arch = plan.QWEN25_05B if cfg.model in (models.QWEN25_SHAPED, "Qwen/Qwen2.5-0.5B-Instruct") \
        else models.architecture(cfg.model)
    device = plan.T4 if on_gpu else plan.CPU_PROBE
    mem = plan.memory_plan(arch, cfg, prompt_len, cfg.max_new_tokens, device)
    if on_gpu:
        measured = dict(reserved_gib=torch.cuda.max_memory_reserved() / GiB,
                        allocated_gib=torch.cuda.max_memory_allocated() / GiB)
        free, total = torch.cuda.mem_get_info()
        measured["outside_allocator_gib"] = (total - free - torch.cuda.memory_reserved()) / GiB
        measured["allocator_cache"] = measured["reserved_gib"] / measured["allocated_gib"] - 1
    else:   # resident memory, the CPU probe's measure (ru_maxrss is in KiB on Linux)
        measured = dict(resident_gib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GiB)
    phases = sorted({k for r in records for k in r if k.startswith("time_")})
    result = dict(
        emulation=emulation, model=cfg.model, precision=cfg.precision, steps=steps,
        torch=torch.__version__, setup_seconds=setup_s, prompt_len=prompt_len,
        max_new_tokens=cfg.max_new_tokens, micro_batch_rows=cfg.prompts_per_step // cfg.grad_accum * cfg.group_size,
        planned=dict(tensors_gib=plan.tensor_bytes(mem) / GiB, reserved_gib=plan.reserved_bytes(mem) / GiB,
                     process_gib=plan.peak_bytes(mem) / GiB,
                     seconds_per_step_t4=plan.time_plan(arch, cfg, prompt_len, cfg.max_new_tokens)["total s/step"]),
        measured=measured,
        step_seconds=[r["step_time"] for r in records],
        phase_seconds={k[5:]: [r.get(k, 0.0) for r in records] for k in phases},
        completion_tokens=[r.get("completion_tokens") for r in records],
        nonfinite_skipped=records[-1]["nonfinite_skipped"],
        scaler_scale=scales,
        scaler=None if scaler_scale(policy) is None else type(policy.accelerator.scaler).__name__,
        probes=probes,
    )
    print(report(result))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return 0


def report(result: dict) -> str:
    p, m = result["planned"], result["measured"]
    lines = [f"gpu_check: {result['model']} ({result['precision']}) on "
             f"{result['emulation'].get('gpu') or 'a CPU'}; prompt {result['prompt_len']} tokens, "
             f"completions up to {result['max_new_tokens']}, micro-batches of {result['micro_batch_rows']} rows"]
    if "reserved_gib" in m:
        e = result["emulation"]
        lines += [f"  allocator capped at {e['allocator_cap_gib']:.2f} GiB (a T4's {plan.T4.total_memory_gib} GiB "
                  f"less {e['outside_allocator_gib_at_start']:.2f} GiB held outside the allocator here)",
                  f"  allocator peak (max_memory_reserved)  {m['reserved_gib']:6.2f} GiB   plan {p['reserved_gib']:6.2f} GiB",
                  f"  tensors' peak (max_memory_allocated)  {m['allocated_gib']:6.2f} GiB   plan {p['tensors_gib']:6.2f} GiB",
                  f"  allocator cache                       {m['allocator_cache']:6.1%}       plan {plan.T4.allocator_cache:6.1%}",
                  f"  outside the allocator                 {m['outside_allocator_gib']:6.2f} GiB   plan "
                  f"{plan.T4.outside_allocator_gib:6.2f} GiB"]
    else:
        lines.append(f"  resident peak {m['resident_gib']:.2f} GiB; plan {p['process_gib']:.2f} GiB "
                     f"(CPU probe overheads)")
    probes = result.get("probes", {})
    if "allocator_cap" in probes:
        c = probes["allocator_cap"]
        lines.append(f"  the cap bounds the allocator: a block past it refused {c['refused_past_cap']}, "
                     f"one under it granted {c['granted_under_cap']}")
    if "autocast_copies" in probes:
        a = probes["autocast_copies"]
        lines.append(f"  autocast's weight copies in one sampling forward: "
                     f"{', '.join(f'{x:.2f}' for x in a['forward_extra_gib'])} GiB (plan 2P = "
                     f"{a['planned_copies_gib']:.2f} GiB), held after it "
                     f"{', '.join(f'{x:.2f}' for x in a['held_after_gib'])} GiB")
    med = statistics.median
    lines.append(f"  seconds per step (median of {result['steps']}): {med(result['step_seconds']):.2f} "
                 "(" + ", ".join(f"{k} {med(v):.2f}" for k, v in result["phase_seconds"].items()) + ")"
                 f"; a T4 by the plan: {p['seconds_per_step_t4']:.1f}")
    scaler = result.get("scaler")
    lines.append(f"  non-finite skips: {result['nonfinite_skipped']}; gradient scaler"
                 f"{f' ({scaler})' if scaler else ''}'s scale per step: "
                 + ("none (no fp16)" if result["scaler_scale"][0] is None
                    else ", ".join(f"{s:g}" for s in result["scaler_scale"])))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
