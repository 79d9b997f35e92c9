"""One GRPO step on a fixed global batch, run by tests/test_distributed.py either as a single
process or under ``accelerate launch`` with 2 CPU processes (gloo). The rollouts are fixed: every
process samples the *whole* global batch with the same seed and keeps its own rows, so both runs
train on identical completions and only the training path differs (local groups, gathered
rewards, global loss normalizers, the gradient all-reduce). Writes the updated parameters.

Variant "inverse_variance" (the default): one step with the seed's variance-scaled entropy bonus.
Variant "adaptive": two steps with the adaptive entropy weight (losses.AdaptiveEntropy), whose
target is set above any entropy so the second step trains with a weight the first one set from
the whole batch's entropy: every process must read the same entropy and move alike."""
import json
import sys

import torch

from course_utils import train
from course_utils.config import load_config
from course_utils.data import Prompt
from course_utils.rollout import Rollout, rollout as real_rollout


ENTROPY = {"inverse_variance": dict(entropy_bonus="inverse_variance", entropy_coef=1e-3,
                                   entropy_weight_max=10.0),
           "adaptive": dict(entropy_bonus="adaptive", entropy_coef=1e-2, entropy_target=20.0,
                            entropy_weight_max=10.0)}


def main(out: str, variant: str = "inverse_variance") -> None:
    cfg = load_config("smoke", prompts_per_step=4, group_size=4, grad_accum=1, loss_type="dapo",
                      max_new_tokens=10, **ENTROPY[variant])
    policy = train.setup(cfg)
    acc = policy.accelerator
    prompts = [Prompt(text=t, snippet=t, target_chars=20 + 4 * i, target_digit_sum=3 + i)
               for i, t in enumerate(["One two three", "Four five six seven eight",
                                      "Nine", "Ten eleven twelve thirteen"])]
    full = real_rollout(policy.model, policy.tokenizer, [p.text for p in prompts],
                        group_size=cfg.group_size, max_new_tokens=cfg.max_new_tokens,
                        eos_ids=policy.eos_ids, temperature=1.0,
                        generator=torch.Generator().manual_seed(7))
    rows_per_process = len(full.texts) // acc.num_processes
    mine = slice(acc.process_index * rows_per_process, (acc.process_index + 1) * rows_per_process)

    def fixed_rollout(*args, **kwargs):
        tensors = {k: getattr(full, k)[mine] for k in ("prompt_ids", "prompt_mask", "completion_ids",
                                                         "completion_mask", "logprobs", "truncated")}
        return Rollout(**tensors, texts=full.texts[mine], group_size=full.group_size)

    train.rollout = fixed_rollout
    before = {n: p.detach().clone() for n, p in policy.model.named_parameters()}
    for _ in range(2 if variant == "adaptive" else 1):
        metrics = train.grpo_step(policy, prompts)
    if acc.is_main_process:
        update = {n: (p.detach() - before[n]) for n, p in policy.model.named_parameters()}
        torch.save(update, out)
        keep = ("reward_mean", "adv_std", "entropy_weight", "loss", "grad_norm", "zero_std_frac")
        control = policy.entropy_control.state_dict() if policy.entropy_control else {}
        print(json.dumps({"processes": acc.num_processes, **{k: metrics[k] for k in keep},
                          **{f"control_{k}": v for k, v in control.items()}}))
    # Every rank waits here until rank 0 has saved and printed, then the process group is torn
    # down explicitly: a rank that exits while gloo's threads still talk to the other aborts
    # ("terminate called without an active exception").
    acc.wait_for_everyone()
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()


if __name__ == "__main__":
    main(*sys.argv[1:])
