"""Lesson 6's exercises 6.4 (token entropy) and 6.5 (the clipped loss of a reused batch, with its
clip fraction and a k3 KL): the checkers accept correct answers written in different ways and
name each plausible wrong answer."""
import pytest
import torch
import torch.nn.functional as F

from course_utils import losses
from course_utils.exercises import ExerciseError
from course_utils.loss_exercises import check_clipped_loss, check_token_entropy, reference_clipped_loss


# --- token entropy ------------------------------------------------------------------------------

def entropy_by_log_softmax(logits, mask):
    logp = F.log_softmax(logits, -1)
    return torch.where(mask.bool(), -(logp.exp() * logp).sum(-1), 0.0)


def entropy_by_logsumexp(logits, mask):
    """Correct, written differently: H = logsumexp(z) - sum_a pi(a) z_a."""
    H = torch.logsumexp(logits, -1) - (torch.softmax(logits, -1) * logits).sum(-1)
    return torch.where(mask.bool(), H, 0.0)


def entropy_by_categorical(logits, mask):
    return torch.where(mask.bool(), torch.distributions.Categorical(logits=logits).entropy(), 0.0)


def test_the_checkers_entropy_is_the_librarys_in_float32():
    logits = 3 * torch.randn(4, 5, 17, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(entropy_by_log_softmax(logits, torch.ones(4, 5)), losses.token_entropy(logits), atol=1e-6)


@pytest.mark.parametrize("answer", [entropy_by_log_softmax, entropy_by_logsumexp, entropy_by_categorical])
def test_token_entropy_checker_accepts_correct_answers(answer):
    check_token_entropy(answer)


def _entropy_wrong(kind):
    def answer(logits, mask):
        if kind == "in place":
            with torch.no_grad():
                logits[..., 0] = 0.0
        logp = F.log_softmax(logits, -1)
        H = -(logp.exp() * logp).sum(-1)
        m = mask.bool()
        p = torch.softmax(logits, -1)
        wrong = {"naive": lambda: torch.where(m, -(p * p.log()).sum(-1), 0.0),
                 "sign": lambda: torch.where(m, -H, 0.0),
                 "bits": lambda: torch.where(m, -(logp.exp() * torch.log2(logp.exp().clamp(min=1e-300))).sum(-1), 0.0),
                 "padding": lambda: H,
                 "times mask": lambda: H * mask,    # right here: the checker's padding logits are finite
                 "vocab mean": lambda: torch.where(m, -(logp.exp() * logp).mean(-1), 0.0),
                 "logits": lambda: torch.where(m, -(p * logits).sum(-1), 0.0),
                 "detached": lambda: torch.where(m, H, 0.0).detach(),
                 "grad detached": lambda: torch.where(m, -(logp.exp().detach() * logp).sum(-1), 0.0),
                 "in place": lambda: torch.where(m, H, 0.0)}
        return wrong[kind]()
    return answer


WRONG_ENTROPY = [("naive", "NaN or inf"), ("sign", "sign is flipped"), ("bits", "bits"),
                 ("padding", "padding positions are not 0"), ("vocab mean", "averages over the vocabulary"),
                 ("logits", "log-normalizer"), ("detached", "carries no gradient"),
                 ("grad detached", "its gradient is not"), ("in place", "changed its input `logits` in place")]


@pytest.mark.parametrize("kind, diagnosis", WRONG_ENTROPY, ids=[k for k, _ in WRONG_ENTROPY])
def test_token_entropy_checker_names_each_mistake(kind, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_token_entropy(_entropy_wrong(kind))


def test_an_entropy_times_the_mask_is_accepted_since_the_padding_logits_are_finite():
    """Multiplying by the mask instead of torch.where is right whenever padding logits are
    finite, as a model's are; the lesson recommends where, and the checker does not insist."""
    check_token_entropy(_entropy_wrong("times mask"))


# --- the clipped loss ------------------------------------------------------------------------------

def clipped_by_library(logprobs, old_logprobs, ref_logprobs, advantages, mask, eps_low, eps_high, beta):
    return reference_clipped_loss(logprobs, old_logprobs, ref_logprobs, advantages, mask, eps_low, eps_high, beta)


def clipped_by_hand(logprobs, old_logprobs, ref_logprobs, advantages, mask, eps_low, eps_high, beta):
    """Correct, written differently: the two branches as losses, max of losses, the mask multiplied."""
    ratio = (logprobs - old_logprobs).exp()
    loss1, loss2 = -ratio * advantages, -ratio.clamp(1 - eps_low, 1 + eps_high) * advantages
    r = (ref_logprobs - logprobs).exp()
    kl = r - (ref_logprobs - logprobs) - 1
    per_token = (torch.max(loss1, loss2) + beta * kl) * mask
    loss = torch.stack([per_token[i].sum() / mask[i].sum() for i in range(len(mask))]).mean()
    clip_fraction = ((loss2 > loss1).to(mask.dtype) * mask).sum() / mask.sum()
    return loss, clip_fraction.item(), ((kl * mask).sum() / mask.sum()).item()


@pytest.mark.parametrize("answer", [clipped_by_library, clipped_by_hand])
def test_clipped_loss_checker_accepts_correct_answers(answer):
    check_clipped_loss(answer)


def _clipped_wrong(kind):
    def answer(lp, old, ref, A, mask, eps_low, eps_high, beta):
        m = mask
        ratio = torch.exp(lp - old)
        clipped = None
        d = ref - lp
        kl = {"k1": lp - ref, "k3 reversed": torch.expm1(-d) + d,
              "kl to old": torch.expm1(old - lp) - (old - lp)}.get(kind, torch.expm1(d) - d)
        if kind == "ratio to ref":
            ratio = torch.exp(lp - ref)
        lo, hi = {"eps_high twice": (eps_high, eps_high), "eps swapped": (eps_high, eps_low)}.get(
            kind, (eps_low, eps_low if kind == "eps_low twice" else eps_high))
        clipped, unclipped = ratio.clamp(1 - lo, 1 + hi) * A, ratio * A
        if kind == "no clip":
            objective = unclipped
        elif kind == "current ratio":
            objective = torch.exp(lp - lp.detach()) * A
        elif kind == "clipped only":
            objective = clipped
        elif kind == "max":
            objective = torch.maximum(unclipped, clipped)
        else:
            objective = torch.minimum(unclipped, clipped)
        sign = -1 if kind == "kl sign" else 1
        per_token = (-objective + sign * beta * kl) * m
        if kind == "dapo":
            loss = per_token.sum() / m.sum()
        elif kind == "padded":
            loss = per_token.mean(-1).mean()
        else:
            loss = (per_token.sum(-1) / m.sum(-1)).mean()
        removed = (clipped < unclipped).to(m.dtype)
        if kind == "clip fraction both sides":
            removed = ((ratio > 1 + eps_high) | (ratio < 1 - eps_low)).to(m.dtype)
        clip_fraction = float((removed * m).sum() / (m.numel() if kind == "clip fraction padded" else m.sum()))
        mean_kl = 0.0 if kind == "kl only with beta" and beta == 0 else float((kl * m).sum() / m.sum())
        if kind == "tuple":
            return loss, clip_fraction
        if kind == "detached":
            loss = loss.detach()
        return loss, clip_fraction, mean_kl
    return answer


WRONG_CLIPPED = [("no clip", "clip is missing"), ("current ratio", "against the current policy"),
                 ("clipped only", "only the clipped branch"), ("max", "optimistic maximum"),
                 ("eps_low twice", "eps_low is used on both sides"), ("kl sign", "wrong sign"),
                 ("k1", "k1 estimate"), ("k3 reversed", "other way round"), ("dapo", "'dapo' aggregation"),
                 ("padded", "padding is counted"),
                 ("clip fraction both sides", "clip_fraction is"), ("clip fraction padded", "clip_fraction is"),
                 ("kl only with beta", "kl is"), ("tuple", "return three things"),
                 ("kl to old", "measured against old_logprobs"), ("ratio to ref", "taken against ref_logprobs"),
                 ("eps_high twice", "eps_high is used on both sides"), ("eps swapped", "swapped"),
                 ("detached", "carries no gradient")]


@pytest.mark.parametrize("kind, diagnosis", WRONG_CLIPPED, ids=[k for k, _ in WRONG_CLIPPED])
def test_clipped_loss_checker_names_each_mistake(kind, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_clipped_loss(_clipped_wrong(kind))


def test_the_correct_hand_written_variant_of_the_mistake_fixture_is_accepted():
    """The fixture above with no mistake switched on is a correct answer: the mistakes are
    single changes to a right answer, not a different program."""
    check_clipped_loss(_clipped_wrong("none"))


def test_clipped_loss_checker_refuses_a_gradient_through_padding():
    def leaky(lp, old, ref, A, mask, eps_low, eps_high, beta):
        loss, clip_fraction, kl = reference_clipped_loss(lp, old, ref, A, mask, eps_low, eps_high, beta)
        return loss + 1e-3 * (lp * (1 - mask)).sum() - 1e-3 * (lp * (1 - mask)).sum().detach(), clip_fraction, kl

    with pytest.raises(ExerciseError, match="gradient flowing through padding"):
        check_clipped_loss(leaky)


def test_clipped_loss_checker_refuses_an_answer_that_changes_old_logprobs():
    def in_place(lp, old, ref, A, mask, eps_low, eps_high, beta):
        out = reference_clipped_loss(lp, old, ref, A, mask, eps_low, eps_high, beta)
        old.zero_()
        return out

    with pytest.raises(ExerciseError, match="changed its input `old_logprobs` in place"):
        check_clipped_loss(in_place)


def test_answers_computed_in_float32_are_accepted_to_float32s_precision():
    """Exercise 6.1 computes in float32 (.float()), as the library does; the checkers' float64
    inputs must not make such answers fail at 1e-8."""
    check_token_entropy(lambda logits, mask: torch.where(mask.bool(), losses.token_entropy(logits), 0.0))
    check_clipped_loss(lambda *args: reference_clipped_loss(*[a.float() if torch.is_tensor(a) else a for a in args]))
