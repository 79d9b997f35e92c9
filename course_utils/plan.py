"""A memory and time plan for a GRPO run, printed before training starts.

Memory is counted term by term for fine-tuning with fp32 master weights (AdamW), in the
steady state (from the second step on, when the optimizer's moments exist). Persistent:

  weights 4P + grads 4P + AdamW moments 8P (2P with 8-bit AdamW) + fp16/bf16 weight copies made
  by autocast 2P + reference model (only if kl_coef > 0) + runtime overhead,

P the parameter count (under LoRA, gradients, moments and the update's temporary count only the
adapters' parameters, and the KL's reference is the base model with adapters off), plus the larger of two transients: activations + logits during the
forward/backward, or one parameter-sized temporary (4P) during AdamW's update (PyTorch's
multi-tensor AdamW computes sqrt(v) out of place). Activations are what the backward pass keeps for one micro-batch:
about ``11 h + 4 kv + 4 i`` values per token and layer for a Llama/Qwen2 block (two RMSNorms,
q/k/v and their rotary versions, the attention output, the four MLP tensors), or only each
layer's input plus one layer's worth with gradient checkpointing. The logits, kept only for the
completion positions, cost about 16 bytes per (token, vocabulary entry) in fp32: the output and
its tempered copy, both kept for the backward, and two transient tensors of the same size.
``tests/test_plan.py`` checks the total against a peak measured on the CPU.

Time is an estimate from published peaks, with the two assumptions stated in ``T4``:
a fraction of peak FLOP/s reached by training matmuls, and a fixed cost per decoding step for
Python and kernel launches (small models decode far below the bandwidth limit in eager mode).
It cannot be checked without the GPU; treat it as a plan, not a measurement.
"""

from __future__ import annotations

from dataclasses import dataclass

GiB = 1024 ** 3


@dataclass(frozen=True)
class Architecture:
    n_params: int
    hidden: int
    layers: int
    kv_dim: int           # key/value width: kv heads x head dim
    intermediate: int
    vocab: int

    @classmethod
    def from_config(cls, config, n_params: int) -> "Architecture":
        head_dim = getattr(config, "head_dim", None) or config.hidden_size // config.num_attention_heads
        kv_heads = getattr(config, "num_key_value_heads", None) or config.num_attention_heads
        return cls(n_params=n_params, hidden=config.hidden_size, layers=config.num_hidden_layers,
                   kv_dim=kv_heads * head_dim, intermediate=config.intermediate_size,
                   vocab=config.vocab_size)

    @classmethod
    def estimate(cls, config) -> "Architecture":
        """From a Llama/Qwen2-style config alone, before any weight is loaded: the parameter
        count is the embeddings (twice if untied) plus per block q and o (h x h each), k and v
        (h x kv each) and the MLP's three h x i matrices (norms and biases are negligible)."""
        arch = cls.from_config(config, n_params=0)
        blocks = arch.layers * (2 * arch.hidden ** 2 + 2 * arch.hidden * arch.kv_dim
                                + 3 * arch.hidden * arch.intermediate)
        embeddings = arch.n_embedding * (1 if getattr(config, "tie_word_embeddings", True) else 2)
        return cls(**{**arch.__dict__, "n_params": embeddings + blocks})

    @property
    def activation_values_per_token_layer(self) -> int:
        return 11 * self.hidden + 4 * self.kv_dim + 4 * self.intermediate

    @property
    def n_embedding(self) -> int:
        return self.vocab * self.hidden

    def lora_params(self, rank: int) -> int:
        """Adapter parameters for rank ``rank`` on every linear layer of every block: each
        d_in x d_out matrix gains r (d_in + d_out). Per block q, k, v, o, gate, up, down give
        2h + 2(h + kv) + 2h + 3(h + i) = 9h + 2kv + 3i."""
        return rank * self.layers * (9 * self.hidden + 2 * self.kv_dim + 3 * self.intermediate)


# Qwen2.5-0.5B-Instruct (tied embeddings): 494,032,768 parameters.
QWEN25_05B = Architecture(n_params=494_032_768, hidden=896, layers=24, kv_dim=2 * 64,
                          intermediate=4864, vocab=151_936)


# SmolLM2-135M-Instruct (the embedded model, tied embeddings): 134,515,008 parameters.
SMOLLM2_135M = Architecture(n_params=134_515_008, hidden=576, layers=30, kv_dim=3 * 64,
                            intermediate=1536, vocab=49_152)


@dataclass(frozen=True)
class Device:
    name: str
    memory_gib: float           # what a program can allocate
    peak_tflops: float          # dense fp16 tensor-core peak (fp32 peak for fp32 runs below)
    peak_tflops_fp32: float
    bandwidth_gbs: float
    train_efficiency: float     # assumed fraction of peak reached by training matmuls
    decode_overhead_s: float    # assumed fixed cost of one decoding step (launches, Python)


# NVIDIA's T4 datasheet: 65 TFLOP/s fp16 tensor cores, 8.1 TFLOP/s fp32, 320 GB/s, 16 GB
# (about 15 GiB usable under Colab). No bf16, no TF32.
T4 = Device("Tesla T4", memory_gib=15.0, peak_tflops=65.0, peak_tflops_fp32=8.1,
            bandwidth_gbs=320.0, train_efficiency=0.3, decode_overhead_s=0.03)


# Memory a run uses beyond its tensors: on the CPU check about 0.8 GiB (allocator slack); on a
# GPU the CUDA context alone takes several hundred MiB.
RUNTIME_OVERHEAD = 0.75 * GiB
TRANSIENT = ("activations", "logits (completion positions)", "optimizer step temporary")


def memory_plan(arch: Architecture, cfg, prompt_len: int, completion_len: int) -> dict[str, float]:
    """Bytes per component of one training step; ``peak_bytes`` combines them."""
    P = arch.n_params
    # what the optimizer updates: every weight, or under LoRA only the adapters (the frozen
    # base needs no gradient and no moments; activations are still kept, for the gradient
    # that flows through the frozen layers to the adapters below them)
    trained = arch.lora_params(cfg.lora_rank) if getattr(cfg, "lora_rank", 0) else P
    mixed = cfg.precision in ("fp16", "bf16")
    act_bytes = 2 if mixed else 4
    eight_bit = cfg.optimizer == "adamw_8bit"
    prompts = cfg.prompts_per_step // cfg.grad_accum            # per micro-batch
    rows = prompts * cfg.group_size
    prompt_rows = prompts if cfg.shares_prompt_in_training else rows
    tokens = rows * completion_len + prompt_rows * prompt_len
    per_layer = arch.activation_values_per_token_layer
    if cfg.gradient_checkpointing:
        activations = tokens * act_bytes * (arch.layers * arch.hidden + per_layer)
    else:
        activations = tokens * act_bytes * arch.layers * per_layer
    logits_values = rows * (completion_len + 1) * arch.vocab
    logits = logits_values * ((act_bytes if mixed else 0) + 4 + 4 + 8)
    separate_reference = cfg.kl_coef > 0 and trained == P   # LoRA: the base with adapters off
    return {
        "weights (fp32 master)": 4 * (P + (trained if trained != P else 0)),
        "gradients": 4 * trained,
        "optimizer state": (2 if eight_bit else 8) * trained,
        "autocast weight copies": 2 * P if mixed else 0,
        "reference model": ((2 if mixed else 4) * P) if separate_reference else 0,
        "runtime overhead": RUNTIME_OVERHEAD,
        "activations": activations,
        "logits (completion positions)": logits,
        "optimizer step temporary": (1 if eight_bit else 4) * trained,
    }


def peak_bytes(mem: dict[str, float]) -> float:
    """Persistent memory plus the larger transient: forward/backward or the optimizer update."""
    persistent = sum(v for k, v in mem.items() if k not in TRANSIENT)
    return persistent + max(mem["activations"] + mem["logits (completion positions)"],
                            mem["optimizer step temporary"])


def time_plan(arch: Architecture, cfg, prompt_len: int, completion_len: int,
              device: Device = T4) -> dict[str, float]:
    """Seconds per optimizer step (generation and training) and for the whole run."""
    mixed = cfg.precision in ("fp16", "bf16")
    peak = (device.peak_tflops if mixed else device.peak_tflops_fp32) * 1e12 * device.train_efficiency
    B, G = cfg.prompts_per_step, cfg.group_size
    n_body = arch.n_params - arch.n_embedding       # weights every token multiplies through
    completion_tokens = B * G * completion_len
    prompt_tokens = B * prompt_len                   # prefilled once per group when sampling
    trained_prompt_tokens = prompt_tokens if cfg.shares_prompt_in_training else B * G * prompt_len
    # training: 6 FLOPs per weight per token (forward 2, backward 4), the output layer only at
    # completion positions; checkpointing recomputes the forward (8 instead of 6)
    per_weight = 8 if cfg.gradient_checkpointing else 6
    train_flops = per_weight * n_body * (completion_tokens + trained_prompt_tokens) + \
        per_weight * arch.n_embedding * completion_tokens
    if cfg.kl_coef > 0:  # the reference model's forward is not prompt-shared either
        train_flops += 2 * arch.n_params * (completion_tokens + B * G * prompt_len)
    train_s = train_flops / peak
    # generation: a prefill, then one step per new token; each step reads every weight once
    weight_bytes = arch.n_params * (2 if mixed else 4)
    prefill_s = 2 * arch.n_params * prompt_tokens / peak
    step_s = max(weight_bytes / (device.bandwidth_gbs * 1e9), 2 * arch.n_params * B * G / peak)
    generate_s = prefill_s + completion_len * (step_s + device.decode_overhead_s)
    per_step = train_s + generate_s
    return {"generation s/step": generate_s, "training s/step": train_s, "total s/step": per_step,
            "steps": cfg.total_steps, "run hours": per_step * cfg.total_steps / 3600}


def format_plan(arch: Architecture, cfg, prompt_len: int, completion_len: int,
                device: Device = T4) -> str:
    mem = memory_plan(arch, cfg, prompt_len, completion_len)
    total = peak_bytes(mem)
    lines = [f"Memory plan on {device.name} ({device.memory_gib:.1f} GiB usable):"]
    lines += [f"  {name:32s} {value / GiB:6.2f} GiB" for name, value in mem.items() if value]
    verdict = "fits" if total <= device.memory_gib * GiB else "DOES NOT FIT: raise grad_accum " \
        "or enable gradient_checkpointing"
    lines.append(f"  {'peak (persistent + larger transient)':32s} {total / GiB:6.2f} GiB -> {verdict}")
    t = time_plan(arch, cfg, prompt_len, completion_len, device)
    lines.append(f"Time plan: generation {t['generation s/step']:.1f} s + training "
                 f"{t['training s/step']:.1f} s = {t['total s/step']:.1f} s per step; "
                 f"{t['steps']} steps = {t['run hours']:.1f} h (assumes {device.train_efficiency:.0%} "
                 f"of peak FLOP/s and {device.decode_overhead_s * 1000:.0f} ms per decoding step)")
    return "\n".join(lines)


# A run is refused only when the plan exceeds the device's whole memory by this factor: the plan
# is an estimate (tests/test_plan.py bounds its error), and a run near the limit is the user's
# call to try, but one planned at several times the memory cannot fit and would only fail late.
CERTAINLY_TOO_BIG = 1.25


def check_fits(cfg, arch: Architecture | None, memory_bytes: int | None, device_name: str) -> None:
    """ConfigError, before any model loads, if ``cfg`` certainly cannot fit in ``memory_bytes``
    (nothing is checked when the architecture or the memory is unknown)."""
    if arch is None or not memory_bytes:
        return
    peak = peak_bytes(memory_plan(arch, cfg, prompt_len=cfg.prompt_tokens,
                                  completion_len=cfg.max_new_tokens))
    if peak > CERTAINLY_TOO_BIG * memory_bytes:
        from .config import ConfigError

        raise ConfigError(
            f"group_size {cfg.group_size} x prompts_per_step {cfg.prompts_per_step} / grad_accum "
            f"{cfg.grad_accum} with max_new_tokens {cfg.max_new_tokens} needs about "
            f"{peak / GiB:.0f} GiB (course_utils.plan), more than {device_name}'s "
            f"{memory_bytes / GiB:.0f} GiB: lower group_size or prompts_per_step, raise grad_accum, "
            f"or shorten max_new_tokens")
