# %% [markdown]
# # Lesson 7 — The full recipe: GRPO on Qwen2.5-0.5B-Instruct on a Colab T4
#
# {{COLAB_BADGE}}
#
# {{SOLUTIONS_NOTE}}
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
#   see it in the metrics, and what an ablation over {{fig:ablation.seeds}} seeds can and cannot say about the
#   fixes (section 6).
#
# Runtime: *Runtime > Change runtime type > T4 GPU*. On a CPU (and in CI) this notebook runs a
# shrunk version of every step with a tiny model, so it can be read and tested anywhere.

# %%
{{SETUP}}

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
# moments (8) and, under autocast, an fp16 copy (2): {{fig:plan.bytes_per_param}} bytes,
# {{fig:plan.persistent_gib}} GiB for {{fig:plan.params_m}} parameters, before a single activation.
# Then come the activations of one micro-batch (gradient checkpointing keeps only each layer's
# input) and the logits: a vocabulary of {{fig:plan.vocab}} makes every completion token's logits
# {{fig:plan.logits_mb_per_token}} MB in fp32, so they are computed only at completion
# positions. `course_utils.plan` adds these up; its memory model is checked against a peak
# measured on a CPU for a smaller batch of the same architecture (`tests/test_plan.py`, within
# 15%), but in fp32, without checkpointing or autocast and against resident memory: the T4 run
# differs in exactly those terms, so 15% there is a claim its first run tests. (On a GPU
# emulating a T4's limits, section 4, the allocator's peak came to {{fig:gpu.reserved_vs_plan}}
# and {{fig:gpu.accum8.reserved_vs_plan}} of the plan's at two micro-batch sizes.) Under autocast
# the checkpointed layer inputs are the residual stream, which stays fp32 (4 bytes a value, not 2).
#
# **Units.** CUDA counts memory in GiB ($2^{30}$ bytes). A T4 sold as 16 GB reports a total of
# {{fig:plan.t4_total_gib}} GiB with ECC on, as on Colab; the CUDA context and the libraries'
# workspaces hold up to {{fig:plan.t4_outside_gib}} GiB outside PyTorch's allocator, which leaves
# it {{fig:plan.t4_reservable_gib}} GiB. The allocator keeps freed blocks for reuse, so what it
# reserves (`torch.cuda.max_memory_reserved`) exceeds what tensors hold (`max_memory_allocated`);
# the plan assumes a cache of {{fig:plan.t4_cache_pct}} of the tensors' peak. The reserved peak is
# the figure to set against the plan and against the T4; both overheads are read from reports of
# Colab T4s (`course_utils/plan.py` cites them), not measured here.
#
# **The prompt.** {{fig:plan.t4_snippet_tokens}} snippet tokens, plus Qwen2.5's chat template,
# which inserts its own system prompt when the messages have none, plus the instruction: at least
# {{fig:plan.t4_frame_tokens}} tokens by Qwen2's pre-tokenizer (`plan.qwen25_prompt_len`; byte-pair
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
# {{fig:plan.t4_prompts}} prompts ({{fig:plan.t4_steps}} steps, one epoch): about
# {{fig:plan.t4_hours}} hours at the planned rate, leaving a factor of two for the plan's
# assumptions inside a 3-hour session. The plan is arithmetic, not a measurement: watch the
# seconds per step in the progress bar and adjust `train_prompts`. Micro-batches of one prompt's
# 8 completions (`grad_accum=16`) keep the allocator's planned peak at
# {{fig:plan.t4_reserved_gib}} GiB, {{fig:plan.t4_headroom_pct}} below the
# {{fig:plan.t4_reservable_gib}} GiB it has: more than the plan's own error. Twice that per
# micro-batch (`grad_accum=8`) would need {{fig:plan.accum8_logits_gib}} GiB for the logits alone
# and plan {{fig:plan.accum8_reserved_gib}} GiB, a headroom of {{fig:plan.accum8_headroom_pct}},
# inside that error: it may fit or not, so do not count on it (on the emulated T4 of section 4
# it fitted, at {{fig:gpu.accum8.reserved_gib}} GiB, but a T4's own context and cache can
# differ). Near the limit,
# `PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True`, set before torch first uses the GPU, lets
# the allocator grow its blocks instead of caching odd-sized ones, which shrinks its cache.
#
# Two options shrink the persistent part, and the plan shows what each buys. `optimizer=
# "adamw_8bit"` (bitsandbytes) keeps AdamW's moments in 8 bits. `lora_rank=16` trains low-rank
# adapters on every linear layer instead of the weights (peft): {{fig:plan.lora16_params_m}}
# trainable parameters instead of {{fig:plan.params_m}}, so gradients and moments almost vanish,
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
# it shrunk on a CPU. It has run on an {{fig:gpu.name}}, with the allocator capped at
# {{fig:gpu.cap_gib}} GiB ({{fig:gpu.steps}} steps after a warm-up; its output is at the end of
# this section):
#
# - **the allocator's peak** was {{fig:gpu.reserved_gib}} GiB against the plan's
#   {{fig:gpu.plan_reserved_gib}} ({{fig:gpu.reserved_vs_plan}}) with the preset's micro-batches
#   of {{fig:gpu.rows}} rows, and {{fig:gpu.accum8.reserved_gib}} GiB against
#   {{fig:gpu.accum8.plan_reserved_gib}} ({{fig:gpu.accum8.reserved_vs_plan}}) with
#   {{fig:gpu.accum8.rows}} (`grad_accum=8`), which fitted under the cap. The terms were off in
#   opposite directions: the tensors' peak was {{fig:gpu.allocated_vs_plan}} and
#   {{fig:gpu.accum8.allocated_vs_plan}} off the plan's, and the allocator's cache
#   {{fig:gpu.cache_pct}} and {{fig:gpu.accum8.cache_pct}} of the tensors' peak against the plan's
#   {{fig:plan.t4_cache_pct}}. The cache, which depends on the order and sizes of allocations, is
#   the plan's least certain term;
# - **autocast's fp16 copies of the weights**: one sampling forward (no gradients, as the
#   sampler runs) held {{fig:gpu.copies_gib}} GiB more than before it (two forwards), against the
#   plan's two bytes a parameter, {{fig:gpu.plan_copies_gib}} GiB, and at most
#   {{fig:gpu.copies_held_after_gib}} GiB stayed after it returned: the copies are made again at
#   every call, so each decoding step reads the fp32 weights and writes and reads their fp16
#   copies, the time plan's 8 bytes a parameter;
# - **the cap is real**: a block a quarter GiB past it was refused and one a quarter GiB under it
#   granted, so the peaks above were measured under a T4's limit, not beside it;
# - **fp16**: {{fig:gpu.nonfinite_skipped}} steps skipped, and the gradient scaler's scale stayed
#   at {{fig:gpu.scaler_scale}}.
#
# What it could not reproduce: a T4's speed (the {{fig:gpu.name}} took {{fig:gpu.step_s}} s a
# step; the plan's {{fig:plan.t4_hours}} hours rest on {{fig:gpu.plan_t4_step_s}} s a step on a
# T4), the fp16 behaviour of trained weights (random weights overflow differently, or not at
# all), what a T4's own CUDA context holds outside the allocator (this GPU's process held
# {{fig:gpu.outside_gib}} GiB there; the plan takes {{fig:plan.t4_outside_gib}} GiB from Colab
# reports), and Qwen2.5's prompt length: without the hub the check tokenizes with the embedded
# SmolLM2's tokenizer and chat template, so its prompts had {{fig:gpu.prompt_len}} tokens, and the
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
# {{GPU_CHECK}}

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
# token cap, {{fig:cpu_shaped.steps}} steps), and that first job with the recipe's binary reward
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
# {{CPU_RESULTS}}

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
# The shaped credit barely penalizes a miss of {{fig:cpu_shaped.template_miss}} characters (the template's), and, worse, inside a group the
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
# {{DIAGNOSIS}}
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
# worse on {{fig:ablation.sharp_worse}}. The
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
# does nothing": the arm was capped at {{fig:ablation.max_sampling_rounds}} sampling rounds and a batch still short was padded
# with groups without signal, which is not DAPO's method (DAPO resamples until the batch is
# full of groups with signal), and {{fig:ablation.seeds}} seeds detect only large effects (6.3). Where it should
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
# passing completion before step {{fig:ablation.earliest_first_pass}}, and GRPO can only
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
# held-out prompts, over seeds {{fig:ablation.seed_list}} (the table lists the seeds each arm has been run with;
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
# {{ABLATION_RESULTS}}
#
# Read the per-seed column before the means. Seeds of one arm end in very different places, a
# template that passes every one-digit target or almost nothing. Compared unpaired, as
# clouds of {{fig:ablation.seeds}} results each, arms that swing that much could hide a gap of tens of points;
# paired, the swing between seeds cancels and what is left is each seed's difference. Even so,
# {{fig:ablation.seeds}} seeds are few: an exact sign-flip test cannot give a p-value below its floor with {{fig:ablation.seeds}}
# seeds (the lines under the table print it), and the t-interval on {{fig:ablation.df}} degrees of freedom is
# wide, so each "no difference detected" comes with the difference the design could have
# detected. What the table does say:
#
# - **The recipe passes half of the held-out prompts on average, not on every seed.** On
#   {{fig:ablation.template_seeds}} of its {{fig:ablation.seeds}} seeds the recipe settles on a template that passes every one-digit target; its weakest seed passes few
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
#   showed no gain for its cost, not because {{fig:ablation.seeds}} seeds of a capped version show it useless.
# - **The sharp reward made {{fig:ablation.sharp_worse}} seeds' results worse and none better.** Added on top of
#   dynamic sampling, it did no better than dynamic sampling alone on any seed and worse on
#   {{fig:ablation.sharp_worse}}; {{fig:ablation.seeds}} seeds cannot call that a difference (its comparison with the dynamic-sampling
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
# {{fig:probes.window}} steps by a fixed rule (`course_utils.ablation.probe_outcome`): *collapsed onto one
# sentence* when at most {{fig:probes.collapsed_distinct}} of a batch's completions are distinct and the entropy is at
# most {{fig:probes.collapsed_entropy}} nats; *filling the token cap* when {{fig:probes.cap_share}} of completions are cut off at
# `max_new_tokens`; otherwise *still exploring*.
#
# {{PROBES}}
#
# Compare the runs with temperature 0.7 and no other lever, on seeds {{fig:probes.temperature_seeds}}: the same change, opposite endings. On
# one seed, sharper sampling made the policy commit early to a sentence that ignores the digit
# target, and a committed policy has nothing left to explore. On the other it made the policy
# commit to short fragments that the 24-token cap cuts at about 32 characters, with the target
# digit among them: that run passes more held-out prompts than {{fig:probes.noise_above_recipe}} of the recipe's {{fig:ablation.seeds}} seeds
# in 6.3, and its text is noise. A higher learning rate committed earlier still, to a sentence without the digit; {{fig:probes.clip_higher_updates}}
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
# all {{fig:ablation.seeds}} seeds, and one of them passes few prompts when its budget ends. To get
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
# {{TEMPLATE_PROBES}}
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
# {{TEMPLATE_PROBE_LOGS}}
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
# {{COUNTED_PROBES}}
#
# {{COUNTED_PROBE_LOGS}}
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
# {{COUNTED_BY_TARGET}}
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
# {{COUNTED_VS_PRESET}}
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
# are, and run it once on seeds {{fig:fresh.seed_list}}, which were never looked at while
# choosing anything. Nothing was changed after seeing them, and all {{fig:fresh.seeds}} are
# reported. Held out, greedy, one run per seed (the mean's interval is Student's t on n - 1
# degrees of freedom, `ablation.seed_table`):
#
# {{FRESH_SEEDS}}
#
# On its tuning seeds the recipe passed {{fig:fresh.tuning_mean}} of the held-out prompts on
# average (worst seed {{fig:fresh.tuning_worst}}); on the fresh seeds it passes
# {{fig:fresh.mean}} (worst seed {{fig:fresh.worst}}), and no fresh seed's greedy replies pass a
# single held-out two-digit target (sampled replies in training did, a few times on each seed,
# as the table's column says). Every tuning seed passes more than every fresh seed. Had being a
# tuning seed made no difference, that ordering would have a chance of {{fig:fresh.order_chance}}
# (an exact permutation test: each choice of which {{fig:fresh.tuning_seeds}} of the runs are the
# tuning ones is equally likely, and one puts them all on top). Two causes are mixed in that gap,
# and these runs cannot separate them: the winner's curse, and the machine, since the fresh
# runs ran on a different CPU, whose matrix kernels change the arithmetic and so, as section 6.3
# showed, the path a sampled run takes (section 6.7 measures how far the precision alone moves
# one seed's run: most of the range, in either direction).
#
# Of the fresh seeds, {{fig:fresh.template_seeds}} did what {{fig:fresh.tuning_template_seeds}} of the
# {{fig:fresh.tuning_seeds}} tuning seeds did: a template that passes every one-digit target
# held out. Of the {{fig:fresh.seeds}}, {{fig:fresh.cap_filling}} ended *filling the token cap*
# (over the last {{fig:probes.window}} logged steps, at least {{fig:probes.cap_share}} of the
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
# {{FRESH_BY_TARGET}}
#
# The `cpu` preset, run on the same fresh seeds and scored on the same held-out prompts, is
# the comparison that says whether the frozen recipe is worth its extra steps. Paired by seed
# (`stats.paired`: the t-interval on n - 1 degrees of freedom, an exact sign-flip test, and the
# smallest difference these seeds could detect), the recipe minus the preset:
#
# {{FRESH_VS_PRESET}}
#
# No difference detected, and with {{fig:fresh.seeds}} seeds whose outcomes spread this widely, none of the
# size that matters could have been (the smallest detectable difference is printed beside each
# line). The preset, too, passes less on the fresh seeds than on the seeds its levers were
# chosen on: {{fig:ablation.recipe_mean}} on average there (section 6.3), {{fig:fresh.preset_mean}}
# on the fresh ones (worst seed {{fig:fresh.preset_worst}}). Read this pairing with its confound: the preset's
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
# The design is a probe and then a fresh seed, each a pair of runs. First a probe on seed {{fig:cap.seed}}, one of
# section 6.5's fresh seeds that filled the cap. Having been looked at, it is no longer fresh, and
# it is where the settings were fixed: weight {{fig:cap.penalty}} and buffer {{fig:cap.buffer}}, so
# no charge up to {{fig:cap.ramp_start}} tokens and the full charge at the cap of
# {{fig:cap.max_new_tokens}}. So seed
# {{fig:cap.seed}} is a tuning seed, and only seed {{fig:cap.fresh_seed}} below is fresh evidence.
# Then the same settings, unchanged, on seed {{fig:cap.fresh_seed}},
# which no run of this course had used. Each run with the punishment has a control: the frozen
# recipe, unchanged, on the same seed, run one after the other on this machine, in the same
# precision ({{fig:cap.precision}}). The build checks that each probe differs from the recipe in
# the two fields only, and that probe and control record the same precision and the same CPU
# capability (the vector instructions torch reports) in `summary.json`. The
# stored run on seed {{fig:cap.seed}} cannot be the comparison: section 6.5 says it ran in bf16
# on another CPU (its summary predates the precision field). Held out, greedy:
#
# {{CAP_PROBES}}
#
# **Seed {{fig:cap.seed}}, the probe.** Read it in this order.
#
# - **The control did not fill the cap either.** On this machine this run of the recipe took
#   another path: {{fig:cap.control_cut}} of its replies were cut off over the last logged steps
#   ({{fig:cap.control_whole_cut}} over the whole run), against the stored run's
#   {{fig:cap.stored_cut}}. So this probe cannot show that the punishment prevents the hack.
#   Section 6.3 found that changing the kernels changes a sampled run's path; here the CPU and
#   the precision changed together, and the path changed with them.
# - **With the punishment, {{fig:cap.punished_cut}} are cut off over the last logged steps**
#   ({{fig:cap.punished_whole_cut}} over the whole run). At step 1, {{fig:cap.first_cut}} of the
#   replies ran to the cap, and a cut reply now scores its credit minus the full weight, at or below
#   zero. By step {{fig:cap.off_cap_step}} the mean reply was {{fig:cap.off_cap_tokens}} tokens
#   (the control's, that step: {{fig:cap.control_off_cap_tokens}}). Up to
#   {{fig:cap.ramp_start}} tokens (the EOS counted) the punishment charges nothing, and the credit took replies
#   shorter still, to {{fig:cap.shortest_tokens}} tokens at step {{fig:cap.shortest_step}}. The
#   log keeps no completions per step, but that length fits bare digits, and against a one-digit
#   target the target's digit alone earns a counted credit of {{fig:cap.bare_digit}}: the whole
#   digit half of the score, and a little length credit. Replies grew again from there.
# - **For most of the run it learned the main job's kind of template, then switched.** In
#   training (sampled replies; the table below), from step {{fig:cap.stretch_start}} to step
#   {{fig:cap.stretch_end}} every {{fig:cap.window}}-step window passed at least {{fig:cap.most}} of the one-digit
#   targets ({{fig:cap.stretch_one}} in all) and no two-digit target, as the main job's template
#   does. After that it moved to a frame that fits a two-digit number: one-digit passes fell to
#   {{fig:cap.after_one}} and two-digit passes rose to {{fig:cap.after_two}}. The held-out score is
#   a snapshot of a run that changed templates near its end, and where training stopped decides it.
# - **Where it stopped, it writes `{{fig:cap.two_digit_reply}}` for every two-digit target**,
#   whose digits add up to {{fig:cap.two_digit_sum}}. It passes the prompts whose target is
#   {{fig:cap.two_digit_sum}} and no other ({{fig:cap.punished_two}} of the two-digit targets, all
#   with one reply: one behaviour, not independent successes). For one-digit targets it puts the
#   target digit in the same frame, {{fig:cap.one_digit_short}} character short of 32, and passes
#   none ({{fig:cap.punished_one}}). It passes {{fig:cap.punished_pass}} of the held-out prompts,
#   against the control's {{fig:cap.control_pass}}.
#
# **Seed {{fig:cap.fresh_seed}}, fresh.** With the punishment it passes {{fig:cap.fresh_punished_pass}} of
# the held-out prompts: one-digit targets {{fig:cap.fresh_punished_one}}, two-digit targets
# {{fig:cap.fresh_punished_two}}. Its control passes {{fig:cap.fresh_control_pass}} (one-digit
# {{fig:cap.fresh_control_one}}, two-digit {{fig:cap.fresh_control_two}}). What it found is a
# frame in which every reply is 32 characters: a two-digit number and a fixed sentence. For a
# one-digit target the number is the target's digit and a 0 (target
# {{fig:cap.fresh_example_target}}: `{{fig:cap.fresh_example}}`). For every two-digit target it
# is one number, `{{fig:cap.fresh_two_digit_reply}}`, whose digits add up to
# {{fig:cap.fresh_two_digit_sum}}, so only those prompts pass. The length is solved for every
# target; the digit sum is solved only where a copied digit is enough, or where one fixed number
# happens to fit. No reply depends on the target beyond copying a one-digit target's digit.
# Its control did not fill the cap either ({{fig:cap.fresh_control_cut}} of its replies cut off
# over the last logged steps, {{fig:cap.fresh_control_whole_cut}} over the whole run; with the
# punishment {{fig:cap.fresh_punished_cut}} and {{fig:cap.fresh_punished_whole_cut}}). So on
# neither seed does a pair show the punishment preventing the hack, because the hack never came;
# what both pairs show is a punished run that found a different template from its control's
# (seed {{fig:cap.fresh_seed}}'s control wrote `This text was N ... long.`, the table at the end).
#
# Sampled passes in training, per {{fig:cap.window}} steps, for both pairs:
#
# {{CAP_TRAINING}}
#
# Paired by seed (`stats.paired`), the punishment minus its control:
#
# {{CAP_PAIRED}}
#
# With {{fig:cap.pairs}} pairs, neither test can settle anything: an exact sign-flip test has so
# few equally likely sign patterns that its p-value cannot go below {{fig:cap.paired_floor}}, and
# the t-interval has {{fig:cap.paired_df}} degree of freedom, so the two-digit interval that
# excludes 0 rests on two numbers and on a normality that two numbers cannot check. Its two
# differences are close by chance of the draw: each is one fixed reply passing the held-out prompts
# of one target sum, and the seeds hold different numbers of such prompts. Both pairs
# point the same way, and the control fared better on neither seed, but that is a lead, not a
# result.
#
# What each run writes, per target. Seed {{fig:cap.seed}}:
#
# {{CAP_BY_TARGET}}
#
# Seed {{fig:cap.fresh_seed}}:
#
# {{CAP_FRESH_BY_TARGET}}
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
# on seeds {{fig:precision.seed_list}}, once in fp32 and once in bf16, one run after the other on
# one machine, nothing else changed. The build checks that the runs of a pair differ in
# `precision` alone and record the same CPU capability (torch reports
# {{fig:precision.capability}}). One caveat on the design: seed 16's bf16 run came first, as one
# more run of section 6.6's probe, and its failure is what prompted the question; its fp32 twin
# and the other seeds' pairs were run for this section. Held out, greedy, with each run's entropy
# per token over its last {{fig:probes.window}} logged steps, then fp32 minus bf16 paired by seed (`stats.paired`):
#
# {{PRECISION_PAIRS}}
#
# **The runs of a seed ended {{fig:precision.abs_diff_mean}} percentage points apart on
# average** ({{fig:precision.min_abs_diff}} to {{fig:precision.max_abs_diff}}). Of the
# {{fig:precision.runs}} runs, {{fig:precision.template_runs}} found the main job's kind of
# template, a frame that passes every one-digit target held out, and passed
# {{fig:precision.template_pass_low}} to {{fig:precision.template_pass_high}} of the prompts. The
# others passed at most {{fig:precision.other_pass_high}}, and none of them more than
# {{fig:precision.other_one_high}} of its one-digit targets. Two-digit targets stay unsolved:
# {{fig:precision.two_digit_runs}} of the runs passed any held out (at most
# {{fig:precision.two_digit_best}} of them), and only the prompts of one target sum, as a single
# fixed number in its reply would, as in section 6.6's runs. Counting seeds, the template came with fp32 alone
# on {{fig:precision.only_fp32}} and with bf16 alone on {{fig:precision.only_bf16}}, so the
# precision has no direction here: an exact sign test on those discordant seeds gives p =
# {{fig:precision.template_sign_p}}, and the t-interval under the table rests on
# {{fig:precision.paired_pass_df}} degrees of freedom of outcomes that are either a template or a
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
# logged by runs made after it was added: {{fig:precision.gap_runs}} of these): {{fig:precision.gap_mean}}
# nats per token averaged over each run, against {{fig:precision.gap_untrained}} that
# `benchmarks/logprob_gap.py` measured on the untrained policy. Small per token, but summed over
# a reply it is the log of the importance weight the update ignores, whose spread that
# benchmark puts at {{fig:precision.sequence_weight_sd}} (weights from {{fig:precision.weight_low}} to {{fig:precision.weight_high}}
# within one standard deviation). Whether that biases learning is a question these pairs cannot answer,
# because the path dominates. The course's loop can correct it the way TRL corrects vLLM's
# samples: `--is_correction` weights each token's surrogate by pi_trainer / pi_sampler, per
# token or per sequence, truncated at `--is_clip_max` or masked above it
# (`mismatch.importance_weights`, lesson 4's function; `tests/test_losses.py` checks the
# weighted loss and its gradient by hand, `tests/test_train.py` that the bf16 step applies it).
# It is off by default, and no run here measured it.
#
# What this changes. Nothing in the presets: the main job runs in fp32 everywhere, and `auto`
# stays the faster choice where bf16 units exist ({{fig:precision.fp32_seconds}} s per fp32 run
# against {{fig:precision.bf16_seconds}} s per bf16 run here, {{fig:precision.seconds_ratio}}x,
# wall time of whole runs whose replies differ in length, not a benchmark). What it changes is
# how to read any comparison of single runs, here and in papers: a difference between runs
# is a draw from a distribution whose spread, on this task, reached {{fig:precision.max_abs_diff}}
# percentage points within one seed. A recipe
# worth reporting has to make the good path the likely one, and that is measured over many
# seeds, not one.

# %% [markdown]
# ### 6.8 Digits first: a credit without a safe harbour
#
# Read section 6.7's runs by how they ended rather than by their seed. Of the
# {{fig:gated.precision_runs}}, {{fig:gated.precision_templates}} found the template (here: passed
# at least {{fig:gated.template_share}} of their one-digit targets held out). Of the
# others, {{fig:gated.precision_length_first}} ended with more held-out replies of the right
# length than with the right digit sum (`figures.dead_end`), and
# {{fig:gated.precision_digits_first}} the other way round. The first kind is the instructive
# one. Seed {{fig:gated.dead_end_seed}}'s bf16 run writes "{{fig:gated.dead_end}}" for every
# prompt: exactly 32 characters and no digit. Against a target of {{fig:gated.dead_end_sum}} the
# counted credit pays it {{fig:gated.dead_end_counted}}, the whole of its length half. Better
# replies were close: for a one-digit target, one letter swapped for the right digit passes
# outright. The policy hardly ever sampled one, and not only once it had learned the length:
# {{fig:gated.dead_end_early_hits}} of its {{fig:gated.dead_end_early_samples}} sampled replies had the
# right digit sum before the share with the right length first reached half (step
# {{fig:gated.dead_end_length_step}}), and {{fig:gated.dead_end_digit_hits}} of
# {{fig:gated.dead_end_later_samples}} from then to step {{fig:gated.dead_end_steps}}. The exact digit
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
# ({{fig:gated.dead_end_gated}} for the sentence above), and the length pays in proportion to
# what the digits earned, so the digits have to come first. Among replies whose digits are right
# the length still ranks them, between 1/2 (excluded) and 1. It is 1 exactly when the binary
# reward is 1, and never above the counted credit $\frac12 D + \frac12 \ell$: their difference
# is $\frac12 \ell (D - 1) \le 0$. `tests/test_rewards.py` checks both on arbitrary text, and
# the formula on hand examples; the cell prints both credits for a few replies.

# %%
from course_utils import rewards

for reply, digit_target in [({{fig:gated.dead_end_literal}}, {{fig:gated.dead_end_sum}}),
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
# {{fig:gated.tuning_seed_list}}, against their stored bf16 runs as controls. Those seeds had
# already been used, so this table chose the change and proves nothing:
#
# {{GATED_TUNING}}
#
# Then, with nothing changed, on fresh seeds {{fig:gated.fresh_seed_list}} that chose nothing,
# each seed's gated run beside a control, the punished recipe. The build checks that the runs of
# a pair differ in `reward` alone and ran in bf16 on the same CPU capability. Both runs of a pair
# ran on one machine, one after the other, but not every pair on the same machine:
# {{fig:gated.fresh_machines}} (`results/gated/fresh/machines.json`, written from the session logs:
# these runs predate the `cpu` field that `summary.json` now records, and torch's capability
# reads "AVX512" on both). The wall times agree with that file, and the build checks them: the
# runs of each pair within {{fig:gated.same_machine}}x of each other, and seed
# {{fig:gated.fresh_slow_seeds}}'s pair about {{fig:gated.fresh_machine_seconds_ratio}}x as long as the
# others. Running both arms of a pair on one machine keeps the comparison fair, but it does not
# cancel the machine out. The kind of bf16 unit can change a bf16 run's rounding, and section 6.7
# showed that a change of rounding can make the runs of one seed close to independent draws. So
# the machine is one more source of spread, in the seeds' results and in a pair's difference:
# seed {{fig:gated.fresh_slow_seeds}}'s pair, the only one on its machine, differs by
# {{fig:gated.fresh_slow_diff}} points.
#
# {{GATED_FRESH}}
#
# **What the fresh seeds say.** The gated recipe passed {{fig:gated.fresh_gated_mean}} of the
# held-out prompts on average (worst seed {{fig:gated.fresh_gated_worst}}, two-digit targets
# {{fig:gated.fresh_gated_two_mean}}), the counted recipe {{fig:gated.fresh_counted_mean}} (worst
# {{fig:gated.fresh_counted_worst}}, two-digit {{fig:gated.fresh_counted_two_mean}}); the paired
# difference, its interval and the smallest difference these seeds could detect are the first
# line under the table. Of the fresh runs, {{fig:gated.fresh_gated_templates}} gated and
# {{fig:gated.fresh_counted_templates}} counted found the template.
#
# **How the runs ended** (`figures.dead_end`), per stage:
#
# | | template | length first | digits first |
# |---|---|---|---|
# | gated, screen (seeds {{fig:gated.tuning_seed_list}}) | {{fig:gated.tuning_gated_n_template}} | {{fig:gated.tuning_gated_n_length}} | {{fig:gated.tuning_gated_n_digits}} |
# | gated, fresh (seeds {{fig:gated.fresh_seed_list}}) | {{fig:gated.fresh_gated_n_template}} | {{fig:gated.fresh_gated_n_length}} | {{fig:gated.fresh_gated_n_digits}} |
# | counted, screen | {{fig:gated.tuning_counted_n_template}} | {{fig:gated.tuning_counted_n_length}} | {{fig:gated.tuning_counted_n_digits}} |
# | counted, fresh | {{fig:gated.fresh_counted_n_template}} | {{fig:gated.fresh_counted_n_length}} | {{fig:gated.fresh_counted_n_digits}} |
#
# No gated run ended on replies without a digit, the end the gate was built against. Of the
# {{fig:gated.counted_runs}} counted runs {{fig:gated.counted_digit_free}} did, seed
# {{fig:gated.dead_end_seed}}'s in the screen, and on the fresh seeds neither arm did: an end too
# rare here for these seeds to say the gate prevents it. The length-first end has a second form
# that the gate leaves open: one sentence frame with a fixed number in it, written for most
# prompts, whose most frequent reply has the right length ({{fig:gated.fixed_number_examples}}). The form is older than the gate; in section 6.7,
# {{fig:gated.precision_fixed_number}}. Where its digits are right that sentence passes, and near
# there the gate still pays a part of it (the cell above prints one such sentence against its own
# digit sum and one two above it): a frame the policy can settle on for most prompts, with no
# digit-free reply needed.
#
# Of the {{fig:gated.digits_first_runs}} gated runs that ended digits first,
# {{fig:gated.digits_first_unsettled}} never settled on one frame (the reply with its digits taken
# out: no frame was written for more than half the prompts), and {{fig:gated.digits_first_short}}:
# a frame {{fig:gated.digits_first_short_chars}} characters long with a one-digit number, a template one character short of the
# one-digit targets. A reply one character off with the right digits earns
# {{fig:gated.one_off}} under either credit: the two agree wherever the digits are right
# (D = 1), so the gate changes nothing for near misses of that kind.
# Two-digit passes sampled in training, per fresh seed: {{fig:gated.fresh_gated_two_sampled}} for
# gated, {{fig:gated.fresh_counted_two_sampled}} for counted.
#
# The verdict: on fresh seeds the gate made no difference these seeds could detect, and in both
# arms the template still came and went from seed to seed. Neither recipe meets what a recipe worth
# shipping would need (a mean of {{fig:gated.bar_mean}} over fresh seeds with no seed below
# {{fig:gated.bar_worst}}), so the presets stay as they are. Nor do these runs show that the gate
# closed the digit-free end (too rare to compare), while the fixed-number end appears under both
# credits: whatever a fixed reply earns, a policy can settle on it. The two-digit targets show what neither credit taught: in {{fig:gated.one_sum_gated}} of
# the {{fig:gated.gated_runs}} gated runs and {{fig:gated.one_sum_counted}} of the
# {{fig:gated.counted_runs}} counted runs, at least {{fig:gated.one_sum_share}} of the two-digit
# targets held out get replies with one and the same digit sum, whatever the target (most often
# {{fig:gated.one_sum_common}}, in {{fig:gated.one_sum_common_runs}} of those
# {{fig:gated.one_sum_all_runs}} runs). The policy does not tell the two-digit targets apart under either
# credit. A lever these runs have not tried is more samples for the targets not yet solved
# (larger groups for them): in no fresh run were more than {{fig:gated.fresh_two_sampled_max_share}}
# of the two-digit replies sampled in training passes. Larger groups only where a group has no
# spread would fire seldom under a graded credit, which gives most groups some spread; whether
# the two-digit groups had spread, these runs' logs cannot say (they count the groups without
# spread per step, not per target). The log now counts them among the two-digit groups
# (`groups_two_digit`, `zero_std_two_digit` in `metrics.jsonl`), so the next runs can tell.
#
# What the gated policies write held out, per target digit sum (greedy; the most frequent reply
# and its digit sum):
#
# {{GATED_BY_TARGET}}

# %% [markdown]
# ### 6.9 Training only at the forks: a screen
#
# A reply here is a sentence frame and a few digits. Most of its tokens belong to the frame and
# are written with little doubt; the digits, and the words where the frame could still go
# another way, are where it forks. Wang et al. (2025, "Beyond the 80/20 rule", arXiv 2506.01939)
# keep the policy term only at the tokens of highest entropy, the top {{fig:forks.share}} of a
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
# runs below kept {{fig:forks.kept}} of them.

# %%
import torch

from course_utils import losses

# entropies of one reply's tokens, in nats: frame, frame, a digit, frame, a word that could go two ways, end
entropy = torch.tensor([[0.05, 0.02, 2.10, 0.01, 0.90, 0.03]])
real = torch.ones_like(entropy)
for rho in (0.2, 0.4, 1.0):
    print(f"rho = {rho}: policy term at", losses.high_entropy_mask(entropy, real, rho).int().tolist()[0])

# %% [markdown]
# The screen is one change, `--top_entropy_quantile {{fig:forks.quantile}}`, to section 6.8's
# gated recipe, on its tuning seeds {{fig:forks.seed_list}}, with section 6.8's stored gated runs as
# the controls (`python benchmarks/forks_runs.py --seed N` runs the forks arm). The controls were
# not run again in full. One of them, rerun on the forks runs' machine for its first
# {{fig:forks.rerun_steps}} steps, matched its stored log bitwise in every logged number but the
# timings (`results/forks/rerun-gated-seed16-steps5`; the build checks it): evidence, checked on
# that seed's first steps, that each pair differs in the one setting only. The build also checks
# that each forks run is its control with that one setting changed, in bf16 on a CPU with AMX.
#
# {{FORKS_TUNING}}
#
# **What the screen says.** The forks arm passed {{fig:forks.forks_mean}} of the held-out prompts
# on average (worst seed {{fig:forks.forks_worst}}, two-digit targets {{fig:forks.forks_two_mean}}),
# its controls {{fig:forks.gated_mean}} (worst {{fig:forks.gated_worst}}, two-digit
# {{fig:forks.gated_two_mean}}); the paired difference, its interval and the smallest difference
# these seeds could detect are the first line under the table. It ended below its control on
# {{fig:forks.seeds_below}} seeds. Of the {{fig:forks.samples_per_run}} replies a run samples in
# training, {{fig:forks.forks_sampled}} passed per seed, against {{fig:forks.gated_sampled}} for the
# controls.
#
# Its entropy stayed high: at the end (the table's entropy columns) it sampled at
# {{fig:forks.forks_entropy_end}} nats per token, its controls at {{fig:forks.gated_entropy_end}}.
# That spread found almost nothing. Its passing two-digit replies in training were
# {{fig:forks.forks_two_of}} sampled (controls: {{fig:forks.gated_two_of}}), and the right digit sum
# came up in {{fig:forks.forks_digits_sampled}} of its sampled replies (controls:
# {{fig:forks.gated_digits_sampled}}). Nor did it find the length: on average over a run's steps
# {{fig:forks.forks_truncated}} of its sampled replies were cut off at the cap (controls:
# {{fig:forks.gated_truncated}}), and held out {{fig:forks.forks_length_ok}} of its replies had the
# right length (controls: {{fig:forks.gated_length_ok}}). Of its {{fig:forks.held_out}} held-out
# replies per seed, {{fig:forks.bare}} were at most {{fig:forks.bare_chars}} characters long and
# {{fig:forks.echo}} ran to {{fig:forks.echo_chars}} characters or more. The adaptive entropy bonus never switched on in the forks arm (entropy never
# fell to its target; steps with the bonus on: {{fig:forks.forks_bonus_steps}}, against
# {{fig:forks.gated_bonus_steps}} for the controls), so the arms differ there too.
#
# Two readings fit these logs, and neither is tested here (the logs do not record which tokens
# the mask kept). The policy term reached about {{fig:forks.kept_per_reply}} tokens of a reply on
# average, a batch average: the threshold is pooled over the step, so long replies of high
# entropy can take most of them. (a) The kept tokens were mostly the first token and the stop,
# so what the policy learned was where to stop: the short replies above, a digit or little more,
# which the gated credit pays {{fig:forks.bare_gated}} of a pass when it is the right digit for a
# one-digit target, while the frame that would fill {{fig:forks.target_chars}} characters is
# written with little doubt and got no policy term. (b) The masked tokens got the KL alone
# ({{fig:forks.kl_coef}} on every token), which pulls them towards the base model's replies, and
# those run to the cap: at the first step, {{fig:forks.first_truncated}} of them were cut off. With the denominators unchanged the policy
# term shrank to the kept share while the KL kept its weight: against the policy term the KL
# weighs about {{fig:forks.kl_scale}} times what it did. The mean KL per token was
# {{fig:forks.forks_kl}} in the forks runs and {{fig:forks.gated_kl}} in the controls. A forks arm
# with `--kl_coef 0`, closer to the paper's recipe, would tell the two apart.
#
# The paper's gains were on models of 14B and 32B parameters trained on long chains of
# reasoning, and at 8B it only matched training on every token; nothing in it predicts a gain
# for a 135M model whose replies are short (the controls end at {{fig:forks.gated_tokens}} tokens
# a reply).
#
# The verdict: dropped at the screen; not run on fresh seeds; the presets are unchanged. These
# are the seeds section 6.8 chose its recipe on, so the controls' scores are inflated by that
# choice, which biases the screen against the lever. The verdict rests on the size of the
# failure, not on a test: no held-out prompt passed in any forks run, and in training no forks
# run sampled more than {{fig:forks.forks_sampled_max}} passing replies, no control fewer than
# {{fig:forks.gated_sampled_min}}.

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
