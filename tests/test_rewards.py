"""The rule checker: exact definitions, TRL's calling convention, and arbitrary Unicode."""
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from course_utils import rewards

T = dict(target_chars=[10], target_digit_sum=[6])


def test_definition_on_hand_examples():
    r = rewards.check("  abc 12 3xyz \n", 10, 6)  # stripped: "abc 12 3xyz" is 11 chars
    assert (r.n_chars, r.digit_sum, r.length_ok, r.digits_ok, r.passed) == (11, 6, False, True, False)
    r = rewards.check("abc 12 3xy", 10, 6)
    assert r.passed
    assert rewards.check("", 1, 0) == rewards.RuleCheck(0, 0, False, True)


def test_non_ascii_digits_are_characters_not_digits():
    # superscript two, Arabic-Indic three, fullwidth seven, Devanagari four: isdigit() is True
    for char in ["²", "٣", "７", "४"]:
        assert char.isdigit()
        r = rewards.check(f"a{char}1", 3, 1)
        assert r.digit_sum == 1 and r.n_chars == 3 and r.passed
    assert rewards.digit_sum("é9ö") == 9


def test_binary_and_shaped_rewards_with_trl_signature():
    completions = ["abc 12 3xy", "abc 12 3xyzw", "no digits"]
    kw = dict(target_chars=[10] * 3, target_digit_sum=[6] * 3)
    assert rewards.binary_reward(prompts=["p"] * 3, completions=completions, **kw) == [1.0, 0.0, 0.0]
    shaped = rewards.shaped_reward(prompts=["p"] * 3, completions=completions, **kw)
    assert shaped[0] == 1.0
    assert shaped[1] == pytest.approx(0.5 / (1 + 2 / 10) + 0.5)
    assert shaped[2] == pytest.approx(0.5 / (1 + 1 / 10) + 0.5 / (1 + 6 / 6))  # 9 chars, sum 0 of 6
    # farther is always worse, however far: there is signal even for very long completions
    far = rewards.shaped_reward(["p"] * 2, ["x" * 50, "x" * 90], target_chars=[10] * 2,
                                target_digit_sum=[0] * 2)
    assert 0 < far[1] < far[0] < 1
    assert rewards.length_reward(["p"] * 3, completions, **kw) == [1.0, 0.0, 0.0]
    assert rewards.digit_sum_reward(["p"] * 3, completions, **kw) == [1.0, 1.0, 0.0]


def test_conversational_completions_as_trl_passes_them():
    chat = [[{"role": "assistant", "content": " abc 12 3xy "}]]
    assert rewards.binary_reward(prompts=[[{"role": "user", "content": "q"}]], completions=chat, **T) == [1.0]


def test_missing_or_ragged_targets_are_clear_errors():
    with pytest.raises(KeyError, match="target_digit_sum"):
        rewards.binary_reward(["p"], ["x"], target_chars=[1])
    with pytest.raises(ValueError, match="2 values for 1 completions"):
        rewards.binary_reward(["p"], ["x"], target_chars=[1, 2], target_digit_sum=[0])
    with pytest.raises(TypeError, match="completion must be"):
        rewards.binary_reward(["p"], [42], **T)


@settings(max_examples=300, deadline=None)
@given(text=st.text(), target_chars=st.integers(1, 200), target_sum=st.integers(0, 300))
def test_rewards_never_raise_on_arbitrary_unicode(text, target_chars, target_sum):
    kw = dict(target_chars=[target_chars], target_digit_sum=[target_sum])
    b = rewards.binary_reward(["p"], [text], **kw)[0]
    s = rewards.shaped_reward(["p"], [text], **kw)[0]
    assert b in (0.0, 1.0) and 0.0 < s <= 1.0 and math.isfinite(s)
    assert (s == 1.0) == (b == 1.0)
    stripped = text.strip()
    assert rewards.check(text, target_chars, target_sum).n_chars == len(stripped)
    assert rewards.digit_sum(text) == sum(int(c) for c in stripped if c in "0123456789")


# --- odd inputs (issue 14, finding 9): scored as what they mean, or refused naming the column ----

def test_chat_content_none_is_empty_text_and_parts_are_joined():
    from course_utils import rewards as R
    assert R.completion_text([{"role": "assistant", "content": None}]) == ""
    parts = [{"role": "assistant", "content": [{"type": "text", "text": "ab"}, {"type": "image"},
                                               {"type": "text", "text": "c1 "}]}]
    assert R.completion_text(parts) == "abc1"
    assert R.check(parts, 4, 1).passed
    with pytest.raises(TypeError, match="content parts"):
        R.completion_text([{"role": "assistant", "content": [3]}])


def test_shaped_reward_with_a_zero_length_target_is_finite_and_one_at_the_target():
    from course_utils import rewards as R
    got = R.shaped_reward(None, ["", "ab"], target_chars=[0, 0], target_digit_sum=[0, 0])
    assert got[0] == 1.0 and 0 < got[1] < 1


@pytest.mark.parametrize("column, values, words", [
    ("target_chars", [-3], "whole numbers >= 0"),
    ("target_digit_sum", [2.5], "whole numbers >= 0"),
    ("target_digit_sum", "7", "one target per completion"),
])
def test_bad_targets_are_refused_naming_the_column(column, values, words):
    from course_utils import rewards as R
    kwargs = {"target_chars": [5], "target_digit_sum": [1], column: values}
    with pytest.raises((ValueError, TypeError), match=words) as err:
        R.shaped_reward(None, ["a1"], **kwargs)
    assert column in str(err.value)


def test_numpy_targets_and_float_whole_numbers_are_accepted():
    import numpy as np

    from course_utils import rewards as R
    texts = ["abcd1", "xy"]
    want = R.binary_reward(None, texts, target_chars=[5, 2], target_digit_sum=[1, 0])
    assert R.binary_reward(None, texts, target_chars=np.array([5, 2]), target_digit_sum=[1.0, 0.0]) == want
    assert R.binary_reward(None, texts[:1], target_chars=np.int64(5), target_digit_sum=np.int32(1)) == [1.0]


def test_a_bare_string_of_completions_is_refused_not_scored_per_character():
    from course_utils import rewards as R
    with pytest.raises(TypeError, match="single string"):
        R.binary_reward(None, "abc", target_chars=[1, 1, 1], target_digit_sum=[0, 0, 0])


def test_graded_reward_counts_whole_units_and_pays_nothing_without_digits():
    """The digit part: 1 / (1 + |digit sum - S|), and 0 when the digits add up to 0 (none)."""
    def graded(text, L=10, S=12):
        return rewards.graded_reward(["p"], [text], target_chars=[L], target_digit_sum=[S])[0]

    assert graded("abcdefgh39") == 1.0                                    # 10 chars, 3 + 9 = 12
    assert graded("abcdefghi8") == pytest.approx(0.5 + 0.5 / 5)           # sum 8: four units short
    assert graded("abcdefghi9") == pytest.approx(0.5 + 0.5 / 4)
    assert graded("abcdefghij") == pytest.approx(0.5)                     # no digit: no digit credit
    assert graded("abcdefghi0") == pytest.approx(0.5)                     # only zeros: the same
    assert graded("abcdefghi0", S=0) == 1.0                               # unless the target is 0
    assert graded("abcdefgh39x") == pytest.approx(0.5 * (0.5 / (1 + 1 / 10) + 0.5 / 2) + 0.5)
    assert graded("abcdefgh39" + "x" * 10) == pytest.approx(0.5 * (0.5 / 2 + 0.5 / 11) + 0.5)
    # the order that matters for two-digit targets: a second digit towards 12 beats any one digit
    assert graded("abcdefghi8") < graded("abcdefghi9") < graded("abcdefgh48x")


@settings(max_examples=300, deadline=None)
@given(text=st.text(), target_chars=st.integers(1, 200), target_sum=st.integers(0, 300))
def test_graded_reward_is_one_exactly_when_binary_is(text, target_chars, target_sum):
    kw = dict(target_chars=[target_chars], target_digit_sum=[target_sum])
    b = rewards.binary_reward(["p"], [text], **kw)[0]
    g = rewards.graded_reward(["p"], [text], **kw)[0]
    assert 0.0 < g <= 1.0 and (g == 1.0) == (b == 1.0)


def test_counted_reward_halves_the_digit_credit_per_digit_too_few():
    """'counted' is 'graded' with the digit part times 2^-(ceil(S/9) - digits), never below 0."""
    def counted(text, L=10, S=12):
        return rewards.counted_reward(["p"], [text], target_chars=[L], target_digit_sum=[S])[0]

    def graded(text, L=10, S=12):
        return rewards.graded_reward(["p"], [text], target_chars=[L], target_digit_sum=[S])[0]

    assert [rewards.digits_needed(s) for s in (0, 1, 9, 10, 18, 19)] == [0, 1, 1, 2, 2, 3]
    assert counted("abcdefgh39") == 1.0
    assert counted("abcdefghi9") == pytest.approx(0.5 + 0.5 / 4 / 2)       # one digit short of 2
    assert counted("abcdefgh45") == pytest.approx(0.5 + 0.5 / 4)           # two digits, sum 9
    assert counted("abcdefghij") == pytest.approx(0.5)                     # no digit: nothing to halve
    assert counted("abcdefgh9x", S=30) == pytest.approx(0.5 + 0.5 / 22 / 8)  # 3 digits short of 4
    # where one digit can reach the target, counted is graded, zeros counting as digits
    for text in ("abcdefghi8", "abcdefgh00", "abcdefgh1", "abcd5efgh3x"):
        assert counted(text, S=8) == graded(text, S=8)
    # the order that matters for two-digit targets: two digits near 12 beat the best one digit
    assert counted("abcdefghi9") < counted("abcdefgh45") < counted("abcdefgh57")


@settings(max_examples=300, deadline=None)
@given(text=st.text(), target_chars=st.integers(1, 200), target_sum=st.integers(0, 300))
def test_counted_reward_is_one_exactly_when_binary_is_and_never_above_graded(text, target_chars,
                                                                              target_sum):
    kw = dict(target_chars=[target_chars], target_digit_sum=[target_sum])
    b = rewards.binary_reward(["p"], [text], **kw)[0]
    c = rewards.counted_reward(["p"], [text], **kw)[0]
    assert 0.0 < c <= rewards.graded_reward(["p"], [text], **kw)[0]
    assert (c == 1.0) == (b == 1.0)


def test_graded_pays_the_best_one_digit_reply_more_than_most_two_digit_replies():
    """Lesson 7, 6.4: against a two-digit target, graded's digit credit for a 9 beats that of
    most replies with two digits (all 100 pairs of digits equally likely), and counted's does
    not beat most of them."""
    for S in (10, 11, 12):
        def credit(reward, digits):
            return reward(["p"], ["x" * (10 - len(digits)) + digits], target_chars=[10],
                          target_digit_sum=[S])[0]
        pairs = [f"{a}{b}" for a in range(10) for b in range(10)]
        for reward, most in ((rewards.graded_reward, True), (rewards.counted_reward, False)):
            below = sum(credit(reward, p) < credit(reward, "9") for p in pairs)
            assert (below > len(pairs) / 2) == most, (S, reward.__name__, below)


@settings(max_examples=200, deadline=None)
@given(target_sum=st.integers(0, 60), padding=st.integers(0, 40), seed=st.integers(0, 10**6))
def test_every_partial_credit_is_one_on_passing_texts(target_sum, padding, seed):
    """The other direction of 'exactly 1 when binary is 1': texts built to pass (digits adding
    up to S, shuffled among letters) score 1 under graded and counted."""
    import random
    rng = random.Random(seed)
    digits = []
    while sum(digits) < target_sum:
        digits.append(rng.randint(1, min(9, target_sum - sum(digits))))
    chars = [str(d) for d in digits] + [rng.choice("abc xyz") for _ in range(padding)]
    rng.shuffle(chars)
    text = "q" + "".join(chars) + "q"   # no surrounding whitespace to strip
    kw = dict(target_chars=[len(text)], target_digit_sum=[target_sum])
    assert rewards.binary_reward(["p"], [text], **kw) == [1.0]
    assert rewards.graded_reward(["p"], [text], **kw) == [1.0]
    assert rewards.counted_reward(["p"], [text], **kw) == [1.0]
    assert rewards.gated_reward(["p"], [text], **kw) == [1.0]


def test_counted_pays_any_two_digits_near_ten_at_least_twice_a_lone_nine():
    """The counted_score docstring: against S = 10, '9' earns a digit credit of 1/4, any two
    digits within one unit of 10 at least 1/2."""
    def digit_credit(digits):
        text = "x" * (10 - len(digits)) + digits
        return 2 * (rewards.counted_reward(["p"], [text], target_chars=[10], target_digit_sum=[10])[0] - 0.5)
    assert digit_credit("9") == pytest.approx(0.25)
    near = [f"{a}{b}" for a in range(10) for b in range(10) if abs(a + b - 10) <= 1]
    assert near and all(digit_credit(p) >= 0.5 - 1e-12 for p in near)


def test_gated_reward_multiplies_counted_credits_on_hand_examples():
    """'gated' = counted's digit credit x (1/2 + 1/2 x length credit): nothing without a digit
    against a positive target."""
    def gated(text, L=10, S=12):
        return rewards.gated_reward(["p"], [text], target_chars=[L], target_digit_sum=[S])[0]

    assert gated("abcdefgh39") == 1.0
    assert gated("abcdefghij") == 0.0                     # counted pays this 1/2
    assert gated("abcdefgh00") == 0.0                     # digits adding up to 0 are none
    assert gated("abc") == 0.0
    assert gated("abcdefgh45") == pytest.approx(1 / 4)    # right length, digit credit 1/4
    assert gated("abcdefghi9") == pytest.approx(1 / 8)    # one digit short of 2: halved
    # right digits, one character off: length credit 1/2 / (1 + 1/10) + 1/2 / 2
    length_credit = 0.5 / 1.1 + 0.25
    assert gated("abcdefghi39") == pytest.approx(0.5 + 0.5 * length_credit)
    assert gated("abcdefghi39") > gated("abcdefghij39") > gated("abcdefgh56") > 0
    # a target of 0 is met by a reply without digits, so that reply is not refused
    assert gated("abcdefghij", S=0) == 1.0
    assert rewards.get_reward_fn("gated") is rewards.gated_reward


@settings(max_examples=300, deadline=None)
@given(text=st.text(), target_chars=st.integers(1, 200), target_sum=st.integers(0, 300))
def test_gated_reward_is_one_exactly_when_binary_is_and_never_above_counted(text, target_chars,
                                                                            target_sum):
    """digit x (1/2 + length/2) <= digit/2 + length/2 for credits in [0, 1], so gated <= counted."""
    kw = dict(target_chars=[target_chars], target_digit_sum=[target_sum])
    b = rewards.binary_reward(["p"], [text], **kw)[0]
    g = rewards.gated_reward(["p"], [text], **kw)[0]
    assert 0.0 <= g <= rewards.counted_reward(["p"], [text], **kw)[0]
    assert (g == 1.0) == (b == 1.0)
    sums_to_zero = rewards.check(text, target_chars, target_sum).digit_sum == 0
    assert (g == 0.0) == (sums_to_zero and target_sum > 0)
