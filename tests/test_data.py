"""Prompts: the deterministic split and the prompt text."""
import pytest

from course_utils import data
from course_utils.config import load_config


def test_offline_split_is_deterministic_and_disjoint():
    snippets = data.offline_snippets()
    assert len(snippets) >= 40 and all(not s.startswith("#") for s in snippets)
    held = [s for s in snippets if data.is_held_out(s)]
    train = [s for s in snippets if not data.is_held_out(s)]
    assert 4 <= len(held) <= len(snippets) // 2 and not set(held) & set(train)
    assert held == [s for s in data.offline_snippets() if data.is_held_out(s)]


def test_prompts_state_their_targets_and_are_chopped(tokenizer):
    cfg = load_config("smoke", prompt_tokens=8, train_prompts=6)
    prompts = data.make_prompts(cfg, tokenizer, held_out=False)
    assert len(prompts) == 6
    for p in prompts:
        assert len(tokenizer(p.snippet, add_special_tokens=False)["input_ids"]) <= 9
        assert f"exactly {p.target_chars} characters" in p.text
        assert f"add up to {p.target_digit_sum}." in p.text
        assert cfg.digit_sum_min <= p.target_digit_sum <= cfg.digit_sum_max
        assert p.text.startswith("<|im_start|>")  # the chat template was applied
    held = data.make_prompts(cfg, tokenizer, held_out=True)
    assert not {p.snippet for p in held} & {p.snippet for p in prompts}
    assert data.make_prompts(cfg, tokenizer, held_out=False) == prompts


def test_raw_style_is_the_snippet_alone(tokenizer):
    cfg = load_config("smoke", prompt_style="raw", digit_sum_min=5, digit_sum_max=5)
    p = data.make_prompts(cfg, tokenizer, held_out=False)[0]
    assert p.text == p.snippet and p.target_digit_sum == 5


def test_unreachable_dataset_names_the_override(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    with pytest.raises(data.DataUnavailable, match="--dataset.*COURSE_DATASET.*offline"):
        data.openwebtext_snippets(2, held_out=False, dataset="no-such-user/no-such-dataset")
