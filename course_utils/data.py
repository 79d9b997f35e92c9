"""Prompts: text snippets cut to N tokens, each paired with the rule its completion must meet.

Text comes from openwebtext (streamed from a parquet mirror) or, offline, from the short
paragraphs in ``assets/snippets.txt`` written for this course. The train/held-out split is by a
hash of the snippet's text, so it is the same on every machine and in every order: a held-out
snippet is never trained on.
"""

from __future__ import annotations

import hashlib
import os
import random
from dataclasses import dataclass
from pathlib import Path

SNIPPETS_FILE = Path(__file__).parent / "assets" / "snippets.txt"
HELD_OUT_PERCENT = 20  # share of snippets reserved for evaluation
DATASET_ENV = "COURSE_DATASET"
# Parquet mirrors tried in order. The original openwebtext repository is a loading script,
# which `datasets` >= 4 refuses; the parquet conversion branch and mirrors load by streaming.
OPENWEBTEXT_SOURCES: list[tuple[str, str | None]] = [
    ("Skylion007/openwebtext", None),
    ("Skylion007/openwebtext", "refs/convert/parquet"),
    ("vietgpt/openwebtext_en", None),
]


class DataUnavailable(RuntimeError):
    """No prompt source could be read; the message names the override to use."""


@dataclass(frozen=True)
class Prompt:
    text: str               # what the model sees (chat template applied for prompt_style="chat")
    snippet: str            # the text being continued
    target_chars: int
    target_digit_sum: int


def is_held_out(snippet: str) -> bool:
    """Deterministic split: a stable hash of the text, not Python's salted ``hash``."""
    digest = hashlib.sha1(snippet.strip().encode("utf-8")).digest()
    return int.from_bytes(digest[:4], "big") % 100 < HELD_OUT_PERCENT


def offline_snippets() -> list[str]:
    blocks = SNIPPETS_FILE.read_text(encoding="utf-8").split("\n\n")
    lines = (" ".join(line for line in block.splitlines() if not line.startswith("#")).strip()
             for block in blocks)
    return [s for s in lines if s]


def openwebtext_snippets(count: int, held_out: bool, dataset: str | None = None) -> list[str]:
    """The first ``count`` documents of one split, streamed (nothing is downloaded in full)."""
    dataset = dataset or os.environ.get(DATASET_ENV)
    sources = [(dataset, None)] if dataset else OPENWEBTEXT_SOURCES
    errors = []
    for repo, revision in sources:
        try:
            from datasets import load_dataset

            stream = load_dataset(repo, split="train", streaming=True, revision=revision)
            out = []
            for row in stream:
                text = row["text"].strip()
                if text and is_held_out(text) == held_out:
                    out.append(text)
                    if len(out) == count:
                        return out
            errors.append(f"{repo}: only {len(out)} documents in this split")
        except Exception as err:  # any failure means: try the next source
            errors.append(f"{repo}{'@' + revision if revision else ''}: "
                          f"{type(err).__name__}: {str(err)[:160]}")
    raise DataUnavailable(
        "could not read openwebtext prompts from " + "; ".join(errors) +
        f". Fix: pass dataset=<hub id of a parquet dataset with a 'text' column> (--dataset, or "
        f"the {DATASET_ENV} environment variable), or use prompt_source='offline' for the "
        "built-in snippets.")


def chop(tokenizer, text: str, n_tokens: int) -> str:
    """The text of the first ``n_tokens`` tokens of ``text``."""
    ids = tokenizer(text, add_special_tokens=False)["input_ids"][:n_tokens]
    return tokenizer.decode(ids, skip_special_tokens=True).strip()


def instruction(snippet: str, target_chars: int, target_digit_sum: int) -> str:
    return (f"Continue this text in exactly {target_chars} characters (spaces count), using digits "
            f"that add up to {target_digit_sum}. Reply with the continuation only.\n\n{snippet}")


def build_prompt(tokenizer, snippet: str, target_chars: int, target_digit_sum: int,
                 style: str) -> Prompt:
    """'chat': the rule stated in a user turn of the model's chat template. 'raw': the snippet
    alone, for base models; the rule is then the config's fixed one."""
    if style == "chat":
        messages = [{"role": "user", "content": instruction(snippet, target_chars, target_digit_sum)}]
        text = tokenizer.apply_chat_template(messages, tokenize=False, add_generation_prompt=True)
    elif style == "raw":
        text = snippet
    else:
        raise ValueError(f"prompt style must be 'chat' or 'raw', got {style!r}")
    return Prompt(text=text, snippet=snippet, target_chars=target_chars,
                  target_digit_sum=target_digit_sum)


def make_prompts(cfg, tokenizer, held_out: bool) -> list[Prompt]:
    """The run's training (or held-out) prompts: snippets cycled, each with its own target
    digit sum drawn from [digit_sum_min, digit_sum_max] by a seeded generator."""
    count = cfg.eval_prompts if held_out else cfg.train_prompts
    if cfg.prompt_source == "offline":
        snippets = [s for s in offline_snippets() if is_held_out(s) == held_out]
    else:
        snippets = openwebtext_snippets(count, held_out, cfg.dataset)
    snippets = [chop(tokenizer, s, cfg.prompt_tokens) for s in snippets]
    rng = random.Random(f"{cfg.seed}-{'held-out' if held_out else 'train'}")
    prompts = []
    for i in range(count):
        digit_target = rng.randint(cfg.digit_sum_min, cfg.digit_sum_max)
        prompts.append(build_prompt(tokenizer, snippets[i % len(snippets)], cfg.target_chars,
                                    digit_target, cfg.prompt_style))
    return prompts
