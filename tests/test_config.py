"""Configuration: presets load, bad values fail with a message naming the field."""
import pytest

from course_utils.config import PRESETS, Config, ConfigError, load_config, smoke_mode


@pytest.mark.parametrize("preset", sorted(set(PRESETS) - {"t4"}))
def test_presets_validate(preset):
    assert load_config(preset).total_steps >= 1


def test_t4_preset_needs_a_gpu_for_fp16_and_says_so():
    import torch
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    with pytest.raises(ConfigError, match="precision.*fp16 needs a CUDA GPU"):
        load_config("t4")
    assert load_config("t4", precision="fp32").model == "Qwen/Qwen2.5-0.5B-Instruct"


@pytest.mark.parametrize("overrides, field, allowed", [
    (dict(group_size=1), "group_size", "from 2 to"),
    (dict(target_chars=-5), "target_chars", "from 1 to"),
    (dict(prompt_tokens=0), "prompt_tokens", "from 1 to"),
    (dict(temperature=0.0), "temperature", "from 0.01 to 10"),
    (dict(lr=-1e-5), "lr", "> 0"),
    (dict(loss_type="mean"), "loss_type", "grpo, bnpo, dapo, dr_grpo"),
    (dict(target_sampling="prioritized", dynamic_sampling=True), "target_sampling", "dynamic sampling"),
    (dict(entropy_bonus="adaptive"), "entropy_coef", "adaptive"),
    (dict(hard_first_steps=10), "hard_first_steps", "--target_sampling prioritized"),
    (dict(target_sampling="prioritized", hard_first_steps=-1), "hard_first_steps", "from 0 to"),
    (dict(target_sampling="prioritized", hard_first_steps=True), "hard_first_steps", "from 0 to"),
    (dict(target_sampling="prioritized", hard_first_steps=5, digit_sum_max=9), "hard_first_steps",
     "same number of digits"),
    (dict(target_sampling="prioritized", hard_first_ramp=True), "hard_first_ramp", "--hard_first_steps N"),
    (dict(target_sampling="prioritized", hard_first_steps=5, hard_first_ramp="yes"), "hard_first_ramp",
     "true or false"),
    (dict(target_sampling="prioritized", hard_first_steps=5, digit_sum_min=12, digit_sum_max=3),
     "digit_sum_min", "between 0 and digit_sum_max"),
    (dict(reward="dense"), "reward", "binary, shaped"),
    (dict(overlong_penalty=-1.0), "overlong_penalty", "from 0 (off) to 100"),
    (dict(overlong_penalty=float("nan")), "overlong_penalty", "finite"),
    (dict(overlong_penalty=1.0, overlong_buffer=48, max_new_tokens=48), "overlong_buffer",
     "below max_new_tokens=48"),
    (dict(overlong_buffer=8), "overlong_buffer", "--overlong_penalty P"),
    (dict(overlong_penalty=1.0, overlong_buffer=-2), "overlong_buffer", "from 0 to"),
    (dict(is_clip_max=0.5), "is_clip_max", "at least 1"),
    (dict(is_clip_max=float("inf")), "is_clip_max", "finite"),
    (dict(is_correction="tokens"), "is_correction", "token_truncate"),
    (dict(dynamic_sampling=1), "dynamic_sampling", "true or false"),
    (dict(clip_eps_low=1.5), "clip_eps_low", "(0, 1)"),
    (dict(grad_accum=3), "grad_accum", "divide prompts_per_step"),
    (dict(digit_sum_min=9, digit_sum_max=3), "digit_sum_min", "between 0 and digit_sum_max"),
    (dict(digit_sum_max=1000), "digit_sum_max", "9 * target_chars"),
    (dict(prompt_style="raw"), "digit_sum_max", "must equal digit_sum_min"),
    (dict(entropy_bonus="constant", entropy_coef=0.0), "entropy_coef", "> 0"),
    (dict(max_steps=0), "max_steps", "from 1 to"),
    (dict(advantage_scale="global"), "advantage_scale", "group, batch, none"),
    # batch centring with the default per-group scale divides all-equal groups by 0 + eps
    (dict(advantage_center="batch"), "advantage_scale", "'batch' or 'none' with advantage_center='batch'"),
    (dict(kl_coef=-0.1), "kl_coef", "from 0 to 100"),
    (dict(lora_rank=-4), "lora_rank", "from 0 to"),
    (dict(lora_rank=8, lora_alpha=0.0), "lora_alpha", "> 0"),
    (dict(kl_schedule="reward_aware"), "kl_schedule", "kl_coef > 0"),
    (dict(kl_schedule="cosine"), "kl_schedule", "constant, reward_aware"),
    (dict(save_every=0), "save_every", "from 1 to"),
    (dict(max_grad_norm=0.0), "max_grad_norm", "> 0"),
    (dict(top_entropy_quantile=0.0), "top_entropy_quantile", "a share of the tokens"),
    (dict(top_entropy_quantile=1.2), "top_entropy_quantile", "in (0, 1]"),
    (dict(top_entropy_quantile=float("nan")), "top_entropy_quantile", "finite"),
])
def test_invalid_values_name_the_field_and_the_allowed_range(overrides, field, allowed):
    with pytest.raises(ConfigError) as err:
        load_config("smoke", **overrides)
    assert field in str(err.value) and allowed in str(err.value)


def test_8bit_adamw_without_bitsandbytes_says_how_to_install_it():
    import importlib.util
    if importlib.util.find_spec("bitsandbytes") is not None:
        pytest.skip("bitsandbytes is installed")
    with pytest.raises(ConfigError, match="optimizer='adamw_8bit' is invalid.*pip install bitsandbytes"):
        load_config("smoke", optimizer="adamw_8bit")


def test_unknown_key_and_preset_suggest_the_right_name():
    with pytest.raises(ConfigError, match="did you mean 'group_size'"):
        load_config("smoke", grop_size=4)
    with pytest.raises(ConfigError, match="did you mean 'cpu'"):
        load_config("cpux")


def test_smoke_switch(monkeypatch):
    monkeypatch.setenv("COURSE_SMOKE", "1")
    assert smoke_mode()
    monkeypatch.setenv("COURSE_SMOKE", "0")
    assert not smoke_mode()


def test_total_steps():
    cfg = Config(train_prompts=10, prompts_per_step=4, epochs=3)
    assert cfg.steps_per_epoch == 3 and cfg.total_steps == 9
