"""The memory plan against peaks measured on the CPU, and the time plan's arithmetic."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from course_utils import plan
from course_utils.config import load_config

PROBE = Path(__file__).with_name("memory_probe.py")
# the probe measures the CPU's resident memory, so it runs on the CPU on a GPU machine too
CPU_ONLY = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}


def _cfg(**kw):
    return load_config("smoke", **{"grad_accum": 1, **kw})


def _unchecked(**kw):
    """A config with options a CPU refuses to run (fp16): planning needs no GPU."""
    from course_utils.config import Config
    return Config.from_dict({**load_config("smoke").to_dict(), "grad_accum": 1, **kw})


def test_qwen_parameter_count_matches_the_architecture():
    from transformers import Qwen2Config
    cfg = Qwen2Config(vocab_size=151_936, hidden_size=896, intermediate_size=4864, num_hidden_layers=24,
                      num_attention_heads=14, num_key_value_heads=2, tie_word_embeddings=True)
    a = plan.Architecture.from_config(cfg, plan.QWEN25_05B.n_params)
    assert a == plan.QWEN25_05B
    h, kv, i, L, V = 896, 128, 4864, 24, 151_936
    per_layer = (h * h + h) + 2 * (h * kv + kv) + h * h + 3 * h * i + 2 * h
    assert V * h + L * per_layer + h == plan.QWEN25_05B.n_params


# The full-size probe takes minutes at the larger shapes, so those peaks are measured by
# benchmarks/memory_peaks.py and stored; the smallest shape is measured live here, so a change in
# what the probe measures (torch, the allocator) still shows up in every test run.
STORED_PEAKS = Path(__file__).resolve().parents[1] / "benchmarks" / "memory_peaks.json"


def _stored_peak(prompts, group, prompt_len, completion_len, lora_rank=0) -> float:
    shape = dict(prompts=prompts, group_size=group, prompt_len=prompt_len,
                 completion_len=completion_len, lora_rank=lora_rank)
    rows = json.loads(STORED_PEAKS.read_text())["peaks"]
    found = [r["peak_gib"] for r in rows if {k: r[k] for k in shape} == shape]
    assert found, f"{shape} is not in {STORED_PEAKS.name}: run python benchmarks/memory_peaks.py"
    return found[0] * plan.GiB


def _predicted(prompts, group, prompt_len, completion_len, lora_rank=0) -> float:
    cfg = _cfg(prompts_per_step=prompts, group_size=group, lora_rank=lora_rank)
    return plan.peak_bytes(plan.memory_plan(plan.QWEN25_05B, cfg, prompt_len, completion_len,
                                            device=plan.CPU_PROBE))


def test_memory_plan_within_15_percent_of_a_cpu_peak_measured_now():
    """A small batch, where AdamW's update is the larger transient, measured in this run."""
    shape = (1, 4, 64, 16)
    out = subprocess.run([sys.executable, str(PROBE), *map(str, shape)], capture_output=True,
                         text=True, timeout=600, check=True, env=CPU_ONLY)
    measured = json.loads(out.stdout.strip().splitlines()[-1])["peak_gib"] * plan.GiB
    predicted = _predicted(*shape)
    assert abs(predicted - measured) / measured < 0.15, (predicted / plan.GiB, measured / plan.GiB)


# Two regimes: the small batch above and a larger one, where activations and logits are the
# larger transient (leaving either of those terms out misses it by 17-27%).
@pytest.mark.parametrize("shape", [(1, 4, 64, 16), (3, 8, 128, 40)])
def test_memory_plan_within_15_percent_of_the_stored_cpu_peaks(shape):
    measured, predicted = _stored_peak(*shape), _predicted(*shape)
    assert abs(predicted - measured) / measured < 0.15, (predicted / plan.GiB, measured / plan.GiB)


def test_lora_memory_plan_within_25_percent_of_the_stored_cpu_peak():
    """LoRA (rank 16) at the larger shape. The peak varies more between machines here (planned
    8.53 GiB; one earlier machine measured 10.78, the stored peak is in
    benchmarks/memory_peaks.json): under
    full fine-tuning part of the transient is covered by gradient memory that is counted as
    persistent but not yet allocated at the peak; under LoRA nothing covers it, so the peak
    depends more on when the allocator reuses memory. The bound is wider to say so; the plan
    stays a guide, not a guarantee, for LoRA."""
    shape = (3, 8, 128, 40, 16)
    measured, predicted = _stored_peak(*shape), _predicted(*shape)
    assert abs(predicted - measured) / measured < 0.25, (predicted / plan.GiB, measured / plan.GiB)


def test_the_stored_peaks_are_the_shapes_the_benchmark_measures():
    import importlib.util
    spec = importlib.util.spec_from_file_location("memory_peaks", STORED_PEAKS.with_suffix(".py"))
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    rows = json.loads(STORED_PEAKS.read_text())["peaks"]
    stored = [(r["prompts"], r["group_size"], r["prompt_len"], r["completion_len"], r["lora_rank"])
              for r in rows]
    assert stored == bench.SHAPES and all(r["peak_gib"] > 0 for r in rows)


def test_memory_plan_terms_respond_to_the_options():
    base = plan.memory_plan(plan.QWEN25_05B, _cfg(), 128, 32)
    assert base["reference model"] == 0 and base["autocast weight copies"] == 0
    with_kl = plan.memory_plan(plan.QWEN25_05B, _cfg(kl_coef=0.04), 128, 32)
    assert with_kl["reference model"] == 4 * plan.QWEN25_05B.n_params
    accum = plan.memory_plan(plan.QWEN25_05B, _cfg(prompts_per_step=4, grad_accum=2), 128, 32)
    whole = plan.memory_plan(plan.QWEN25_05B, _cfg(prompts_per_step=4), 128, 32)
    assert accum["activations"] == pytest.approx(whole["activations"] / 2)
    from course_utils.config import Config
    eight_bit = plan.memory_plan(plan.QWEN25_05B, Config(optimizer="adamw_8bit"), 128, 32)
    assert eight_bit["optimizer state"] == 2 * plan.QWEN25_05B.n_params  # not validated: no GPU here
    lora = plan.memory_plan(plan.QWEN25_05B, _cfg(lora_rank=16, kl_coef=0.04), 128, 32)
    assert lora["gradients"] == 4 * plan.QWEN25_05B.lora_params(16) == 4 * 8_798_208
    assert lora["reference model"] == 0              # the base with adapters off
    assert lora["optimizer state"] < whole["optimizer state"] / 50
    ckpt = plan.memory_plan(plan.QWEN25_05B, _cfg(gradient_checkpointing=True), 128, 32)
    assert ckpt["activations"] < whole["activations"] / 4


def test_time_plan_by_hand():
    cfg = _cfg(prompts_per_step=2, group_size=4, max_new_tokens=16)
    t = plan.time_plan(plan.QWEN25_05B, cfg, prompt_len=100, completion_len=10)
    a, dev = plan.QWEN25_05B, plan.T4
    peak = dev.peak_tflops_fp32 * 1e12 * dev.train_efficiency
    body = a.n_params - a.n_embedding
    train = (6 * body * (2 * 4 * 10 + 2 * 100) + 6 * a.n_embedding * 2 * 4 * 10) / peak
    assert t["training s/step"] == pytest.approx(train)
    decode = max(4 * a.n_params / 320e9, 2 * a.n_params * 8 / peak) + dev.decode_overhead_s
    assert t["generation s/step"] == pytest.approx(2 * a.n_params * 200 / peak + 10 * decode)
    assert "fits" in plan.format_plan(a, cfg, 100, 10)
    # gradient checkpointing: the forward is recomputed (8 FLOPs per weight and token instead of
    # 6) and the prompt is not shared, so it is trained once per completion
    ckpt = _cfg(prompts_per_step=2, group_size=4, max_new_tokens=16, gradient_checkpointing=True)
    t = plan.time_plan(a, ckpt, prompt_len=100, completion_len=10)
    assert t["training s/step"] == pytest.approx(
        (8 * body * (2 * 4 * 10 + 2 * 4 * 100) + 8 * a.n_embedding * 2 * 4 * 10) / peak)


def test_lora_saves_time_too_it_skips_the_frozen_weights_gradient_matmuls():
    """Lesson 7 says LoRA saves about a third of the training FLOPs, not only memory: the
    frozen weights need no weight gradient (one of the three matmuls per weight and token),
    while the forward and the gradient flowing down to lower adapters remain. Counted here on
    two small Qwen2 shapes, one training step each."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from course_utils import models

    def train_flops(model, vocab):
        ids = torch.randint(0, vocab, (4, 32), generator=torch.Generator().manual_seed(0))
        with FlopCounterMode(display=False) as counter:
            model(input_ids=ids).logits.float().pow(2).mean().backward()
        return counter.get_total_flops()

    for vocab, hidden, intermediate in [(256, 64, 128), (1000, 128, 512)]:
        shape = dict(hidden_size=hidden, intermediate_size=intermediate)
        full = train_flops(models.tiny_qwen2(vocab, **shape), vocab)
        lora = train_flops(models.add_lora(models.tiny_qwen2(vocab, **shape), rank=4, alpha=8), vocab)
        # 4 of 6 FLOPs per frozen weight and token, plus the adapters and attention's own matmuls
        assert 0.6 < lora / full < 0.78, (vocab, lora / full)


def test_units_are_what_cuda_reports():
    """The T4 in GiB (2**30 bytes) as CUDA reports it: less than the datasheet's 16 GB (16e9
    bytes, 14.9 GiB) with ECC on; the allocator may reserve the total less what the process
    holds outside it; the reserved peak is the tensors' peak plus the allocator's cache, and the
    process is that plus the outside share."""
    assert plan.GiB == 2 ** 30
    t4 = plan.T4
    assert 14.5 * plan.GiB < t4.total_memory_gib * plan.GiB < 16e9
    assert t4.reservable_bytes == pytest.approx((t4.total_memory_gib - t4.outside_allocator_gib) * plan.GiB)
    cfg = _unchecked(precision="fp16", gradient_checkpointing=True)
    mem = plan.memory_plan(plan.QWEN25_05B, cfg, 128, 32)
    tensors = plan.tensor_bytes(mem)
    assert plan.reserved_bytes(mem) == pytest.approx(tensors * (1 + t4.allocator_cache))
    assert plan.peak_bytes(mem) == pytest.approx(plan.reserved_bytes(mem) + t4.outside_allocator_gib * plan.GiB)
    text = plan.format_plan(plan.QWEN25_05B, cfg, 128, 32)
    assert f"{t4.reservable_bytes / plan.GiB:.2f} GiB for PyTorch's allocator" in text
    assert f"{plan.reserved_bytes(mem) / plan.GiB:6.2f} GiB -> fits" in text
    # the verdict is the reserved peak against the reservable memory, not the tensors against the total
    huge = _unchecked(prompts_per_step=8, group_size=16)
    mem = plan.memory_plan(plan.QWEN25_05B, huge, 185, 64)
    assert plan.reserved_bytes(mem) > t4.reservable_bytes
    assert "DOES NOT FIT" in plan.format_plan(plan.QWEN25_05B, huge, 185, 64)


def test_the_t4_preset_leaves_more_headroom_than_the_plans_error():
    from course_utils.config import PRESETS, Config

    t4 = Config.from_dict(PRESETS["t4"])
    mem = plan.memory_plan(plan.QWEN25_05B, t4, plan.qwen25_prompt_len(t4), t4.max_new_tokens)
    assert plan.reserved_bytes(mem) < 0.85 * plan.T4.reservable_bytes


def test_autocast_keeps_the_checkpointed_residual_stream_in_fp32():
    """With checkpointing, each layer's input is kept: the residual stream, fp32 under autocast
    (4 bytes), while the one recomputed layer's tensors are fp16 (2 bytes)."""
    a = plan.QWEN25_05B
    rows, prompt_len, completion_len = 8, 100, 20
    for precision, layer_bytes in (("fp16", 2), ("fp32", 4)):
        cfg = _unchecked(prompts_per_step=1, group_size=rows, precision=precision,
                         gradient_checkpointing=True)
        prompt_rows = 1 if cfg.shares_prompt_in_training else rows
        tokens = rows * completion_len + prompt_rows * prompt_len
        mem = plan.memory_plan(a, cfg, prompt_len, completion_len)
        assert mem["activations"] == tokens * (4 * a.layers * a.hidden + layer_bytes * a.activation_values_per_token_layer)


def test_decoding_under_autocast_reads_the_fp32_weights_and_their_fp16_copies():
    """Each decoding step under fp16 autocast reads 4P (fp32), writes 2P and reads 2P (the cast):
    8 bytes a parameter; in fp32, 4. One prompt, one completion, bandwidth-bound."""
    a, dev = plan.QWEN25_05B, plan.T4
    for precision, bytes_per_param in (("fp16", 8), ("fp32", 4)):
        cfg = _unchecked(prompts_per_step=1, group_size=1, precision=precision)
        t1 = plan.time_plan(a, cfg, prompt_len=10, completion_len=1)
        t2 = plan.time_plan(a, cfg, prompt_len=10, completion_len=2)
        per_token = t2["generation s/step"] - t1["generation s/step"]
        assert per_token == pytest.approx(bytes_per_param * a.n_params / (dev.bandwidth_gbs * 1e9)
                                          + dev.decode_overhead_s)


def test_prompt_length_counts_qwens_pre_tokenizer_pieces():
    # special tokens, "user", "\n", "Hello", " world", "!", "\n\n", "12" as two digits
    assert plan.pretoken_count("<|im_start|>user\nHello world!\n\n12<|im_end|>") == 9
    from course_utils.config import PRESETS, Config
    from course_utils.data import instruction

    t4 = Config.from_dict(PRESETS["t4"])
    frame = plan.QWEN25_CHAT_HEAD + instruction("", t4.target_chars, 12) + plan.QWEN25_CHAT_TAIL
    assert "You are Qwen" in plan.QWEN25_CHAT_HEAD               # the default system prompt
    assert plan.qwen25_prompt_len(t4) == t4.prompt_tokens + plan.pretoken_count(frame)
    # the frame without the system prompt is shorter by that prompt's pieces
    assert plan.pretoken_count(frame) - plan.pretoken_count(frame.replace(plan.QWEN25_CHAT_HEAD, "<|im_start|>user\n")) > 10
