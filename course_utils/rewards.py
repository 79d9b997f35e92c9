"""The rule checker: the only judge of a completion in this course.

The rule, exactly
-----------------
A completion is judged on its *text*: the completion's tokens decoded with special tokens
skipped (so an end-of-sequence token such as ``<|im_end|>`` is not text), then stripped of
leading and trailing whitespace (``str.strip``). On that text:

* **characters** are Python ``str`` characters (Unicode code points): ``len(text)``.
  "é" is one character, so is "7"; a space inside the text counts.
* **digits** are the ASCII characters ``0``-``9`` only. ``str.isdigit`` also accepts
  superscripts and other scripts' digits ("²", "٣") that ``int`` rejects or that a reader
  would not call digits; they count as ordinary characters here, never as digits.
* **digit sum**: the sum of the values of those ASCII digits ("a1b22" -> 5; no digits -> 0).
* the **length constraint** passes when ``len(text) == target_chars``;
  the **digit constraint** passes when ``digit_sum == target_digit_sum``.

Where the targets come from: for an instruction-tuned model each prompt states its own
``target_chars`` and ``target_digit_sum`` in the instruction (see ``data.build_prompt``); for a
base model such as gpt2, which cannot read instructions, both are fixed by the config.

Six rewards are provided (and two one-constraint metrics, ``length_reward`` and
``digit_sum_reward``), all with TRL's reward-function signature
``f(prompts, completions, **kwargs) -> list[float]``; the targets arrive as per-completion
lists in ``kwargs``, exactly as TRL passes extra dataset columns:

* ``binary_reward``: 1.0 when both constraints pass, else 0.0 (the recipe's reward);
* ``shaped_reward``: partial credit, the mean of a length credit and a digit credit, each 1 when
  met exactly and falling smoothly towards 0 as the miss grows, never reaching it (see
  ``shaped_score``), so a group of different misses always has some spread to learn from.
  It equals 1.0 exactly when ``binary_reward`` does.
* ``sharp_reward``: 2/3 of the shaped score plus 1/3 of the binary one, so a pass pays clearly
  more than any near miss (see ``sharp_score``, and lesson 7, section 6, for why).
* ``graded_reward``: partial credit counted in whole units of the digit sum (none without a
  digit) and half in whole characters (``graded_score``);
* ``counted_reward``: ``graded_reward`` with the digit credit halved for each digit a reply is
  short of the fewest that can reach the target (``counted_score``, lesson 7, section 6.4).
* ``gated_reward``: ``counted_reward``'s digit credit times the mean of 1 and its length credit,
  so against a positive target a reply without digits earns nothing and the length pays in
  proportion to the digits (``gated_score``, lesson 7, section 6.8).

Every partial credit is exactly 1.0 when ``binary_reward`` is, and below 1 otherwise.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import Any, Sequence

ASCII_DIGITS = "0123456789"


def _content_text(content: Any) -> str:
    """A chat message's content as text: a string; None (a message with no text, such as a tool
    call) is empty; a list of parts (``{"type": "text", "text": ...}``) is its text parts joined."""
    if content is None:
        return ""
    if isinstance(content, str):
        return content
    if isinstance(content, (list, tuple)):
        parts = []
        for part in content:
            if isinstance(part, str):
                parts.append(part)
            elif isinstance(part, dict) and part.get("type", "text") == "text":
                parts.append(_content_text(part.get("text")))
            elif not isinstance(part, dict):
                raise TypeError(f"a message's content parts must be str or dicts, got "
                                f"{type(part).__name__}: {part!r:.80}")
        return "".join(parts)
    raise TypeError(f"a message's content must be a str, a list of parts or None, got "
                    f"{type(content).__name__}: {content!r:.80}")


def _message_content(message: dict) -> Any:
    """A chat message's ``content``; a dict without that key (``{"text": ...}``, a typo) is not a
    message, and scoring it as an empty reply would hide the mistake behind a reward of 0."""
    if "content" not in message:
        raise TypeError(f"a chat message must have a 'content' key (as in {{'role': 'assistant', "
                        f"'content': ...}}), got keys {sorted(map(str, message))}")
    return message["content"]


def completion_text(completion: Any) -> str:
    """The text a rule is applied to: str as given, or the last message of a chat completion.

    TRL passes plain strings for standard datasets and lists of ``{"role", "content"}`` dicts
    for conversational ones; both are accepted, and a message's content may be a string, a list
    of text parts, or None (no text). Surrounding whitespace is stripped.
    """
    if isinstance(completion, str):
        text = completion
    elif isinstance(completion, (list, tuple)) and completion and isinstance(completion[-1], dict):
        text = _content_text(_message_content(completion[-1]))
    elif isinstance(completion, dict):
        text = _content_text(_message_content(completion))
    else:
        raise TypeError(f"a completion must be a str or a list of chat messages, got "
                        f"{type(completion).__name__}: {completion!r:.80}")
    return text.strip()


def digit_sum(text: str) -> int:
    """Sum of the ASCII digits 0-9 in ``text``; other Unicode digits are not digits here."""
    return sum(ord(c) - ord("0") for c in text if c in ASCII_DIGITS)


@dataclass(frozen=True)
class RuleCheck:
    """Everything the checker measured about one completion."""
    n_chars: int
    digit_sum: int
    length_ok: bool
    digits_ok: bool
    n_digits: int = 0   # how many ASCII digits the text holds (zeros included)

    @property
    def passed(self) -> bool:
        return self.length_ok and self.digits_ok


def check(completion: Any, target_chars: int, target_digit_sum: int) -> RuleCheck:
    """Apply the rule to one completion (see the module docstring for the exact definition)."""
    text = completion_text(completion)
    n, s = len(text), digit_sum(text)
    return RuleCheck(n_chars=n, digit_sum=s, length_ok=n == target_chars,
                     digits_ok=s == target_digit_sum,
                     n_digits=sum(c in ASCII_DIGITS for c in text))


def shaped_score(result: RuleCheck, target_chars: int, target_digit_sum: int) -> float:
    """Partial credit in (0, 1]: 1/2 * length credit + 1/2 * digit credit, where

    length credit = 1 / (1 + |n_chars - target_chars| / max(target_chars, 1))
    digit credit  = 1 / (1 + |digit_sum - target_digit_sum| / max(target_digit_sum, 1))

    A miss by the whole target halves a credit; a miss ten times the target leaves 1/11. Each is
    1 only when its constraint passes, so the score is 1 only when both do. Unlike a linear
    ramp clipped at 0, a completion three times too long still scores better than one five
    times too long, so early, very long completions still give a learning signal.
    """
    length_credit = 1.0 / (1.0 + abs(result.n_chars - target_chars) / max(target_chars, 1))
    digit_credit = 1.0 / (1.0 + abs(result.digit_sum - target_digit_sum) / max(target_digit_sum, 1))
    return 0.5 * length_credit + 0.5 * digit_credit


def _targets(name: str, kwargs: dict, n: int) -> list[int]:
    """Per-completion targets from TRL-style kwargs (a list, one entry per completion): whole
    numbers >= 0 (Python or numpy integers, or floats with no fraction)."""
    if name not in kwargs:
        raise KeyError(f"reward needs the '{name}' column (one value per completion); got only "
                       f"{sorted(kwargs)}")
    values = kwargs[name]
    if getattr(values, "ndim", None) == 0 and hasattr(values, "item"):
        values = values.item()   # a 0-d numpy array or torch tensor is one number
    elif hasattr(values, "tolist") and not isinstance(values, (str, bytes)):
        values = values.tolist()   # a numpy array or tensor column: its Python numbers
    if isinstance(values, numbers.Number):  # convenience: one target for every completion
        values = [values] * n
    if not isinstance(values, (list, tuple)):
        # a dict would be read as its keys, a generator has no length, None is not a column
        raise TypeError(f"'{name}' must be a list with one target per completion, got "
                        f"{type(values).__name__}")
    if len(values) != n:
        raise ValueError(f"'{name}' has {len(values)} values for {n} completions")
    out = []
    for v in values:
        whole = isinstance(v, numbers.Integral) or (isinstance(v, numbers.Real) and float(v).is_integer())
        if isinstance(v, bool) or not whole or v < 0:
            raise ValueError(f"'{name}' must hold whole numbers >= 0, got {v!r}")
        out.append(int(v))
    return out


def _completions(completions: Any) -> Sequence[Any]:
    """The completions argument: a list (one entry per completion), never a bare string, which
    would otherwise be scored one character at a time."""
    if isinstance(completions, (str, bytes)):
        raise TypeError("completions must be a list of completions, got a single string; wrap "
                        "it in a list")
    if not isinstance(completions, (list, tuple)):
        # a bare message dict would be scored key by key; a generator has no length
        raise TypeError(f"completions must be a list of completions (one str or chat message "
                        f"list each), got {type(completions).__name__}; wrap a single "
                        f"completion in a list")
    return completions


def check_all(completions: Sequence[Any], **kwargs) -> list[RuleCheck]:
    """``check`` on every completion, targets taken from kwargs as TRL passes them."""
    completions = _completions(completions)
    n = len(completions)
    chars, sums = _targets("target_chars", kwargs, n), _targets("target_digit_sum", kwargs, n)
    return [check(c, L, S) for c, L, S in zip(completions, chars, sums)]


def _scored(score, completions: Sequence[Any], kwargs: dict) -> list[float]:
    """``score(check(c, L, S), L, S)`` for every completion c, targets taken from kwargs."""
    completions = _completions(completions)
    n = len(completions)
    chars, sums = _targets("target_chars", kwargs, n), _targets("target_digit_sum", kwargs, n)
    return [score(check(c, L, S), L, S) for c, L, S in zip(completions, chars, sums)]


def binary_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """The recipe's reward: 1.0 if the length and digit-sum constraints both pass, else 0.0."""
    return [float(r.passed) for r in check_all(completions, **kwargs)]


def shaped_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """Partial-credit reward in [0, 1] (see ``shaped_score``); 1.0 exactly when both pass."""
    return _scored(shaped_score, completions, kwargs)


def length_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """1.0 if the length constraint alone passes (useful as a TRL metric or a curriculum)."""
    return [float(r.length_ok) for r in check_all(completions, **kwargs)]


def digit_sum_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """1.0 if the digit-sum constraint alone passes."""
    return [float(r.digits_ok) for r in check_all(completions, **kwargs)]


def sharp_score(result: RuleCheck, target_chars: int, target_digit_sum: int) -> float:
    """Partial credit in (0, 1] that pays a pass clearly more than any near miss:

    sharp = 2/3 * shaped_score + 1/3 * (1 if both constraints pass else 0)

    Before any completion passes, this is ``shaped_score`` times 2/3, and GRPO's group
    standardization removes a common factor: the advantages, and so the whole early run, are
    those of the shaped reward, which quickly teaches short answers near the target. Once
    passes turn up, each one earns a third of the whole score more than the best near miss, a
    large advantage inside its group. With ``shaped_score`` alone, a template two characters
    short keeps 0.97 of the score, and the 0.03 it loses against a pass is small next to the
    spread of the digit credits in a group, so the policy settles two characters short
    (lesson 7's reward-hacking run).

    Designs that failed in the course's runs, and why (lesson 7, section 6): a bonus for the
    exact length alone made the policy lock onto the first 32-character sentence it found,
    whatever its digit sum; a bonus for the exact digit sum made writing the digit alone the
    easiest thing to learn. The score is 1 exactly when ``binary_reward`` is 1.
    """
    return 2.0 / 3.0 * shaped_score(result, target_chars, target_digit_sum) + \
        1.0 / 3.0 * float(result.passed)


def sharp_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """Partial credit that pays an exact hit clearly more than a near miss (``sharp_score``)."""
    return _scored(sharp_score, completions, kwargs)


def graded_score(result: RuleCheck, target_chars: int, target_digit_sum: int) -> float:
    """Partial credit in [0, 1] whose digit part counts whole units of the digit sum:

    graded = 1/2 * length credit + 1/2 * digit credit, where, with m = |n_chars - target_chars|,

    length credit = 1/2 / (1 + m / target_chars) + 1/2 / (1 + m)

    (``shaped_score``'s relative credit, which still ranks very long replies, averaged with one
    in whole characters, so the last few characters are worth as much as the last few units of
    the digit sum; with the relative credit alone a reply one character short of 32 keeps 97%
    of its length credit, and a policy learns the digits and stops a few characters off), and

    digit credit = 0                          if the digits add up to 0 (none, or only zeros)
                                              and S > 0,
                   1 / (1 + |digit_sum - S|)  otherwise.

    Why not ``shaped_score``'s relative digit credit: against S = 12 it pays a reply with no
    digit 1/2 and the one-digit reply "8" 3/4, so a policy that copies one digit into a
    template has earned most of the credit and two-digit targets look nearly solved. Counted in
    whole units, "8" earns 1/5, "9" 1/4 and any digits that add up to 12 earn 1: each unit
    closer to the target is worth more than the unit before it, and the last one most. A reply without digits
    earns no digit credit, so it is never a safe harbour. The score is 1 exactly when
    ``binary_reward`` is 1.
    """
    return 0.5 * _graded_length_credit(result, target_chars) + \
        0.5 * _unit_digit_credit(result, target_digit_sum)


def _graded_length_credit(result: RuleCheck, target_chars: int) -> float:
    # half relative (the credit of shaped_score), half in whole characters: against 32
    # characters, one character short now loses a quarter of the length credit, not 3%
    miss = abs(result.n_chars - target_chars)
    return 0.5 / (1.0 + miss / max(target_chars, 1)) + 0.5 / (1.0 + miss)


def _unit_digit_credit(result: RuleCheck, target_digit_sum: int) -> float:
    # 1 / (1 + units missed); nothing for a reply whose digits add up to 0 unless S is 0
    counts = result.digit_sum > 0 or target_digit_sum == 0
    return 1.0 / (1.0 + abs(result.digit_sum - target_digit_sum)) if counts else 0.0


def graded_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """Partial credit in whole units of the digit sum, none without a digit (``graded_score``)."""
    return _scored(graded_score, completions, kwargs)


def digits_needed(target_digit_sum: int) -> int:
    """The fewest digits that can add up to the target: each adds at most 9."""
    return -(-target_digit_sum // 9)


def counted_score(result: RuleCheck, target_chars: int, target_digit_sum: int) -> float:
    """``graded_score`` whose digit credit also knows how many digits the target needs:

    counted = 1/2 * length credit + 1/2 * digit credit * 2^-(digits short),

    with the length credit and digit credit of ``graded_score``, and digits short =
    max(0, digits_needed(S) - n_digits), digits_needed(S) = ceil(S / 9). Why: against S = 10 to
    12 a one-digit reply can never pass (9 is the most one digit adds), yet ``graded_score``
    pays "9" more digit credit than most pairs of digits (against S = 10 a credit of 1/2), so a
    policy that writes one digit into a template keeps its template on every target. Halved
    for the missing digit, "9" earns 1/4 against S = 10, while any two digits within one unit
    of 10 earn at least 1/2: the credit points towards writing the second digit, which the base
    model does now and then. Digits that add up to S are never short (fewer than ceil(S/9)
    digits cannot reach S), so the score is 1 exactly when ``binary_reward`` is 1.
    """
    return 0.5 * _graded_length_credit(result, target_chars) + \
        0.5 * _counted_digit_credit(result, target_digit_sum)


def _counted_digit_credit(result: RuleCheck, target_digit_sum: int) -> float:
    # the unit digit credit, halved per digit too few to reach the target
    short = max(0, digits_needed(target_digit_sum) - result.n_digits)
    return _unit_digit_credit(result, target_digit_sum) * 0.5 ** short


def counted_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """``graded_reward`` with the digit credit halved per digit too few to reach the target
    (``counted_score``)."""
    return _scored(counted_score, completions, kwargs)


def gated_score(result: RuleCheck, target_chars: int, target_digit_sum: int) -> float:
    """``counted_score``'s digit credit times the mean of 1 and its length credit, so the digits
    come first:

    gated = D * (1/2 + 1/2 * length credit),   D = digit credit * 2^-(digits short),

    with the credits of ``counted_score``. Why: the counted credit pays the length half on its
    own, so a policy can climb it with no digit at all, and one run of lesson 7, section 6.7 did,
    ending on one 32-character sentence without a digit for every prompt. Gated, a reply whose
    digits add up to 0 (none, or only zeros) earns nothing against a positive target, and the
    length pays in proportion to D. Among replies whose digits are right the length still
    ranks them, in (1/2, 1]. gated - counted = (length credit / 2) * (D - 1) <= 0, so gated is
    never above counted, and it is 1 exactly when ``binary_reward`` is: D and the length credit
    are 1 only when their constraints pass.
    """
    return _counted_digit_credit(result, target_digit_sum) * \
        (0.5 + 0.5 * _graded_length_credit(result, target_chars))


def gated_reward(prompts: Sequence[Any], completions: Sequence[Any], **kwargs) -> list[float]:
    """``counted_reward``'s digit credit times the mean of 1 and its length credit: nothing
    without digits against a positive target (``gated_score``)."""
    return _scored(gated_score, completions, kwargs)


REWARDS = {"binary": binary_reward, "shaped": shaped_reward, "sharp": sharp_reward,
           "graded": graded_reward, "counted": counted_reward, "gated": gated_reward}


def get_reward_fn(name: str):
    if name not in REWARDS:
        raise ValueError(f"unknown reward {name!r}; choose one of {', '.join(REWARDS)}")
    return REWARDS[name]


def overlong_punishment(lengths: Sequence[int], truncated: Sequence[bool], max_len: int,
                        buffer: int) -> list[float]:
    """DAPO's soft overlong punishment (its eq. 13; TRL's ``get_soft_overlong_punishment``), in
    [-1, 0], to be scaled and *added* to a reward. It judges tokens, not text, so it is not part
    of the rule above: a pass is still judged by ``check`` alone.

    ``lengths`` counts each completion's tokens, its EOS included. A completion of at most
    ``max_len - buffer`` tokens gets 0; from there the punishment falls linearly to -1 at
    ``max_len``. With ``buffer == 0`` (a course extension: TRL's version then punishes nothing)
    only a completion cut off at ``max_len`` without an EOS (``truncated``) gets -1. Why it
    matters here: a policy that never stops has its text cut at the cap, and the cut can land
    on the target length by itself (lesson 7, section 6.5)."""
    if not 0 <= buffer < max_len:
        raise ValueError(f"buffer={buffer} must be from 0 to max_len - 1 = {max_len - 1}")
    if len(lengths) != len(truncated):
        raise ValueError(f"{len(lengths)} lengths for {len(truncated)} truncated flags")
    if buffer == 0:
        return [-1.0 if cut else 0.0 for cut in truncated]
    start = max_len - buffer
    return [-1.0 if cut else -min(max(n - start, 0), buffer) / buffer
            for n, cut in zip(lengths, truncated)]
