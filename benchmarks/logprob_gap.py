"""How differently the bf16 sampler and the trainer score the same tokens.

    python benchmarks/logprob_gap.py [--batches 2] [--out benchmarks/logprob_gap.json]

With ``precision`` bf16 on a CPU, completions are sampled by a bf16 copy of the policy
(``train.sampling_model``) and scored for the loss by the fp32 policy under bf16 autocast. The
two networks round differently, so log pi_sampler(o_t) and log pi_trainer(o_t) differ. With one
update per batch the ratio is forced to 1 (pi_old := the trainer's own detached log-probs), so
the gap is never corrected: the step is REINFORCE on tokens drawn from a slightly different
distribution, off-policy by the sequence weight exp(sum_t gap_t). This script measures those
gaps on batches of the cpu preset from the untrained policy, against exact fp32 scoring too.
"""
from __future__ import annotations

import argparse
import json

import torch


def summary(gap: torch.Tensor) -> dict:
    a = gap.abs()
    return dict(mean=float(gap.mean()), mean_abs=float(a.mean()),
                p99_abs=float(a.quantile(0.99)), max_abs=float(a.max()))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--batches", type=int, default=2)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    from course_utils import data, train
    from course_utils.config import load_config
    from course_utils.rollout import completion_logprobs

    cfg = load_config("cpu", precision="bf16", out_dir="/tmp/unused")
    policy = train.setup(cfg)
    prompts = data.make_prompts(cfg, policy.tokenizer, held_out=False)
    token_gaps = {"trainer - sampler": [], "trainer - fp32": [], "sampler - fp32": []}
    sequence_log_weights = []
    for step in range(args.batches):
        ro, *_ = train.sample_batch(policy, train.batch_for_step(step, prompts, cfg))
        mask = ro.completion_mask.bool()
        score = dict(prompt_ids=ro.prompt_ids, prompt_mask=ro.prompt_mask,
                     completion_ids=ro.completion_ids, completion_mask=ro.completion_mask,
                     temperature=cfg.temperature, group_size=cfg.group_size)
        with torch.no_grad():
            with train.cpu_autocast(cfg):
                trainer, _ = completion_logprobs(policy.model, **score)
            exact, _ = completion_logprobs(policy.model, **score)
        sampler = ro.logprobs
        token_gaps["trainer - sampler"].append((trainer - sampler)[mask])
        token_gaps["trainer - fp32"].append((trainer - exact)[mask])
        token_gaps["sampler - fp32"].append((sampler - exact)[mask])
        sequence_log_weights.append(((trainer - sampler) * mask).sum(-1))
    result = {k: summary(torch.cat(v)) for k, v in token_gaps.items()}
    w = torch.cat(sequence_log_weights)
    result["sequence log weight sum_t (trainer - sampler)"] = dict(
        mean=float(w.mean()), sd=float(w.std()), mean_abs=float(w.abs().mean()),
        max_abs=float(w.abs().max()))
    tokens = int(sum(len(v) for v in token_gaps["trainer - sampler"]))
    print(f"{tokens} completion tokens in {len(w)} completions, {args.batches} batches, untrained "
          f"policy\n\n| log-prob gap (nats) | mean | mean abs | 99th pct abs | max abs |\n|---|---|---|---|---|")
    for k, v in result.items():
        if k.startswith("sequence"):
            continue
        print(f"| {k} | {v['mean']:+.4f} | {v['mean_abs']:.4f} | {v['p99_abs']:.4f} | {v['max_abs']:.4f} |")
    s = result["sequence log weight sum_t (trainer - sampler)"]
    print(f"\nper completion, log of the ignored weight sum_t (trainer - sampler): mean {s['mean']:+.4f}, "
          f"sd {s['sd']:.4f}, mean abs {s['mean_abs']:.4f}, max abs {s['max_abs']:.4f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(dict(tokens=tokens, completions=len(w), **result), f, indent=1)


if __name__ == "__main__":
    main()
