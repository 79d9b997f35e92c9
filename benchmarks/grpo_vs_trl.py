"""course_utils' GRPO step against TRL's GRPOTrainer on identical work, in one process.

    python benchmarks/grpo_vs_trl.py            # both shapes, 3 measured steps each (~25 min, 2 cores)
    python benchmarks/grpo_vs_trl.py --shapes short --steps 2

Same model (the embedded SmolLM2-135M-Instruct, fp32, full fine-tuning), same prompts (the
course's chat prompts, as plain text for both), same group size and batch (4 prompts x 8),
same completion budget, temperature 1 with no top-k/top-p, the same shaped reward function,
AdamW with the same learning rate, gradient clipping at 1, KL coefficient 0 (no reference model
for either), one update per batch, loss_type 'grpo'. After one warm-up step each, the two
alternate step by step, so both see the same machine state.

Per phase (generation, scoring, forward, backward, optimizer) it prints seconds per step,
tokens per second and the ratio TRL / ours; the peak resident memory of each step above the
memory held before it (Linux VmHWM, reset before every step); and the achieved FLOP/s of each
trainer's forward + backward against a float32 matmul peak measured in the same run.

TRL is driven step by step through its own ``training_step`` (sampling, scoring, loss and
backward exactly as GRPOTrainer does them) followed by the clip + AdamW step its Trainer loop
would do; the Trainer's logging and callbacks are left out, which can only favour TRL.
Sampled completions differ between the two (different samplers), so the completion lengths are
printed and tokens per second is the fairer unit when they differ.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import statistics
import tempfile
import time
import warnings

import torch

from course_utils import data, models, rewards, train
from course_utils.config import load_config
from course_utils.train import PhaseTimer

# ~60-token prompts (a 16-token snippet inside the chat template and instruction) with up to 40
# new tokens; and the recipe's 128-token snippets with a 64-character target (64 new tokens).
# The benchmark's work is pinned here rather than inherited from the cpu preset: TRL is given the
# same settings (the shaped reward, lr 3e-5, one plain sampling round per step), so the preset's
# dynamic sampling, which TRL's GRPOTrainer does not do, must stay off.
SAME_WORK = dict(reward="shaped", dynamic_sampling=False, lr=3e-5)
SHAPES = {
    "short": dict(prompt_tokens=16, max_new_tokens=40, target_chars=32),
    "recipe": dict(prompt_tokens=128, max_new_tokens=64, target_chars=64),
}
PHASES = ("generation", "scoring", "forward", "backward", "optimizer")


# --- measurement helpers ----------------------------------------------------------------------

def reset_peak_memory() -> None:
    """Linux: writing 5 to clear_refs resets the process's peak resident set (VmHWM)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _status_gib(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024 ** 2
    raise RuntimeError(f"{field} not in /proc/self/status")


def matmul_peak_flops(n: int = 2048, repeats: int = 8, dtype: torch.dtype = torch.float32) -> float:
    """Best-case FLOP/s of this machine in ``dtype``: large square matmuls, best of 3."""
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    a @ b
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(repeats):
            a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * n ** 3 * repeats / best


def training_flops(model, prompt_tokens: int, completion_tokens: int, logit_positions: int) -> float:
    """Forward + backward FLOPs: 6 per weight per token through the transformer body, and 6 per
    output-layer weight at the positions where logits are computed."""
    n_params = sum(p.numel() for p in model.parameters())
    n_embed = model.get_input_embeddings().weight.numel()
    return 6 * (n_params - n_embed) * (prompt_tokens + completion_tokens) + 6 * n_embed * logit_positions


# --- the two trainers --------------------------------------------------------------------------

class Ours:
    name = "course_utils"

    def __init__(self, cfg, prompts):
        self.cfg, self.prompts = cfg, prompts
        self.policy = train.setup(cfg)
        self.step_index = 0

    def step(self) -> dict:
        batch = train.batch_for_step(self.step_index, self.prompts, self.cfg)
        self.step_index += 1
        m = train.grpo_step(self.policy, batch)
        G = self.cfg.group_size
        prompt_tokens = sum(len(self.policy.tokenizer(p.text, add_special_tokens=False).input_ids)
                            for p in batch)
        completion_tokens = m["completion_tokens"] * len(batch) * G
        return dict(seconds={k: m.get(f"time_{k}", 0.0) for k in PHASES}, step=m["step_time"],
                    completion_tokens=completion_tokens, prompt_tokens_in_batch=prompt_tokens * G,
                    # the training forward runs each prompt once per group (prefix sharing)
                    flops=training_flops(self.policy.model, prompt_tokens, completion_tokens,
                                         completion_tokens + len(batch) * G),
                    mean_length=m["completion_tokens"], reward=m["reward_mean"])


class TRL:
    name = "TRL GRPOTrainer"

    def __init__(self, cfg, prompts, out_dir):
        from datasets import Dataset
        from transformers import AutoModelForCausalLM
        from trl import GRPOConfig, GRPOTrainer

        self.cfg = cfg
        tokenizer = models.load_tokenizer(cfg.model)
        model = AutoModelForCausalLM.from_pretrained(models.embedded_model_dir(), dtype=torch.float32)
        dataset = Dataset.from_list([dict(prompt=p.text, target_chars=p.target_chars,
                                          target_digit_sum=p.target_digit_sum) for p in prompts])
        rows = cfg.prompts_per_step * cfg.group_size
        args = GRPOConfig(
            output_dir=out_dir, per_device_train_batch_size=rows, num_generations=cfg.group_size,
            gradient_accumulation_steps=1, max_completion_length=cfg.max_new_tokens,
            temperature=cfg.temperature, top_p=1.0, top_k=0, beta=0.0, num_iterations=1,
            loss_type="grpo", scale_rewards="group", learning_rate=cfg.lr,
            weight_decay=cfg.weight_decay, max_grad_norm=cfg.max_grad_norm, optim="adamw_torch",
            lr_scheduler_type="constant", use_cpu=True, bf16=False, fp16=False, report_to="none",
            # TRL's default is True, applied only by trainer.train(), which this loop does not
            # call; said here so that nobody reads the comparison as checkpointed
            gradient_checkpointing=False,
            save_strategy="no", logging_steps=10 ** 6, seed=cfg.seed, disable_dropout=True,
            dataloader_num_workers=0)
        self.trainer = GRPOTrainer(model=model, reward_funcs=rewards.shaped_reward, args=args,
                                   train_dataset=dataset, processing_class=tokenizer)
        self.trainer.create_optimizer_and_scheduler(num_training_steps=10 ** 6)
        self.trainer.current_gradient_accumulation_steps = 1  # what Trainer's loop would set
        self.timer = PhaseTimer()
        self._instrument()
        self.batches = iter(self.trainer.get_train_dataloader())
        self.tokenizer = tokenizer

    def _timed(self, obj, method: str, phase: str):
        original = getattr(obj, method)
        timer = self.timer

        def wrapper(*args, **kwargs):
            with timer(phase):
                return original(*args, **kwargs)
        setattr(obj, method, wrapper)

    def _instrument(self):
        t = self.trainer
        self._timed(t, "_generate", "generation")
        self._timed(t, "_calculate_rewards", "scoring")
        self._timed(t, "_generate_and_score_completions", "rollout (all)")
        self._timed(t, "compute_loss", "forward")
        self._timed(t.accelerator, "backward", "backward")
        captured = {}
        original = t._generate_and_score_completions

        def capture(*args, **kwargs):
            out = original(*args, **kwargs)
            captured.update(out)
            return out
        t._generate_and_score_completions = capture
        self.captured = captured

    def step(self) -> dict:
        t = self.trainer
        self.timer.seconds.clear()
        start = time.perf_counter()
        t.model.train()
        batch = next(self.batches)
        t.training_step(t.model, batch, None)
        with self.timer("optimizer"):
            torch.nn.utils.clip_grad_norm_(t.model.parameters(), self.cfg.max_grad_norm)
            t.optimizer.step()
            t.lr_scheduler.step()
            t.optimizer.zero_grad(set_to_none=True)
        seconds = dict(self.timer.seconds)
        step = time.perf_counter() - start
        # everything in the rollout that is neither sampling nor scoring (TRL's tokenizing,
        # reward bookkeeping, logging) is reported under scoring
        seconds["scoring"] = seconds.pop("rollout (all)") - seconds["generation"]
        mask = self.captured["completion_mask"]
        prompt_mask = self.captured["prompt_mask"]
        completion_tokens = float(mask.sum())
        prompt_tokens = float(prompt_mask.sum())  # every row carries its full prompt
        return dict(seconds={k: seconds.get(k, 0.0) for k in PHASES}, step=step,
                    completion_tokens=completion_tokens, prompt_tokens_in_batch=prompt_tokens,
                    flops=training_flops(t.model, prompt_tokens, completion_tokens,
                                         completion_tokens + mask.shape[0]),
                    mean_length=float(mask.sum(-1).float().mean()), reward=float("nan"))


# --- the run -----------------------------------------------------------------------------------

def release_free_memory() -> None:
    """Hand memory freed by the previous step back to the OS (glibc keeps it otherwise), so the
    resident set before a step is what is live, and its peak above that is the step's own."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass


def measure(runner, results: list) -> None:
    release_free_memory()
    before = _status_gib("VmRSS")
    reset_peak_memory()
    r = runner.step()
    r["peak_gib"] = _status_gib("VmHWM") - before
    results.append(r)


def run_shape(shape: str, steps: int, matmul_peak: float) -> dict:
    cfg = load_config("cpu", **SAME_WORK, **SHAPES[shape], max_steps=steps + 1, out_dir="runs/benchmark")
    tokenizer = models.load_tokenizer(cfg.model)
    prompts = data.make_prompts(cfg, tokenizer, held_out=False)
    ours = Ours(cfg, prompts)
    with tempfile.TemporaryDirectory() as tmp:
        trl = TRL(cfg, prompts, tmp)
        warm = {"ours": [], "trl": []}
        measure(ours, warm["ours"])   # warm-up: first-call costs (allocations, caches)
        measure(trl, warm["trl"])
        results = {"ours": [], "trl": []}
        for _ in range(steps):
            measure(ours, results["ours"])
            measure(trl, results["trl"])
    return summarize(shape, cfg, results, matmul_peak)


def summarize(shape, cfg, results, matmul_peak) -> dict:
    def mean(side, f):
        return statistics.mean(f(r) for r in results[side])
    out = {"shape": shape, "prompts_per_step": cfg.prompts_per_step, "group_size": cfg.group_size,
           "max_new_tokens": cfg.max_new_tokens, "steps": len(results["ours"]), "sides": {}}
    for side in ("ours", "trl"):
        rs = results[side]
        fwd_bwd = mean(side, lambda r: r["seconds"]["forward"] + r["seconds"]["backward"])
        out["sides"][side] = dict(
            step_s=mean(side, lambda r: r["step"]),
            phase_s={k: mean(side, lambda r, k=k: r["seconds"][k]) for k in PHASES},
            completion_tokens=mean(side, lambda r: r["completion_tokens"]),
            mean_completion_length=mean(side, lambda r: r["mean_length"]),
            prompt_tokens=mean(side, lambda r: r["prompt_tokens_in_batch"]),
            peak_gib=max(r["peak_gib"] for r in rs),
            train_gflops=mean(side, lambda r: r["flops"]) / fwd_bwd / 1e9,
        )
    o, t = out["sides"]["ours"], out["sides"]["trl"]
    out["speedup_per_step"] = t["step_s"] / o["step_s"]
    # per generated token, to discount different completion lengths
    out["speedup_per_token"] = (t["step_s"] / t["completion_tokens"]) / (o["step_s"] / o["completion_tokens"])
    out["matmul_peak_gflops"] = matmul_peak / 1e9
    return out


def print_table(r: dict) -> None:
    o, t = r["sides"]["ours"], r["sides"]["trl"]
    print(f"\n## shape '{r['shape']}': {r['prompts_per_step']} prompts x {r['group_size']} completions, "
          f"up to {r['max_new_tokens']} new tokens, mean of {r['steps']} steps after a warm-up\n")
    print("| phase | course_utils s | TRL s | TRL / ours |")
    print("|---|---|---|---|")
    for k in PHASES:
        a, b = o["phase_s"][k], t["phase_s"][k]
        ratio = f"{b / a:.1f}x" if a >= 0.01 else "(both under 10 ms)" if b < 0.01 else "-"
        print(f"| {k} | {a:.3f} | {b:.3f} | {ratio} |")
    print(f"| **whole step** | **{o['step_s']:.2f}** | **{t['step_s']:.2f}** | **{r['speedup_per_step']:.1f}x** |")
    print()
    print("| | course_utils | TRL |")
    print("|---|---|---|")
    print(f"| completion tokens per step (mean length) | {o['completion_tokens']:.0f} ({o['mean_completion_length']:.1f}) "
          f"| {t['completion_tokens']:.0f} ({t['mean_completion_length']:.1f}) |")
    print(f"| tokens per second (prompt + completion, whole step) | "
          f"{(o['prompt_tokens'] + o['completion_tokens']) / o['step_s']:.0f} | "
          f"{(t['prompt_tokens'] + t['completion_tokens']) / t['step_s']:.0f} |")
    print(f"| generation tokens per second | {o['completion_tokens'] / o['phase_s']['generation']:.0f} | "
          f"{t['completion_tokens'] / t['phase_s']['generation']:.0f} |")
    print(f"| step peak memory above the resident set before it | {o['peak_gib']:.2f} GiB | {t['peak_gib']:.2f} GiB |")
    print(f"| forward+backward GFLOP/s (share of the {r['matmul_peak_gflops']:.0f} GFLOP/s matmul peak) | "
          f"{o['train_gflops']:.0f} ({o['train_gflops'] / r['matmul_peak_gflops']:.0%}) | "
          f"{t['train_gflops']:.0f} ({t['train_gflops'] / r['matmul_peak_gflops']:.0%}) |")
    print(f"\nspeed-up per step {r['speedup_per_step']:.2f}x; per generated token {r['speedup_per_token']:.2f}x")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=list(SHAPES))
    parser.add_argument("--steps", type=int, default=3, help="measured steps per trainer and shape")
    parser.add_argument("--json", default=None, help="also write the results to this file")
    args = parser.parse_args(argv)
    try:
        import trl
    except ImportError:
        raise SystemExit("the benchmark needs TRL: pip install -r benchmarks/requirements.txt")
    warnings.filterwarnings("ignore")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    torch.manual_seed(0)
    peak = matmul_peak_flops()
    print(f"# course_utils vs TRL {trl.__version__} (torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, {platform.machine()})")
    all_results = []
    for shape in args.shapes:
        r = run_shape(shape, args.steps, peak)
        print_table(r)
        all_results.append(r)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(all_results, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
