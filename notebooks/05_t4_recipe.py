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
# # Lesson 5 — The full recipe: GRPO on Qwen2.5-0.5B-Instruct on a Colab T4
#
# [![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/05_t4_recipe.ipynb)
#
# *This lesson has no exercises: run it, change the configuration, read the curves.*
#
# Everything from lessons 1-4, on a real language model: Qwen2.5-0.5B-Instruct continues
# openwebtext snippets and must write exactly 64 characters whose digits add up to a target the
# prompt states, judged only by the rule checker. The loop is `course_utils.train` (the same code
# as the command line), nothing hidden.
#
# **What you will learn**
# - how a GRPO run is sized for a 16 GB GPU: a memory and time plan, term by term, before any
#   model loads;
# - what a T4 can and cannot do (fp16 with a gradient scaler and NaN guards; no bf16, no TF32);
# - how to survive a Colab disconnect (checkpoints, on Google Drive if you like, and resume);
# - how to read a run: the curves, and held-out completions before and after.
#
# Runtime: *Runtime > Change runtime type > T4 GPU*. On a CPU (and in CI) this notebook runs a
# shrunk version of every step with a tiny model, so it can be read and tested anywhere.

# %%
# Set-up. In Colab: install course_utils from the course repository. Colab's own torch is
# kept (course_utils only asks for torch>=2.2). Anywhere else this cell does nothing: there
# you installed the course with the README's command.
import sys

if "google.colab" in sys.modules:
    import subprocess

    subprocess.run([sys.executable, "-m", "pip", "install", "-q",
                    "course-utils @ git+https://github.com/policy-gradients-course/policy-gradients-for-llms.git"], check=True)

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
# (the seed standardized over the whole batch instead; `advantage_center="batch"` restores that),
# the shaped reward rather than the seed's binary one (section 5 shows why),
# 16 prompts per step, 128-token openwebtext prompts, a 64-character target, AdamW with lr 1e-5
# and weight decay 0.01, gradient clipping at 1.0, gradient accumulation, fp16 autocast with fp32
# master weights, gradient checkpointing, and the seed's entropy bonus scaled by the inverse
# reward variance (a course extension, not part of GRPO). Without a GPU the same preset runs
# shrunk: a tiny random model, offline prompts, fp32, three steps.

# %%
RUN_DIR = "runs/t4"
USE_DRIVE = False   # True: keep checkpoints and logs on Google Drive, safe from disconnects
if IN_COLAB and USE_DRIVE:
    from google.colab import drive
    drive.mount("/content/drive")
    RUN_DIR = "/content/drive/MyDrive/grpo-course/runs/t4"

if GPU:
    cfg = load_config("t4", out_dir=RUN_DIR)
else:  # the T4 code paths (checkpointing, accumulation, entropy bonus) on a tiny model, fp32
    cfg = load_config("t4", model="tiny-qwen2", prompt_source="offline", precision="fp32",
                      prompt_tokens=16, target_chars=48, prompts_per_step=2, group_size=4,
                      grad_accum=2, max_new_tokens=12, lr=1e-3, train_prompts=6, eval_prompts=4,
                      save_every=2, out_dir="runs/t4-smoke")
print(json.dumps(cfg.to_dict(), indent=1))

# %% [markdown]
# ## 2. The plan: will it fit, and how long will it take?
#
# Full fine-tuning keeps, per parameter, an fp32 weight (4 bytes), its gradient (4), AdamW's two
# moments (8) and, under autocast, an fp16 copy (2): 18 bytes, 8.4 GiB for 494M parameters,
# before a single activation. Then come the activations of one micro-batch (gradient
# checkpointing keeps only each layer's input) and the logits: a vocabulary of 151,936 makes
# every completion token's logits 0.6 MB in fp32, so they are computed only at completion
# positions. `course_utils.plan` adds these up; its memory model is checked against a peak
# measured on a CPU for a smaller batch of the same architecture (`tests/test_plan.py`, within
# 15%). The time plan divides FLOPs by the T4's published peak and adds a fixed cost per decoding
# step: both efficiency figures are assumptions, printed with the result.

# %%
t4_cfg = Config.from_dict(PRESETS["t4"])   # the T4 run's settings (not validated: no GPU needed to plan)
prompt_len = 128 + 45          # snippet + chat template and instruction
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
# 10,240 prompts (640 steps, one epoch): about 1.3 hours at the planned rate, leaving a factor
# of two for the plan's assumptions inside a 3-hour session. The plan is arithmetic, not a
# measurement: watch the seconds per step in the progress bar and adjust `train_prompts`.
# Micro-batches of 2 prompts x 8 completions (`grad_accum=8`) keep the peak near 12 GiB; with
# `grad_accum=4` the logits alone would need 5.3 GiB and the run would not fit.
#
# Two options shrink the persistent part, and the plan shows what each buys. `optimizer=
# "adamw_8bit"` (bitsandbytes) keeps AdamW's moments in 8 bits. `lora_rank=16` trains low-rank
# adapters on every linear layer instead of the weights (peft): 8.8M trainable parameters instead
# of 494M, so gradients and moments almost vanish, and with a KL term the reference model is the
# same network with its adapters switched off, not a second copy. Neither is needed to fit this
# run, so both are off by default: LoRA changes what is learned (a rank-16 update), and the
# saving is in memory, not time (the forward and backward still run through every frozen weight).
# The LoRA memory estimate is rougher than the full fine-tuning one (within 25% of a CPU
# measurement, `tests/test_plan.py`).

# %%
for name, change in [("8-bit AdamW", dict(optimizer="adamw_8bit")), ("LoRA r=16", dict(lora_rank=16))]:
    variant = Config.from_dict({**PRESETS["t4"], **change})
    peak = plan.peak_bytes(plan.memory_plan(plan.QWEN25_05B, variant, prompt_len, variant.max_new_tokens))
    print(f"{name:12s} planned peak {peak / plan.GiB:5.2f} GiB")

# %% [markdown]
# ## 3. Train (and resume)
#
# `resume=True` continues from the run directory's last checkpoint if there is one, and starts
# fresh otherwise, so **this same cell is the resume cell**: after a disconnect, run the cells
# above again and then this one. Checkpoints are written atomically every `save_every` steps;
# the metrics log is append-only and is trimmed back to the checkpoint on resume, so no step is
# lost or counted twice. With fp16, a step whose loss or gradients are not finite is skipped and
# counted (`nonfinite_skipped` in the metrics), never applied.

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
# ## 5. A real result on a CPU
#
# The T4 run cannot be executed where this course is built. What was run, for real, is the same
# loop on the embedded SmolLM2-135M-Instruct on 2 CPU cores (the `cpu` preset: 32-character
# target, 32-token snippets, 40 steps of 4 prompts x 8 completions), with the recipe's binary
# reward and with the shaped one. The commands:
#
# ```bash
# python -m course_utils.train --preset cpu --out_dir runs/cpu                  # shaped reward
# python -m course_utils.train --preset cpu --reward binary --out_dir runs/cpu-binary
# ```
#
# Their outputs are saved in `notebooks/results/`; both runs are deterministic on a CPU, so the
# commands reproduce them exactly.
#
# **Run `cpu`** (files in `notebooks/results/cpu/`)
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

# %% [markdown]
# **Binary or shaped?** With the recipe's binary reward nothing happened, and the curves say
# why: at the start no completion passes both constraints, so in all 40 steps every group of 8
# had the same reward (0), every advantage was 0, the gradient was exactly 0 (`grad_norm` 0 in
# `metrics.jsonl`) and the held-out table is unchanged. With the shaped reward every group had
# spread from step 1, the mean miss fell from 88 to 2 characters and the mean reward rose from
# 0.42 to 0.94. But read the completions: the recipe's pass rate is still 0%. The policy found a
# template, "*N* characters with only spaces.", with *N* the target digit sum copied from the
# instruction: 30 characters, which the shaped length credit barely penalizes, and a correct
# digit sum whenever the target is a single digit. By the last steps whole groups write the
# same template, so zero-std groups come back (`zero_std_frac` up to 0.75): the policy has
# collapsed onto it. Partial credit gave the signal the binary reward could not, and then
# became the target. The `t4` preset still trains on the **shaped** reward, because without
# signal nothing is learned at all, and *reports* the recipe's binary pass rate ("both" in the
# tables) so that a hack like this one is visible; a binary reward needs a policy that already
# passes sometimes, or larger groups, or DAPO's dynamic sampling. Counters worth trying (not
# built in; good exercises): a curriculum that switches to the binary reward once the length
# pass rate is clearly above 0, or a sharper length credit. Set `reward="binary"` to run the
# seed's choice and watch `zero_std_frac`.
#
# ## 6. Next steps: the same rewards in TRL
#
# `course_utils.rewards` functions have TRL's signature, so TRL's `GRPOTrainer` takes them
# unchanged; extra dataset columns (`target_chars`, `target_digit_sum`) reach them as keyword
# arguments. TRL adds what a bigger run needs: multi-GPU through `accelerate launch`, vLLM for
# fast generation, DeepSpeed. The cell runs only where `trl` is installed and a GPU is present.

# %%
import importlib.util

if importlib.util.find_spec("trl") is None or not GPU or SMOKE:
    print("Skipped: needs `pip install trl` and a GPU (the course does not install trl).")
else:
    from datasets import Dataset
    from trl import GRPOConfig, GRPOTrainer

    from course_utils import data, models, rewards

    tokenizer = models.load_tokenizer(cfg.model)
    prompts = data.make_prompts(cfg, tokenizer, held_out=False)[:64]
    dataset = Dataset.from_list([{"prompt": p.text, "target_chars": p.target_chars,
                                  "target_digit_sum": p.target_digit_sum} for p in prompts])
    args = GRPOConfig(output_dir="runs/trl", num_generations=cfg.group_size,
                      per_device_train_batch_size=cfg.group_size, max_completion_length=cfg.max_new_tokens,
                      learning_rate=cfg.lr, weight_decay=cfg.weight_decay, max_grad_norm=cfg.max_grad_norm,
                      beta=cfg.kl_coef, loss_type=cfg.loss_type, fp16=True, max_steps=10, logging_steps=1)
    trainer = GRPOTrainer(model=cfg.model, reward_funcs=[rewards.shaped_reward, rewards.binary_reward],
                          args=args, train_dataset=dataset)
    trainer.train()

# %% [markdown]
# ## Check yourself
#
# 1. Which term of the memory plan is largest, and which one does gradient accumulation shrink?
# 2. Why does a T4 need a gradient scaler with fp16, and why does the scaler not protect the
#    forward pass from overflow?
# 3. After a disconnect, which cells do you run, and how do you know no step was repeated?
# 4. Why might the binary reward give no learning signal at the start, and what do the
#    `zero_std_frac` curves show?
