"""A memory and time plan for a GRPO run, printed before training starts.

Memory is counted term by term for fine-tuning with fp32 master weights (AdamW), in the
steady state (from the second step on, when the optimizer's moments exist). Persistent:

  weights 4P + grads 4P + AdamW moments 8P (2P with 8-bit AdamW) + fp16/bf16 weight copies made
  by autocast 2P + reference model (only if kl_coef > 0) + what the process holds outside
  PyTorch's allocator (on a GPU the CUDA context and library workspaces) + the allocator's cache
  (memory reserved but not allocated: a fraction of the tensors' peak),

P the parameter count (under LoRA, gradients, moments and the update's temporary count only the
adapters' parameters, and the KL's reference is the base model with adapters off), plus the larger of two transients: activations + logits during the
forward/backward, or one parameter-sized temporary (4P) during AdamW's update (PyTorch's
multi-tensor AdamW computes sqrt(v) out of place). Activations are what the backward pass keeps for one micro-batch:
about ``11 h + 4 kv + 4 i`` values per token and layer for a Llama/Qwen2 block (two RMSNorms,
q/k/v and their rotary versions, the attention output, the four MLP tensors), or only each
layer's input plus one layer's worth with gradient checkpointing (under autocast the layer
inputs are the fp32 residual stream: 4 bytes each, not 2). The logits, kept only for the
completion positions, cost about 16 bytes per (token, vocabulary entry) in fp32: the output and
its tempered copy, both kept for the backward, and two transient tensors of the same size.
``tests/test_plan.py`` checks the total against peaks measured on the CPU (one live, the larger
ones stored by ``benchmarks/memory_peaks.py``).

Units: memory is in GiB (2**30 bytes), the unit of ``torch.cuda`` and of its out-of-memory
messages. The comparison on a GPU is with ``torch.cuda.max_memory_reserved`` (the allocator's
peak, its cache included), which ``reserved_bytes`` models; ``max_memory_allocated`` leaves the
cache out and the context is outside both. ``peak_bytes`` is the whole process and is what must
fit in the device's total capacity.

Time is an estimate from published peaks, with the two assumptions stated in ``T4``:
a fraction of peak FLOP/s reached by training matmuls, and a fixed cost per decoding step for
Python and kernel launches (small models decode far below the bandwidth limit in eager mode).
A decoding step reads every weight: under autocast the sampler is the fp32 policy, so each step
reads the fp32 weights (4P), writes their fp16 copies (2P) and reads those again (2P).
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
    total_memory_gib: float     # what CUDA reports: get_device_properties(0).total_memory / GiB
    outside_allocator_gib: float  # held by the process outside PyTorch's allocator (CUDA context, libraries)
    allocator_cache: float      # reserved but unallocated memory, as a fraction of the tensors' peak
    peak_tflops: float          # dense fp16 tensor-core peak (fp32 peak for fp32 runs below)
    peak_tflops_fp32: float
    bandwidth_gbs: float
    train_efficiency: float     # assumed fraction of peak reached by training matmuls
    decode_overhead_s: float    # assumed fixed cost of one decoding step (launches, Python)

    @property
    def reservable_bytes(self) -> float:
        """What ``torch.cuda.max_memory_reserved`` can reach: the total less what the process
        holds outside the allocator."""
        return (self.total_memory_gib - self.outside_allocator_gib) * GiB


# NVIDIA's T4 datasheet: 65 TFLOP/s fp16 tensor cores, 8.1 TFLOP/s fp32, 320 GB/s, 16 GB. CUDA
# reports less, with ECC on as on Colab: "GPU 0 has a total capacity of 14.75 GiB" (a Colab
# T4's out-of-memory message, yifanlu0227/MIT-6.5940 issue 1; 14.74 GiB in zai-org/CogVideo
# issue 741). Memory held outside PyTorch's allocator in such messages ranges from 0.13 GiB
# (Zheng-Chong/CatVTON issue 133) to 1.0 GiB (the MIT-6.5940 one: 14.20 GiB in use, 13.20 GiB
# reserved by PyTorch); the plan takes the larger. The allocator's cache is an assumption (10%
# of the tensors' peak; out-of-memory messages show less, but PyTorch empties its cache before
# it raises): benchmarks/gpu_check.py measures it. No bf16, no TF32.
T4 = Device("Tesla T4", total_memory_gib=14.75, outside_allocator_gib=1.0, allocator_cache=0.10,
            peak_tflops=65.0, peak_tflops_fp32=8.1, bandwidth_gbs=320.0, train_efficiency=0.3,
            decode_overhead_s=0.03)

# The CPU memory check (tests/memory_probe.py) measures resident memory: the interpreter, torch
# and the allocator's slack come to about 0.75 GiB beyond the tensors there. Memory and
# only these overheads of this Device are used (in the probe's test and in ``check_fits``).
CPU_PROBE = Device("CPU (resident memory)", total_memory_gib=float("inf"), outside_allocator_gib=0.75,
                   allocator_cache=0.0, peak_tflops=0.0, peak_tflops_fp32=0.0, bandwidth_gbs=0.0,
                   train_efficiency=0.0, decode_overhead_s=0.0)

# Qwen2.5-Instruct's chat template around a user turn, with the system prompt the template
# inserts when the messages have none (the course's prompts have none).
QWEN25_CHAT_HEAD = ("<|im_start|>system\nYou are Qwen, created by Alibaba Cloud. You are a helpful "
                    "assistant.<|im_end|>\n<|im_start|>user\n")
QWEN25_CHAT_TAIL = "<|im_end|>\n<|im_start|>assistant\n"
QWEN25_SPECIAL = ("<|im_start|>", "<|im_end|>")


def pretoken_count(text: str) -> int:
    """Pieces of ``text`` under Qwen2's pre-tokenizer (its regular expression, read from
    transformers), each special token one piece. Byte-pair encoding never merges across pieces,
    so this is a lower bound on the token count, and equal to it when every piece is one token of
    the vocabulary (common English words in a 151,646-token vocabulary are)."""
    import regex
    from transformers.models.qwen2.tokenization_qwen2 import PRETOKENIZE_REGEX

    pieces = regex.split("(" + "|".join(regex.escape(t) for t in QWEN25_SPECIAL) + ")", text)
    return sum(1 if p in QWEN25_SPECIAL else len(regex.findall(PRETOKENIZE_REGEX, p))
               for p in pieces if p)


def qwen25_prompt_len(cfg) -> int:
    """The prompt length a Qwen2.5 run trains on: ``cfg.prompt_tokens`` of snippet (cut by the
    tokenizer itself) plus the chat template and the instruction, at least ``pretoken_count``
    tokens (the tokenizer files are not available offline here; the T4 run prints the real
    length). The widest instruction: two-digit sum, the config's target length."""
    from .data import instruction

    frame = QWEN25_CHAT_HEAD + instruction("", cfg.target_chars, max(cfg.digit_sum_max, 10)) + QWEN25_CHAT_TAIL
    return cfg.prompt_tokens + pretoken_count(frame)


TRANSIENT = ("activations", "logits (completion positions)", "optimizer step temporary")
OUTSIDE = "outside the allocator (context, libraries)"
CACHE = "allocator cache (reserved, unallocated)"


def memory_plan(arch: Architecture, cfg, prompt_len: int, completion_len: int,
                device: Device = T4) -> dict[str, float]:
    """Bytes per component of one training step on ``device``; ``peak_bytes`` combines them."""
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
    if cfg.gradient_checkpointing:   # each layer's input: the residual stream, fp32 under autocast
        activations = tokens * (4 * arch.layers * arch.hidden + act_bytes * per_layer)
    else:
        activations = tokens * act_bytes * arch.layers * per_layer
    logits_values = rows * (completion_len + 1) * arch.vocab
    logits = logits_values * ((act_bytes if mixed else 0) + 4 + 4 + 8)
    separate_reference = cfg.kl_coef > 0 and trained == P   # LoRA: the base with adapters off
    mem = {
        "weights (fp32 master)": 4 * (P + (trained if trained != P else 0)),
        "gradients": 4 * trained,
        "optimizer state": (2 if eight_bit else 8) * trained,
        "autocast weight copies": 2 * P if mixed else 0,
        "reference model": ((2 if mixed else 4) * P) if separate_reference else 0,
        "activations": activations,
        "logits (completion positions)": logits,
        "optimizer step temporary": (1 if eight_bit else 4) * trained,
    }
    mem[CACHE] = device.allocator_cache * tensor_bytes(mem)
    mem[OUTSIDE] = device.outside_allocator_gib * GiB
    return mem


def tensor_bytes(mem: dict[str, float]) -> float:
    """The tensors' peak (what ``torch.cuda.max_memory_allocated`` reports): persistent tensors
    plus the larger transient, the forward/backward or the optimizer update."""
    persistent = sum(v for k, v in mem.items() if k not in TRANSIENT and k not in (CACHE, OUTSIDE))
    return persistent + max(mem["activations"] + mem["logits (completion positions)"],
                            mem["optimizer step temporary"])


def reserved_bytes(mem: dict[str, float]) -> float:
    """The allocator's peak, its cache included (what ``torch.cuda.max_memory_reserved`` reports)."""
    return tensor_bytes(mem) + mem.get(CACHE, 0.0)


def peak_bytes(mem: dict[str, float]) -> float:
    """The whole process: the allocator's peak plus what is held outside it. This must fit in the
    device's total memory (equivalently, ``reserved_bytes`` in ``Device.reservable_bytes``)."""
    return reserved_bytes(mem) + mem.get(OUTSIDE, 0.0)


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
    # generation: a prefill, then one step per new token; each step reads every weight once, and
    # under autocast the fp32 weights are cast again at every step (read 4P, write and read 2P)
    weight_bytes = arch.n_params * (8 if mixed else 4)
    prefill_s = 2 * arch.n_params * prompt_tokens / peak
    step_s = max(weight_bytes / (device.bandwidth_gbs * 1e9), 2 * arch.n_params * B * G / peak)
    generate_s = prefill_s + completion_len * (step_s + device.decode_overhead_s)
    per_step = train_s + generate_s
    return {"generation s/step": generate_s, "training s/step": train_s, "total s/step": per_step,
            "steps": cfg.total_steps, "run hours": per_step * cfg.total_steps / 3600}


def format_plan(arch: Architecture, cfg, prompt_len: int, completion_len: int,
                device: Device = T4) -> str:
    mem = memory_plan(arch, cfg, prompt_len, completion_len, device)
    reserved = reserved_bytes(mem)
    lines = [f"Memory plan on {device.name} ({device.total_memory_gib:.2f} GiB total as CUDA reports it, "
             f"{device.reservable_bytes / GiB:.2f} GiB for PyTorch's allocator):"]
    lines += [f"  {name:42s} {value / GiB:6.2f} GiB" for name, value in mem.items() if value]
    verdict = "fits" if reserved <= device.reservable_bytes else "DOES NOT FIT: raise grad_accum " \
        "or enable gradient_checkpointing"
    lines.append(f"  {'tensors at peak (max_memory_allocated)':42s} {tensor_bytes(mem) / GiB:6.2f} GiB")
    lines.append(f"  {'allocator at peak (max_memory_reserved)':42s} {reserved / GiB:6.2f} GiB -> {verdict}, "
                 f"{1 - reserved / device.reservable_bytes:.0%} headroom")
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
    device = T4 if device_name != "this machine's RAM" else CPU_PROBE   # only the overheads matter here
    peak = peak_bytes(memory_plan(arch, cfg, prompt_len=cfg.prompt_tokens,
                                  completion_len=cfg.max_new_tokens, device=device))
    if peak > CERTAINLY_TOO_BIG * memory_bytes:
        from .config import ConfigError

        raise ConfigError(
            f"group_size {cfg.group_size} x prompts_per_step {cfg.prompts_per_step} / grad_accum "
            f"{cfg.grad_accum} with max_new_tokens {cfg.max_new_tokens} needs about "
            f"{peak / GiB:.0f} GiB (course_utils.plan), more than {device_name}'s "
            f"{memory_bytes / GiB:.0f} GiB: lower group_size or prompts_per_step, raise grad_accum, "
            f"or shorten max_new_tokens")
