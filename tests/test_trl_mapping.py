"""Lesson 7's table of TRL flags, checked against TRL's own GRPOConfig."""
from __future__ import annotations

import dataclasses
import importlib.metadata

import pytest

from course_utils import trl_mapping
from course_utils.config import PRESETS, Config

trl = pytest.importorskip("trl")
GRPOConfig = trl.GRPOConfig
TRL_FIELDS = {f.name: f for f in dataclasses.fields(GRPOConfig)}


def build(kwargs: dict, **overrides) -> "trl.GRPOConfig":
    return GRPOConfig(**{**kwargs, "report_to": "none", **overrides})


def test_the_table_is_for_the_installed_trl():
    assert importlib.metadata.version("trl") == trl_mapping.TRL_VERSION


@pytest.mark.parametrize("row", trl_mapping.MAPPING, ids=lambda r: ",".join(r.course) or next(iter(r.trl)))
def test_every_trl_flag_exists_with_the_default_the_table_prints(row):
    for name, default in row.trl.items():
        assert name in TRL_FIELDS, f"GRPOConfig has no field {name!r}"
        assert TRL_FIELDS[name].default == default, \
            f"GRPOConfig.{name} defaults to {TRL_FIELDS[name].default!r}, the table says {default!r}"
    assert bool(row.trl) + bool(row.trainer) <= 1, "a row maps to flags or to a trainer argument"


def test_every_config_field_has_exactly_one_row():
    named = [name for row in trl_mapping.MAPPING for name in row.course]
    assert len(named) == len(set(named)), "a Config field is in two rows"
    assert set(named) == trl_mapping.config_fields(), \
        f"rows for fields Config lacks: {set(named) - trl_mapping.config_fields()}; " \
        f"fields without a row: {trl_mapping.config_fields() - set(named)}"


def test_the_markdown_table_has_a_line_per_row_and_every_field():
    table = trl_mapping.markdown_table()
    assert len(table.splitlines()) == 2 + len(trl_mapping.MAPPING)
    for name in trl_mapping.config_fields():
        assert f"`{name}`" in table


VARIANTS = {
    "cpu": {},
    "adaptive entropy": dict(entropy_bonus="adaptive", entropy_coef=0.01, entropy_target=0.7,
                             entropy_weight_max=0.05),
    "constant entropy": dict(entropy_bonus="constant", entropy_coef=0.003),
    "dapo clip-higher overlong": dict(loss_type="dapo", clip_eps_high=0.28, overlong_filter=True),
    "bnpo, two updates, KL": dict(loss_type="bnpo", updates_per_batch=2, kl_coef=0.04),
    "top-entropy fifth": dict(top_entropy_quantile=0.2),
    "dr grpo, accumulation, warm-up": dict(loss_type="dr_grpo", advantage_scale="none",
                                           grad_accum=2, warmup_steps=5, max_steps=None),
}


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_kwargs_build_a_grpo_config_that_holds_the_courses_values(variant):
    cfg = Config.from_dict({**PRESETS["cpu"], **VARIANTS[variant]})
    kwargs, left_out = trl_mapping.grpo_config_kwargs(cfg)
    assert left_out == []
    args = build(kwargs)
    assert args.num_generations == cfg.group_size
    assert args.per_device_train_batch_size * args.gradient_accumulation_steps \
        == cfg.prompts_per_step * cfg.group_size
    assert args.gradient_accumulation_steps == cfg.grad_accum
    assert args.max_completion_length == cfg.max_new_tokens
    assert (args.temperature, args.top_p, args.top_k) == (cfg.temperature, 1.0, 0)
    assert (args.learning_rate, args.weight_decay, args.max_grad_norm) == \
        (cfg.lr, cfg.weight_decay, cfg.max_grad_norm)
    assert args.warmup_steps == cfg.warmup_steps
    assert str(args.lr_scheduler_type.value) == "constant_with_warmup"
    assert args.loss_type == cfg.loss_type and args.scale_rewards == cfg.advantage_scale
    assert args.num_iterations == cfg.updates_per_batch
    assert (args.epsilon, args.epsilon_high) == (cfg.clip_eps_low, cfg.clip_eps_high)
    assert args.beta == cfg.kl_coef and args.use_bias_correction_kl is False
    assert args.mask_truncated_completions == cfg.overlong_filter
    assert args.top_entropy_quantile == cfg.top_entropy_quantile and args.importance_sampling_level == "token"
    assert args.bf16 is False and args.fp16 is False       # fp32, not TRL's bf16 default
    assert args.gradient_checkpointing == cfg.gradient_checkpointing
    assert args.use_cpu is True and args.seed == cfg.seed
    assert args.max_steps == (-1 if cfg.max_steps is None else cfg.max_steps)
    if cfg.entropy_bonus == "adaptive":
        assert args.use_adaptive_entropy and args.entropy_coef == 0.0
        assert (args.entropy_coef_delta, args.entropy_target, args.entropy_coef_max) == \
            (cfg.entropy_coef, cfg.entropy_target, cfg.entropy_weight_max)
    else:
        assert not args.use_adaptive_entropy
        assert args.entropy_coef == (cfg.entropy_coef if cfg.entropy_bonus == "constant" else 0.0)


@pytest.mark.parametrize("preset", ["t4", "gpt2-rtx4070", "smoke"])
def test_every_presets_precision_reaches_trl(preset):
    cfg = Config.from_dict(PRESETS[preset])
    kwargs, _ = trl_mapping.grpo_config_kwargs(cfg)
    args = build(kwargs, use_cpu=True) if cfg.precision == "bf16" else build(kwargs)  # bf16 needs a device TRL accepts
    assert (args.fp16, args.bf16) == (cfg.precision == "fp16", cfg.precision == "bf16")


@pytest.mark.parametrize("option, value, words", [
    ("advantage_center", "batch", "advantage_center='batch'"),
    ("dynamic_sampling", True, "dynamic_sampling=True"),
    ("kl_schedule", "reward_aware", "kl_schedule='reward_aware'"),
    ("entropy_bonus", "inverse_variance", "entropy_bonus='inverse_variance'"),
    ("target_sampling", "prioritized", "target_sampling='prioritized'"),
    ("is_correction", "sequence_truncate", "is_correction='sequence_truncate'"),
])
def test_options_trl_cannot_express_are_named(option, value, words):
    extra = dict(advantage_scale="batch") if option == "advantage_center" else {}
    cfg = Config.from_dict({**PRESETS["cpu"], option: value, **extra})
    _, left_out = trl_mapping.grpo_config_kwargs(cfg)
    assert len(left_out) == 1 and left_out[0].startswith(words)


@pytest.mark.parametrize("mode, clip_max", [("none", 3.0), ("token_truncate", 2.0), ("sequence_mask", 5.0)])
def test_the_mismatch_correction_reaches_trls_vllm_flags(mode, clip_max):
    cfg = Config.from_dict({**PRESETS["cpu"], "is_correction": mode, "is_clip_max": clip_max})
    args = build(trl_mapping.grpo_config_kwargs(cfg)[0])
    assert args.vllm_importance_sampling_correction is (mode != "none")
    assert args.vllm_importance_sampling_mode == ("sequence_mask" if mode == "none" else mode)
    assert args.vllm_importance_sampling_clip_max == clip_max


def test_the_top_entropy_mask_with_an_entropy_bonus_is_named_as_a_difference():
    # TRL 1.16 applies its entropy bonus on the kept tokens only; the course's covers every token
    cfg = Config.from_dict({**PRESETS["cpu"], "top_entropy_quantile": 0.2, "entropy_bonus": "adaptive",
                            "entropy_coef": 0.01})
    _, left_out = trl_mapping.grpo_config_kwargs(cfg)
    assert left_out == ["top_entropy_quantile with an entropy bonus (TRL applies its bonus, and measures "
                        "its adaptive target, on the kept tokens only; the course on every token)"]
    assert trl_mapping.grpo_config_kwargs(Config.from_dict({**PRESETS["cpu"], "top_entropy_quantile": 0.2}))[1] == []


def test_the_curriculum_is_named_beside_the_prioritized_sampling_it_needs():
    cfg = Config.from_dict({**PRESETS["cpu"], "target_sampling": "prioritized", "hard_first_steps": 5})
    _, left_out = trl_mapping.grpo_config_kwargs(cfg)
    assert left_out == ["target_sampling='prioritized' (TRL shuffles uniformly)",
                        "hard_first_steps=5 (TRL has no curriculum)"]
    cfg = Config.from_dict({**PRESETS["cpu"], "target_sampling": "prioritized", "hard_first_steps": 5,
                            "hard_first_ramp": True})
    assert trl_mapping.grpo_config_kwargs(cfg)[1][-1] == "hard_first_steps=5, ramped (TRL has no curriculum)"


def test_an_unresolved_precision_is_refused_and_a_resolved_one_used():
    cfg = Config.from_dict({**PRESETS["cpu"], "precision": "auto"})
    with pytest.raises(ValueError, match="effective_precision"):
        trl_mapping.grpo_config_kwargs(cfg)
    kwargs, _ = trl_mapping.grpo_config_kwargs(cfg, precision="bf16")
    assert kwargs["bf16"] is True and kwargs["fp16"] is False


def test_the_install_raises_exactly_what_trl_declares_and_never_downgrades(monkeypatch):
    declared = dict(req.split(">=") for req in importlib.metadata.requires("trl")
                    if "extra" not in req and ">=" in req)
    for name, lowest in trl_mapping.TRL_NEEDS.items():
        assert declared[name].split(",")[0].strip() == lowest, name
    real = importlib.metadata.version

    def colab(name):            # Colab's runtime: both too old for TRL 1.16
        return {"datasets": "4.0.0", "pyarrow": "18.1.0"}.get(name) or real(name)

    monkeypatch.setattr(trl_mapping.importlib.metadata, "version", colab)
    assert trl_mapping.install_specs() == ["trl==1.16.0", "datasets==4.7.0", "pyarrow==21.0.0"]

    def newer(name):
        return {"datasets": "5.2.0", "pyarrow": "21.0.0"}.get(name) or real(name)

    monkeypatch.setattr(trl_mapping.importlib.metadata, "version", newer)
    assert trl_mapping.install_specs() == ["trl==1.16.0"]


def test_trl_needs_names_every_package_colab_has_too_old():
    from pathlib import Path
    import re
    from packaging.requirements import Requirement
    freeze = Path(__file__).parent / "colab" / "pip-freeze.gpu.txt"
    colab = {re.sub(r"[-_.]+", "-", m.group(1)).lower(): m.group(2)
             for m in re.finditer(r"^([A-Za-z0-9_.\-]+)==(\S+)$", freeze.read_text(), re.M)}
    too_old = set()
    for text in importlib.metadata.requires("trl"):
        req = Requirement(text)
        if req.marker is not None:            # extras
            continue
        name = re.sub(r"[-_.]+", "-", req.name).lower()
        assert name in colab, f"TRL needs {name}, which Colab does not have"
        version = colab[name].split("+")[0]
        if not req.specifier.contains(version, prereleases=True):
            too_old.add(name)
    assert too_old == set(trl_mapping.TRL_NEEDS)
