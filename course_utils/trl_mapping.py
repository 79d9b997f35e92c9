"""From this course's ``Config`` to TRL 1.16's ``GRPOConfig``: which flag does what.

Lesson 7 prints ``MAPPING`` as its table and trains TRL with ``grpo_config_kwargs(cfg)``.
``tests/test_trl_mapping.py`` checks every TRL name and default here against ``trl.GRPOConfig``,
that every ``Config`` field has a row, and that the kwargs build a ``GRPOConfig`` whose fields
hold the course's values.

Three TRL defaults differ from what a reader of the GRPO papers expects, and each changes a run
if it is not set: ``loss_type`` is "dapo" (the course's default is "grpo"), ``bf16`` is switched
on whenever ``fp16`` is off (also on a CPU), and ``use_bias_correction_kl`` multiplies the k3
term by the ratio, which changes the KL's gradient even on-policy. ``grpo_config_kwargs`` sets all
three, and the learning-rate schedule (TRL's default decays linearly to 0; the course's is
constant after its warm-up).
"""
from __future__ import annotations

import dataclasses
import importlib.metadata
from dataclasses import dataclass, field
from typing import Any

from packaging.version import Version

from .config import Config

TRL_VERSION = "1.16.0"
# What TRL 1.16 requires at a version newer than Colab's runtime has (datasets 4.0.0 and
# pyarrow 18.1.0 on 2026-08-19): the lowest versions TRL accepts, so the install changes least.
TRL_NEEDS = {"datasets": "4.7.0", "pyarrow": "21.0.0"}


def install_specs() -> list[str]:
    """The pip requirements that add TRL to this environment: TRL itself, and each of
    ``TRL_NEEDS`` only where the installed version is older (nothing is downgraded)."""
    specs = [f"trl=={TRL_VERSION}"]
    for name, lowest in TRL_NEEDS.items():
        try:
            have = Version(importlib.metadata.version(name))
        except importlib.metadata.PackageNotFoundError:
            have = None
        if have is None or have < Version(lowest):
            specs.append(f"{name}=={lowest}")
    return specs


@dataclass(frozen=True)
class Row:
    """One line of the table: course options, the TRL flags that do the same, and how."""
    course: tuple[str, ...]                      # Config fields
    trl: dict[str, Any] = field(default_factory=dict)   # GRPOConfig field -> TRL 1.16's default
    trainer: str = ""                            # or a GRPOTrainer argument instead of a flag
    note: str = ""


MAPPING: tuple[Row, ...] = (
    Row(("group_size",), {"num_generations": 8}, note="G, the completions per prompt"),
    Row(("prompts_per_step", "grad_accum"),
        {"per_device_train_batch_size": 8, "gradient_accumulation_steps": 1},
        note="TRL counts completions: per device = prompts_per_step x G / grad_accum"),
    Row(("max_new_tokens",), {"max_completion_length": 512}),
    Row(("temperature",), {"temperature": 1.0, "top_p": 1.0, "top_k": 0},
        note="the course samples from the whole tempered distribution (lesson 4, section 6: "
             "what top-p or top-k would bias)"),
    Row(("lr",), {"learning_rate": 1e-6}),
    Row(("weight_decay",), {"weight_decay": 0.0}),
    Row(("warmup_steps",), {"warmup_steps": 0, "lr_scheduler_type": "linear"},
        note="the course holds the rate constant after warm-up: 'constant_with_warmup'; TRL's "
             "default decays it to 0 over the run"),
    Row(("max_grad_norm",), {"max_grad_norm": 1.0}),
    Row(("optimizer",), {"optim": "adamw_torch_fused"},
        note="'adamw' is 'adamw_torch', 'adamw_8bit' is 'adamw_bnb_8bit'"),
    Row(("advantage_center",),
        note="TRL always centres on the group's mean; the course's 'batch' has no TRL flag"),
    Row(("advantage_scale",), {"scale_rewards": "group"},
        note="the same three values: 'group', 'batch' (the batch's std), 'none' (Dr. GRPO)"),
    Row(("loss_type",), {"loss_type": "dapo"},
        note="the same four names and formulas; TRL's default is 'dapo', the course's 'grpo'"),
    Row(("updates_per_batch",), {"num_iterations": 1}, note="mu, updates on each batch"),
    Row(("clip_eps_low",), {"epsilon": 0.2}),
    Row(("clip_eps_high",), {"epsilon_high": None},
        note="None means epsilon; DAPO's clip-higher is 0.28"),
    Row(("kl_coef",), {"beta": 0.0, "use_bias_correction_kl": True},
        note="the course's plain k3 is use_bias_correction_kl=False; TRL's default multiplies "
             "it by the ratio (lesson 6, section 6)"),
    Row(("kl_schedule",), note="'reward_aware' is a course extension (lesson 8): no TRL flag"),
    Row(("overlong_filter",), {"mask_truncated_completions": False}),
    Row(("overlong_penalty", "overlong_buffer"), {"reward_weights": None},
        note="a second reward function, trl.rewards.get_soft_overlong_punishment(max_new_tokens, "
             "overlong_buffer), weighted by reward_weights=[1, overlong_penalty]; "
             "overlong_buffer=0 (only text cut off without EOS) has no TRL equivalent"),
    Row(("dynamic_sampling", "max_sampling_rounds"),
        note="no TRL flag: TRL trains on every group; an all-equal group has advantage 0"),
    Row(("entropy_bonus", "entropy_coef", "entropy_target", "entropy_weight_max"),
        {"entropy_coef": 0.0, "use_adaptive_entropy": False, "entropy_coef_delta": 0.005,
         "entropy_target": 0.2, "entropy_coef_min": 0.0, "entropy_coef_max": 1.0},
        note="'constant': entropy_coef. 'adaptive' is TRL's use_adaptive_entropy (the course's "
             "entropy_coef is TRL's entropy_coef_delta, its entropy_weight_max TRL's "
             "entropy_coef_max, starting from 0; TRL gates at or below the target, the course below "
             "it). TRL adds each micro-batch's per-token mean entropy whatever the loss type; the "
             "course aggregates the bonus like the loss, the same for 'dapo' without accumulation. "
             "'inverse_variance' has no TRL flag"),
    Row(("top_entropy_quantile",), {"top_entropy_quantile": 1.0},
        note="1 trains on every token; 0.2 keeps the highest-entropy fifth of each micro-batch's "
             "tokens in the policy term (lesson 6); both threshold at torch.quantile, >=, the course over "
             "each process's micro-batch, TRL over the micro-batch gathered from every process"),
    Row((), {"importance_sampling_level": "token"},
        note="the course's ratio is per token; 'sequence' is GSPO's"),
    Row((), {"use_vllm": False},
        note="the course samples with its own loop: the policy, or under bf16 on a CPU a bf16 "
             "copy of it"),
    Row(("is_correction", "is_clip_max"),
        {"vllm_importance_sampling_correction": True, "vllm_importance_sampling_mode": "sequence_mask",
         "vllm_importance_sampling_clip_max": 3.0},
        note="TRL corrects only vLLM's samples, on by default; the course corrects its bf16 "
             "copy's, off by default ('none'; lesson 4, section 6, and lesson 7, section 6.7)"),
    Row(("target_sampling", "hard_first_steps", "hard_first_ramp"), {"shuffle_dataset": True},
        note="'uniform' is TRL's shuffle; 'prioritized' and hard_first_steps(_ramp) "
             "(course_utils.curriculum) have no TRL flag"),
    Row(("precision",), {"fp16": False, "bf16": None},
        note="bf16=None turns bf16 on unless fp16 is set, on a CPU too: set both"),
    Row(("gradient_checkpointing",), {"gradient_checkpointing": True},
        note="on by default in TRL, off in the course's cpu preset"),
    Row(("device",), {"use_cpu": False}),
    Row(("seed",), {"seed": 42}),
    Row(("epochs", "max_steps"), {"num_train_epochs": 3.0, "max_steps": -1}),
    Row(("save_every",), {"save_steps": 500}),
    Row(("out_dir",), {"output_dir": None}),
    Row(("model",), trainer="model", note="pass the model loaded in fp32 (lesson 7, section 7)"),
    Row(("reward",), trainer="reward_funcs", note="course_utils.rewards has TRL's signature"),
    Row(("lora_rank", "lora_alpha"), trainer="peft_config",
        note="peft.LoraConfig(r=lora_rank, lora_alpha=lora_alpha, target_modules='all-linear')"),
    Row(("prompt_source", "dataset", "prompt_tokens", "prompt_style", "target_chars",
         "digit_sum_min", "digit_sum_max", "train_prompts"), trainer="train_dataset",
        note="the prompts of data.make_prompts, with target_chars and target_digit_sum columns"),
    Row(("eval_prompts", "eval_every"),
        note="the course's held-out greedy pass rate; TRL evaluates with eval_dataset"),
    Row(("kernels",), note="the course's own sampler and output layer (train.py)"),
)

OPTIM = {"adamw": "adamw_torch", "adamw_8bit": "adamw_bnb_8bit"}


def no_equivalent(cfg: Config) -> list[str]:
    """The options of ``cfg`` that TRL 1.16 cannot express, one short line each."""
    lines = []
    if cfg.advantage_center != "group":
        lines.append(f"advantage_center={cfg.advantage_center!r} (TRL centres on the group)")
    if cfg.dynamic_sampling:
        lines.append("dynamic_sampling=True (TRL keeps every group)")
    if cfg.kl_schedule != "constant":
        lines.append(f"kl_schedule={cfg.kl_schedule!r} (TRL's beta is constant)")
    if cfg.entropy_bonus == "inverse_variance":
        lines.append("entropy_bonus='inverse_variance' (TRL has constant and adaptive)")
    if cfg.target_sampling != "uniform":
        lines.append(f"target_sampling={cfg.target_sampling!r} (TRL shuffles uniformly)")
    if cfg.overlong_penalty and not cfg.overlong_buffer:
        lines.append("overlong_penalty with overlong_buffer=0 (TRL's soft punishment with no "
                     "cache punishes nothing)")
    elif cfg.overlong_penalty:
        lines.append("overlong_penalty (add trl.rewards.get_soft_overlong_punishment to the "
                     "reward functions, weighted by reward_weights)")
    if cfg.is_correction != "none":
        lines.append(f"is_correction={cfg.is_correction!r} (TRL corrects only vLLM's samples; "
                     f"the kwargs carry the mode, which acts once use_vllm=True)")
    if cfg.top_entropy_quantile < 1 and cfg.entropy_bonus != "none":
        lines.append("top_entropy_quantile with an entropy bonus (TRL applies its bonus, and "
                     "measures its adaptive target, on the kept tokens only; the course on every token)")
    if cfg.hard_first_steps:
        ramp = ", ramped" if cfg.hard_first_ramp else ""
        lines.append(f"hard_first_steps={cfg.hard_first_steps}{ramp} (TRL has no curriculum)")
    return lines


def grpo_config_kwargs(cfg: Config, precision: str | None = None) -> tuple[dict[str, Any], list[str]]:
    """``GRPOConfig`` keyword arguments that train as ``cfg`` does, and what they leave out.

    ``precision`` is the run's resolved precision (``train.effective_precision(cfg)``) when
    ``cfg.precision`` is 'auto'. The second value lists the options of ``cfg`` that TRL has no
    flag for (``no_equivalent``): the kwargs train without them.
    """
    precision = precision or cfg.precision
    if precision not in ("fp32", "fp16", "bf16"):
        raise ValueError(f"precision {precision!r} is not resolved: pass "
                         f"precision=train.effective_precision(cfg)")
    rows = cfg.prompts_per_step * cfg.group_size
    if rows % cfg.grad_accum:
        raise ValueError(f"prompts_per_step x group_size = {rows} completions do not split into "
                         f"grad_accum={cfg.grad_accum} equal micro-batches")
    kwargs = dict(
        num_generations=cfg.group_size, per_device_train_batch_size=rows // cfg.grad_accum,
        gradient_accumulation_steps=cfg.grad_accum, max_completion_length=cfg.max_new_tokens,
        temperature=cfg.temperature, top_p=1.0, top_k=0,
        learning_rate=cfg.lr, weight_decay=cfg.weight_decay, warmup_steps=cfg.warmup_steps,
        lr_scheduler_type="constant_with_warmup", max_grad_norm=cfg.max_grad_norm,
        optim=OPTIM[cfg.optimizer],
        scale_rewards=cfg.advantage_scale, loss_type=cfg.loss_type,
        num_iterations=cfg.updates_per_batch, epsilon=cfg.clip_eps_low,
        epsilon_high=cfg.clip_eps_high, beta=cfg.kl_coef, use_bias_correction_kl=False,
        mask_truncated_completions=cfg.overlong_filter, top_entropy_quantile=cfg.top_entropy_quantile,
        importance_sampling_level="token", shuffle_dataset=True,
        vllm_importance_sampling_correction=cfg.is_correction != "none",
        vllm_importance_sampling_mode="sequence_mask" if cfg.is_correction == "none" else cfg.is_correction,
        vllm_importance_sampling_clip_max=cfg.is_clip_max,
        fp16=precision == "fp16", bf16=precision == "bf16",
        gradient_checkpointing=cfg.gradient_checkpointing, use_cpu=cfg.device == "cpu",
        seed=cfg.seed, num_train_epochs=cfg.epochs,
        max_steps=-1 if cfg.max_steps is None else cfg.max_steps, save_steps=cfg.save_every,
        output_dir=cfg.out_dir.rstrip("/") + "-trl",
    )
    if cfg.entropy_bonus == "constant":
        kwargs.update(entropy_coef=cfg.entropy_coef)
    elif cfg.entropy_bonus == "adaptive":
        kwargs.update(use_adaptive_entropy=True, entropy_coef=0.0, entropy_coef_min=0.0,
                      entropy_coef_delta=cfg.entropy_coef, entropy_target=cfg.entropy_target,
                      entropy_coef_max=cfg.entropy_weight_max)
    else:
        kwargs.update(entropy_coef=0.0)
    return kwargs, no_equivalent(cfg)


def _cell(row: Row) -> str:
    if row.trainer:
        return f"GRPOTrainer({row.trainer}=...)"
    if not row.trl:
        return "none"
    return ", ".join(f"`{name}` ({default!r})" for name, default in row.trl.items())


def markdown_table() -> str:
    """``MAPPING`` as a Markdown table: course option | TRL flag (its default) | note."""
    lines = [f"| course option | TRL {TRL_VERSION} (default) | note |", "|---|---|---|"]
    for row in MAPPING:
        course = ", ".join(f"`{name}`" for name in row.course) or "(fixed)"
        lines.append(f"| {course} | {_cell(row)} | {row.note} |")
    return "\n".join(lines)


def config_fields() -> set[str]:
    return {f.name for f in dataclasses.fields(Config)}
