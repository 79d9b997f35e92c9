"""Run in a fresh process by tests/test_plan.py and benchmarks/memory_peaks.py: two GRPO-shaped
training steps of a random model with Qwen2.5-0.5B's architecture on the CPU; prints the peak
resident memory they added."""
import json
import resource
import sys

import torch
from transformers import Qwen2Config, Qwen2ForCausalLM

from course_utils.rollout import completion_logprobs


def resident_gib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 1024 ** 3


def main(prompts: int, group_size: int, prompt_len: int, completion_len: int, lora_rank: int = 0) -> None:
    torch.set_num_threads(2)
    config = Qwen2Config(vocab_size=151_936, hidden_size=896, intermediate_size=4864,
                         num_hidden_layers=24, num_attention_heads=14, num_key_value_heads=2,
                         max_position_embeddings=32768, tie_word_embeddings=True)
    baseline = resident_gib()
    torch.manual_seed(0)
    model = Qwen2ForCausalLM(config).eval()
    if lora_rank:
        from course_utils.models import add_lora
        model = add_lora(model, lora_rank, 2 * lora_rank)
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-5,
                                  weight_decay=0.01)
    rows = prompts * group_size
    prompt_ids = torch.randint(0, config.vocab_size, (prompts, prompt_len)).repeat_interleave(group_size, 0)
    completion_ids = torch.randint(0, config.vocab_size, (rows, completion_len))
    for _ in range(2):  # the second step has the optimizer's moments: the steady state
        logprobs, _ = completion_logprobs(model, prompt_ids, torch.ones_like(prompt_ids), completion_ids,
                                          torch.ones_like(completion_ids), with_entropy=True,
                                          group_size=group_size)
        loss = -(logprobs * torch.randn(rows, 1)).mean()
        optimizer.zero_grad(set_to_none=True)  # as the training loop does
        loss.backward()
        optimizer.step()
        del logprobs, loss
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    print(json.dumps({"peak_gib": peak - baseline,
                      "params": sum(p.numel() for p in model.parameters())}))


if __name__ == "__main__":
    main(*[int(a) for a in sys.argv[1:6]])
