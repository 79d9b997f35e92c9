"""LoRA (peft): only adapters train, the reference is the base with adapters off, and a resumed
LoRA run is bitwise the uninterrupted one (the checkpoint holds adapters, not the base)."""
import pytest
import torch

pytest.importorskip("peft")

from course_utils import checkpoint, models, train  # noqa: E402
from course_utils.config import ConfigError, load_config  # noqa: E402
from course_utils.data import Prompt  # noqa: E402

PROMPTS = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5)
           for t in ("One two three", "Four five six seven eight")]


def _adapters(path):
    from safetensors.torch import load_file
    return load_file(str(path / "checkpoint" / "adapter_model.safetensors"))


def test_lora_trains_only_the_adapters_and_starts_at_the_base_model():
    policy = train.setup(load_config("smoke", lora_rank=4, kl_coef=0.1))
    base = models.load_policy("tiny-qwen2", seed=0)
    trainable = {n for n, p in policy.model.named_parameters() if p.requires_grad}
    assert trainable and all("lora_" in n for n in trainable)
    n_adapter = sum(p.numel() for p in policy.optimizer.param_groups[0]["params"])
    n_base = sum(p.numel() for p in base.parameters())
    assert 0 < n_adapter < 0.1 * n_base           # the optimizer holds the adapters only
    assert policy.ref_model is None               # no second copy of the model for the KL
    ids = torch.tensor([[5, 17, 42, 7, 99]])
    with torch.no_grad():                          # B = 0 at init: exactly the base model
        torch.testing.assert_close(policy.model(input_ids=ids).logits, base(input_ids=ids).logits)
    before = {n: p.detach().clone() for n, p in policy.model.named_parameters()}
    metrics = train.grpo_step(policy, PROMPTS)
    assert metrics["adv_std"] > 0 and metrics["kl"] == pytest.approx(0.0, abs=1e-6)
    for n, p in policy.model.named_parameters():
        changed = not torch.equal(before[n], p.detach())
        assert changed == ("lora_" in n), n        # the base weights never move
    assert policy.model.base_model.model.model.layers[0].self_attn.q_proj.lora_A["default"].weight.grad.abs().max() == 0
    # (dL/dA goes through B, which is 0 on step 1: A moves only by weight decay; B learns)
    metrics = train.grpo_step(policy, PROMPTS)
    assert metrics["kl"] > 0                       # adapters on vs off now differ


def test_a_resumed_lora_run_matches_an_uninterrupted_one_bitwise(tmp_path):
    settings = dict(lora_rank=4, kl_coef=0.05, save_every=1)
    train.train(load_config("smoke", out_dir=str(tmp_path / "full"), max_steps=4, **settings),
                progress=False)
    train.train(load_config("smoke", out_dir=str(tmp_path / "part"), max_steps=2, **settings),
                progress=False)
    train.train(load_config("smoke", out_dir=str(tmp_path / "part"), max_steps=4, **settings),
                resume=True, progress=False)
    a, b = _adapters(tmp_path / "full"), _adapters(tmp_path / "part")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert not (tmp_path / "full" / "checkpoint" / "model.safetensors").exists()  # no base copy
    ra = checkpoint.MetricsLog(tmp_path / "full" / "metrics.jsonl").read()
    rb = checkpoint.MetricsLog(tmp_path / "part" / "metrics.jsonl").read()
    assert [r["kl"] for r in ra] == [r["kl"] for r in rb] and [r["step"] for r in rb] == [1, 2, 3, 4]


def test_lora_with_gradient_checkpointing_gives_the_same_gradient():
    grads = []
    for ck in (False, True):
        policy = train.setup(load_config("smoke", lora_rank=4, gradient_checkpointing=ck))
        with torch.no_grad():  # a non-zero B, so that A gets a gradient too
            for n, p in policy.model.named_parameters():
                if "lora_B" in n:
                    p.copy_(torch.randn(p.shape, generator=torch.Generator().manual_seed(1)) * 0.01)
        policy.optimizer.step = lambda *a, **k: None
        train.grpo_step(policy, PROMPTS)
        grads.append(torch.cat([p.grad.flatten() for p in policy.model.parameters()
                                if p.requires_grad]))
    assert grads[0].abs().sum() > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-7)


def test_lora_rank_is_validated():
    with pytest.raises(ConfigError, match="lora_rank=-1 is invalid: must be an integer from 0"):
        load_config("smoke", lora_rank=-1)
