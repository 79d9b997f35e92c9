"""The measurements behind the CPU choices in course_utils, each timed side by side in one run.

    python benchmarks/kernels.py [--out benchmarks/kernels.json]

On the cpu preset's model (SmolLM2-135M) and batch shape (32 completions of a 60-token prompt,
up to 24 completion tokens here):

1. sampling one token per row: ``torch.multinomial`` against ``rollout.draw`` (inverse CDF);

The training rows use ``kernels='fast'`` (the output layer applied at completion tokens only).
2. AdamW over all weights: torch's default (foreach) against ``fused=True``;
3. the training forward + backward under bf16 autocast: SDPA attention against eager;
4. the same, rows per chunk 8 against 32 (``rollout.ROWS_PER_CHUNK``, ``FAST_ROWS_PER_CHUNK``);
5. the fp32 training forward + backward, reference kernels against fast ones;
6. sampling 24 tokens: the fp32 policy (with and without autocast) against a bf16 copy
   (``train.sampling_model``), and what refreshing the copy costs.

Each entry is the best of a few repeats (seconds), so other work on the machine inflates less.
Prints a Markdown table, pasted whole into benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import copy
import json
import time

import torch


def best_of(fn, repeats: int = 3) -> float:
    fn()   # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    from course_utils import cpu, models, rollout
    from course_utils.config import load_config

    cpu.keep_freed_memory()
    cfg = load_config("cpu", out_dir="/tmp/unused")
    tokenizer = models.load_tokenizer(cfg.model)
    model = models.load_policy(cfg.model)
    rows, prompt_len, completion_len = cfg.prompts_per_step * cfg.group_size, 60, 24
    g = torch.Generator().manual_seed(0)
    vocab = model.config.vocab_size
    rows_table = []

    def add(what, a_name, a, b_name, b):
        rows_table.append(dict(what=what, a=a_name, a_s=a, b=b_name, b_s=b))

    # 1. one sampled token per row from a [rows, vocab] distribution
    probs = torch.softmax(torch.randn(rows, vocab, generator=g) * 3, -1)
    add("draw one token per row, [32, 49152]", "torch.multinomial",
        best_of(lambda: [torch.multinomial(probs, 1, generator=g) for _ in range(10)]) / 10,
        "rollout.draw", best_of(lambda: [rollout.draw(probs, g) for _ in range(10)]) / 10)

    # 2. AdamW steps over every weight
    params = [p for p in model.parameters()]
    for p in params:
        p.grad = torch.randn_like(p) * 1e-3
    times = {}
    for name, kw in [("default (foreach)", {}), ("fused=True", dict(fused=True))]:
        saved = [p.detach().clone() for p in params]
        opt = torch.optim.AdamW(params, lr=1e-5, weight_decay=0.01, **kw)
        times[name] = best_of(opt.step)
        with torch.no_grad():
            for p, s in zip(params, saved):
                p.copy_(s)
    add("AdamW step, 135M weights", "default (foreach)", times["default (foreach)"],
        "fused=True", times["fused=True"])
    for p in params:
        p.grad = None

    # 3-4. training forward + backward of completion log-probs under bf16 autocast
    prompt_ids = torch.randint(0, vocab, (rows, prompt_len), generator=g)
    prompt_mask = torch.ones_like(prompt_ids)
    lengths = torch.randint(4, completion_len + 1, (rows,), generator=g)
    completion_ids = torch.randint(0, vocab, (rows, completion_len), generator=g)
    completion_mask = (torch.arange(completion_len) < lengths[:, None]).long()

    def fwd_bwd(net, rows_per_chunk, fast=True, bf16=True):
        def run():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                lp, _ = rollout.completion_logprobs(
                    net, prompt_ids, prompt_mask, completion_ids, completion_mask,
                    group_size=cfg.group_size, rows_per_chunk=rows_per_chunk, fast=fast)
            (lp.sum() / completion_mask.sum()).backward()
            net.zero_grad(set_to_none=True)
        return run

    add("training forward + backward, fp32", "reference kernels (full logits, 8 rows)",
        best_of(fwd_bwd(model, None, fast=False, bf16=False), 2), "fast kernels (fused head, 32 rows)",
        best_of(fwd_bwd(model, None, fast=True, bf16=False), 2))
    model.set_attn_implementation("sdpa")
    sdpa = best_of(fwd_bwd(model, rollout.FAST_ROWS_PER_CHUNK), 2)
    model.set_attn_implementation("eager")
    eager = best_of(fwd_bwd(model, rollout.FAST_ROWS_PER_CHUNK), 2)
    add("training forward + backward (bf16 autocast), attention", "SDPA", sdpa, "eager", eager)
    add("training forward + backward (bf16 autocast, eager), rows per chunk", str(rollout.ROWS_PER_CHUNK),
        best_of(fwd_bwd(model, rollout.ROWS_PER_CHUNK), 2), str(rollout.FAST_ROWS_PER_CHUNK), eager)

    # 5. sampling: autocast over the fp32 policy against a bf16 copy
    model.set_attn_implementation("sdpa")
    ids, mask = prompt_ids[::cfg.group_size], prompt_mask[::cfg.group_size]

    def sample(net):
        return lambda: rollout.sample(net, ids, mask, group_size=cfg.group_size,
                                      max_new_tokens=completion_len, eos_ids=[-1],
                                      pad_id=tokenizer.pad_token_id, generator=g, fast=True)

    def autocast_sample():
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            sample(model)()

    copy_bf16 = copy.deepcopy(model).to(torch.bfloat16).requires_grad_(False)
    add(f"sample {completion_len} tokens x {rows} rows", "fp32 weights under autocast",
        best_of(autocast_sample, 2), "bf16 copy", best_of(sample(copy_bf16), 2))
    with torch.no_grad():
        refresh = best_of(lambda: copy_bf16.load_state_dict(model.state_dict()))
    add(f"sample {completion_len} tokens x {rows} rows", "fp32 weights, no autocast",
        best_of(sample(model), 2), "bf16 copy", rows_table[-1]["b_s"])

    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"native bf16: {cpu.native_bf16()}\n")
    print("| measurement | A | A s | B | B s | A / B |\n|---|---|---|---|---|---|")
    for r in rows_table:
        print(f"| {r['what']} | {r['a']} | {r['a_s']:.4f} | {r['b']} | {r['b_s']:.4f} | "
              f"{r['a_s'] / r['b_s']:.1f}x |")
    print(f"\nRefreshing the bf16 copy from the fp32 weights (load_state_dict): {refresh:.4f} s, "
          f"{refresh / rows_table[-1]['b_s']:.1%} of sampling {completion_len} tokens with it.")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(dict(torch=torch.__version__, threads=torch.get_num_threads(),
                           native_bf16=cpu.native_bf16(), rows=rows_table, refresh_s=refresh), f, indent=1)


if __name__ == "__main__":
    main()
