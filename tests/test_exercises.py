"""Every checker accepts a correct answer and rejects plausible wrong ones, saying why."""
import re

import pytest
import torch
import torch.nn.functional as F

from course_utils import exercises as ex
from course_utils import losses


def stub(*args, **kwargs):
    raise NotImplementedError


# ------------------------------------------------------------------- correct implementations
def sf_grad(theta, actions, rewards):
    score = F.one_hot(actions, theta.shape[0]).float() - torch.softmax(theta, -1)
    return (rewards[:, None] * score).mean(0)


def sf_grad_autograd(theta, actions, rewards):  # a second, independent correct answer
    theta = theta.clone().requires_grad_()
    (grad,) = torch.autograd.grad((torch.log_softmax(theta, -1)[actions] * rewards).mean(), theta)
    return grad


def seq_logp(logits, tokens):
    return torch.log_softmax(logits, -1).gather(-1, tokens.unsqueeze(-1)).squeeze(-1).sum(-1)


def rtg(rewards, gamma):
    out, running = torch.zeros_like(rewards), torch.zeros(rewards.shape[0])
    for t in reversed(range(rewards.shape[1])):
        running = rewards[:, t] + gamma * running
        out[:, t] = running
    return out


def cmask(ids, eos):
    is_eos = ids == eos
    first = torch.where(is_eos.any(-1), is_eos.int().argmax(-1), ids.shape[1])
    return (torch.arange(ids.shape[1])[None] <= first[:, None]).long()


def group_adv(r, G):
    r2 = r.view(-1, G)
    return ((r2 - r2.mean(-1, keepdim=True)) / (r2.std(-1, keepdim=True) + 1e-4)).reshape(-1)


def clipped(logp, old, adv, el, eh):
    ratio, A = (logp - old).exp(), adv[:, None]
    return torch.maximum(-ratio * A, -ratio.clamp(1 - el, 1 + eh) * A)


def aggregate(x, m, kind):
    m = m.float()
    if kind == "grpo":
        return ((x * m).sum(-1) / m.sum(-1)).mean()
    return (x * m).sum() / m.sum()


CASES = {  # checker: (correct answers, [(wrong answer, expected words in the message)])
    ex.check_score_function_gradient: ([sf_grad, sf_grad_autograd], [
        (lambda t, a, r: -sf_grad(t, a, r), "sign flipped"),
        (lambda t, a, r: sf_grad(t, a, r) * len(a), "summed over samples"),
        (lambda t, a, r: (r[:, None] * torch.softmax(t, -1)[a][:, None]
                          * (F.one_hot(a, t.shape[0]) - torch.softmax(t, -1))).mean(0), "grad pi(a) instead"),
        (lambda t, a, r: torch.zeros_like(t), "differs from the reference"),
    ]),
    ex.check_sequence_log_prob: ([seq_logp], [
        (lambda l, t: torch.log_softmax(l, -1).gather(-1, t.unsqueeze(-1)).squeeze(-1).mean(-1), "averaged over tokens"),
        (lambda l, t: l.gather(-1, t.unsqueeze(-1)).squeeze(-1).sum(-1), "raw logits"),
        (lambda l, t: seq_logp(l, t).exp(), "probability, not a log-probability"),
    ]),
    ex.check_surrogate_loss: ([lambda lp, r: -(lp * r).mean()], [
        (lambda lp, r: (lp * r).mean(), "sign flipped"),
        (lambda lp, r: -(lp * r).sum(), "summed instead of averaged"),
        (lambda lp, r: -(lp.detach() * r).mean(), "carries no gradient"),
        (lambda lp, r: -(lp * r), "must be a scalar"),
    ]),
    ex.check_returns_to_go: ([rtg, lambda r, g: losses.returns_to_go(r, g)], [
        (lambda r, g: torch.cumsum(r, -1), "PAST rewards"),
        (lambda r, g: rtg(r, 1.0), "ignored gamma"),
        (lambda r, g: torch.flip(torch.cumsum(torch.flip(r * g ** torch.arange(r.shape[1]), [-1]), -1), [-1]), "gamma^(k - t)"),
    ]),
    ex.check_masked_reinforce_loss: ([lambda lp, G, m: -(lp * G * m).sum(-1).mean()], [
        (lambda lp, G, m: -(lp * G).sum(-1).mean(), "padding tokens counted"),
        (lambda lp, G, m: (lp * G * m).sum(-1).mean(), "sign flipped"),
        (lambda lp, G, m: -(lp * G * m).sum() / m.sum(), "averaged over tokens"),
    ]),
    ex.check_completion_mask: ([cmask], [
        (lambda ids, eos: (ids != eos).long(), "ids != pad_id"),
        (lambda ids, eos: torch.where((ids == eos).any(-1, keepdim=True),
                                      (torch.arange(ids.shape[1]) < cmask(ids, eos).sum(-1, keepdim=True) - 1).long(),
                                      cmask(ids, eos)), "excluded the EOS"),
        (lambda ids, eos: cmask(ids, eos) * (ids == eos).any(-1, keepdim=True), "without EOS"),
    ]),
    ex.check_leave_one_out_baseline: ([lambda r, G: losses.leave_one_out_baseline(r, G)], [
        (lambda r, G: r.view(-1, G).mean(-1, keepdim=True).expand(-1, G).reshape(-1), "own reward"),
        (lambda r, G: ((r.view(-1, G).sum(-1, keepdim=True) - r.view(-1, G)) / G).reshape(-1), "instead of G - 1"),
    ]),
    ex.check_self_baseline_factor: ([lambda n: (n - 1) / n], [
        (lambda n: 1.0, "NOT independent"),
        (lambda n: n / (n - 1), "inverted"),
        (lambda n: "(n-1)/n", "return a number"),
    ]),
    ex.check_actor_critic_advantage: ([lambda r, v: r - v.detach()], [
        (lambda r, v: r - v, "still carries the critic's gradient"),
        (lambda r, v: v.detach() - r, "sign flipped"),
    ]),
    ex.check_group_advantages: ([group_adv, lambda r, G: losses.group_advantages(r, G)[0]], [
        (lambda r, G: (r - r.mean()) / (r.std() + 1e-4), "whole batch"),
        (lambda r, G: ((r.view(-1, G) - r.view(-1, G).mean(-1, keepdim=True))
                       / r.view(-1, G).std(-1, keepdim=True)).reshape(-1), "no epsilon"),
        (lambda r, G: ((r.view(-1, G) - r.view(-1, G).mean(-1, keepdim=True))
                       / (r.view(-1, G).std(-1, unbiased=False, keepdim=True) + 1e-4)).reshape(-1), "population std"),
    ]),
    ex.check_clipped_surrogate: ([clipped], [
        (lambda lp, o, a, el, eh: clipped(lp, o, a, el, el), "eps_low on both sides"),
        (lambda lp, o, a, el, eh: -(lp - o).exp() * a[:, None], "no clipping"),
        (lambda lp, o, a, el, eh: torch.minimum(-(lp - o).exp() * a[:, None],
                                                -(lp - o).exp().clamp(1 - el, 1 + eh) * a[:, None]), "pessimistic"),
    ]),
    ex.check_k3_kl: ([lambda lp, ref: (ref - lp).exp() - (ref - lp) - 1], [
        (lambda lp, ref: lp - ref, "k1"),
        (lambda lp, ref: (lp - ref).exp() - (lp - ref) - 1, "upside down"),
        (lambda lp, ref: 0.5 * (lp - ref) ** 2, "k2"),
    ]),
    ex.check_aggregate: ([aggregate], [
        (lambda x, m, kind: aggregate(x, torch.ones_like(m), kind), "padding counted"),
        (lambda x, m, kind: aggregate(x, m, "dapo" if kind == "grpo" else "grpo"), "other aggregation"),
    ]),
}


@pytest.mark.parametrize("checker", list(CASES), ids=lambda c: c.__name__)
def test_checker_accepts_correct_answers(checker, capsys):
    for correct in CASES[checker][0]:
        checker(correct)
    assert "✓" in capsys.readouterr().out


@pytest.mark.parametrize("checker", list(CASES), ids=lambda c: c.__name__)
def test_checker_rejects_plausible_wrong_answers_and_says_why(checker):
    wrong_answers = CASES[checker][1]
    assert len(wrong_answers) >= 2
    for wrong, words in wrong_answers:
        with pytest.raises(ex.ExerciseError, match=re.escape(words)):
            checker(wrong)


@pytest.mark.parametrize("checker", list(CASES), ids=lambda c: c.__name__)
def test_an_untouched_stub_says_not_implemented(checker):
    with pytest.raises(ex.ExerciseError, match="not implemented yet"):
        checker(stub)
