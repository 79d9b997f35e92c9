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


def group_adv_eps6(r, G):  # CS336's epsilon
    r2 = r.view(-1, G)
    return ((r2 - r2.mean(-1, keepdim=True)) / (r2.std(-1, keepdim=True) + 1e-6)).reshape(-1)


def group_adv_guarded(r, G):  # an exact 0 for an all-equal group, no epsilon at all
    r2 = r.view(-1, G)
    std = r2.std(-1, keepdim=True)
    centred = r2 - r2.mean(-1, keepdim=True)
    return torch.where(std > 0, centred / std.clamp(min=1e-12), torch.zeros_like(centred)).reshape(-1)


def in_place(fn, which=0):
    """A wrong answer that returns the right value but scribbles on one of its inputs."""
    def wrapped(*args):
        out = fn(*args)
        with torch.no_grad():
            args[which].mul_(2)
        return out
    return wrapped


def detached(fn):
    """A wrong answer with the right value and no gradient (computed as a new tensor)."""
    return lambda *args: torch.tensor(fn(*args).detach().tolist())


def cmask_to_last_eos(ids, eos):  # keeps the text between a first and a later EOS
    is_eos = ids == eos
    last = ids.shape[1] - 1 - torch.flip(is_eos, [-1]).int().argmax(-1)
    return torch.where(is_eos.any(-1, keepdim=True),
                       (torch.arange(ids.shape[1])[None] <= last[:, None]).long(), torch.ones_like(ids))


def cmask_eos2(ids, eos):  # hard-coded to the EOS id of lesson 2's first example
    return cmask(ids, 2)


CASES = {  # checker: (correct answers, [(wrong answer, expected words in the message)])
    ex.check_score_function_gradient: ([sf_grad, sf_grad_autograd], [
        (lambda t, a, r: -sf_grad(t, a, r), "sign flipped"),
        (lambda t, a, r: sf_grad(t, a, r) * len(a), "summed over samples"),
        (lambda t, a, r: (r[:, None] * torch.softmax(t, -1)[a][:, None]
                          * (F.one_hot(a, t.shape[0]) - torch.softmax(t, -1))).mean(0), "grad pi(a) instead"),
        (lambda t, a, r: torch.zeros_like(t), "differs from the reference"),
        (lambda t, a, r: (r[:, None] * F.one_hot(a, t.shape[0]).float()).mean(0), "one-hot alone"),
        (lambda t, a, r: sf_grad(t, a, r) * len(a) / 64, "n=10"),                 # n = 64 hard-coded
        (in_place(sf_grad, 2), "changed its input `rewards` in place"),
    ]),
    ex.check_sequence_log_prob: ([seq_logp, lambda l, t: torch.log(torch.softmax(l, -1)).gather(-1, t[..., None])[..., 0].sum(1)], [
        (lambda l, t: torch.log_softmax(l, -1).gather(-1, t.unsqueeze(-1)).squeeze(-1).mean(-1), "averaged over tokens"),
        (lambda l, t: l.gather(-1, t.unsqueeze(-1)).squeeze(-1).sum(-1), "raw logits"),
        (lambda l, t: seq_logp(l, t).exp(), "probability, not a log-probability"),
        (detached(seq_logp), "carries no gradient"),
        (lambda l, t: seq_logp(l.detach(), t) + 0 * l.sum(), "gradient with respect to `logits`"),
        (in_place(seq_logp, 0), "changed its input `logits` in place"),
    ]),
    ex.check_surrogate_loss: ([lambda lp, r: -(lp * r).mean(), lambda lp, r: -torch.dot(lp, r) / len(r)], [
        (lambda lp, r: (lp * r).mean(), "sign flipped"),
        (lambda lp, r: -(lp * r).sum(), "summed instead of averaged"),
        (lambda lp, r: -(lp.detach() * r).mean(), "carries no gradient"),
        (lambda lp, r: -(lp * r), "must be a scalar"),
        (lambda lp, r: -(lp.exp() * r).mean(), "probabilities where the loss needs log-probabilities"),
        (lambda lp, r: -(lp * r).sum() / 8, "differs"),              # N = 8 hard-coded
    ]),
    ex.check_returns_to_go: ([rtg, lambda r, g: losses.returns_to_go(r, g)], [
        (lambda r, g: torch.cumsum(r, -1), "PAST rewards"),
        (lambda r, g: rtg(r, 1.0), "ignored gamma"),
        (lambda r, g: torch.flip(torch.cumsum(torch.flip(r * g ** torch.arange(r.shape[1]), [-1]), -1), [-1]), "gamma^(k - t)"),
        (lambda r, g: rtg(r, 0.9 if g != 1.0 else 1.0), "gamma=0.5"),   # 0.9 hard-coded
        (in_place(rtg, 0), "changed its input `rewards` in place"),
    ]),
    ex.check_masked_reinforce_loss: ([lambda lp, G, m: -(lp * G * m).sum(-1).mean(),
                                      lambda lp, G, m: -torch.where(m.bool(), lp * G, 0.0).sum() / lp.shape[0]], [
        (lambda lp, G, m: -(lp * G).sum(-1).mean(), "padding tokens counted"),
        (lambda lp, G, m: (lp * G * m).sum(-1).mean(), "sign flipped"),
        (lambda lp, G, m: -(lp * G * m).sum() / m.sum(), "averaged over tokens"),
        (lambda lp, G, m: -((lp * G * m).sum(-1) / m.sum(-1)).mean(), "averaged over each sequence's tokens"),
        (detached(lambda lp, G, m: -(lp * G * m).sum(-1).mean()), "carries no gradient"),
        (lambda lp, G, m: -(lp * G * m).sum(-1).mean() * 0 - (lp.detach() * G * m).sum(-1).mean(), "gradient with respect to `logprobs`"),
        (in_place(lambda lp, G, m: -(lp * G * m).sum(-1).mean(), 1), "changed its input `returns` in place"),
    ]),
    ex.check_completion_mask: ([cmask, lambda ids, eos: losses_mask(ids, eos)], [
        (lambda ids, eos: (ids != eos).long(), "ids != pad_id"),
        (lambda ids, eos: torch.where((ids == eos).any(-1, keepdim=True),
                                      (torch.arange(ids.shape[1]) < cmask(ids, eos).sum(-1, keepdim=True) - 1).long(),
                                      cmask(ids, eos)), "excluded the EOS"),
        (lambda ids, eos: cmask(ids, eos) * (ids == eos).any(-1, keepdim=True), "without EOS"),
        (cmask_eos2, "instead of the eos_id argument"),
        (cmask_to_last_eos, "FIRST EOS"),
        (in_place(cmask, 0), "changed its input `ids` in place"),
    ]),
    ex.check_leave_one_out_baseline: ([lambda r, G: losses.leave_one_out_baseline(r, G),
                                       lambda r, G: torch.stack([torch.cat([g[:i], g[i + 1:]]).mean()
                                                                 for g in r.view(-1, G) for i in range(G)])], [
        (lambda r, G: r.view(-1, G).mean(-1, keepdim=True).expand(-1, G).reshape(-1), "own reward"),
        (lambda r, G: ((r.view(-1, G).sum(-1, keepdim=True) - r.view(-1, G)) / G).reshape(-1), "instead of G - 1"),
        (lambda r, G: r - losses.leave_one_out_baseline(r, G), "returned the advantage"),
        (lambda r, G: losses.leave_one_out_baseline(r, 4), "G=2"),              # G = 4 hard-coded
        (in_place(lambda r, G: losses.leave_one_out_baseline(r, G), 0), "changed its input `rewards` in place"),
    ]),
    ex.check_self_baseline_factor: ([lambda n: (n - 1) / n, lambda n: 1 - 1 / n], [
        (lambda n: 1.0, "NOT independent"),
        (lambda n: n / (n - 1), "inverted"),
        (lambda n: "(n-1)/n", "return a number"),
        (lambda n: 0.5 if n == 2 else 0.8 if n == 5 else 15 / 16, "N=3"),        # the old three values only
    ]),
    ex.check_actor_critic_advantage: ([lambda r, v: r - v.detach(), lambda r, v: (r - v).detach()], [
        (lambda r, v: r - v, "still carries the critic's gradient"),
        (lambda r, v: v.detach() - r, "sign flipped"),
        (in_place(lambda r, v: r - v.detach(), 0), "changed its input `rewards` in place"),
    ]),
    ex.check_group_advantages: ([group_adv, lambda r, G: losses.group_advantages(r, G)[0],
                                 group_adv_eps6, group_adv_guarded], [
        (lambda r, G: (r - r.mean()) / (r.std() + 1e-4), "whole batch"),
        (lambda r, G: ((r.view(-1, G) - r.view(-1, G).mean(-1, keepdim=True))
                       / r.view(-1, G).std(-1, keepdim=True)).reshape(-1), "no epsilon"),
        (lambda r, G: ((r.view(-1, G) - r.view(-1, G).mean(-1, keepdim=True))
                       / (r.view(-1, G).std(-1, unbiased=False, keepdim=True) + 1e-4)).reshape(-1), "population std"),
        (lambda r, G: group_adv(r, 4), "G=3"),                                   # G = 4 hard-coded
        (lambda r, G: ((r.view(-1, G) - r.view(-1, G).mean(-1, keepdim=True))
                       / (r.view(-1, G).var(-1, keepdim=True) + 1e-4)).reshape(-1), "variance, not the std"),
        (in_place(group_adv, 0), "changed its input `rewards` in place"),
    ]),
    ex.check_clipped_surrogate: ([clipped, lambda lp, o, a, el, eh: losses.clipped_surrogate(lp, o, a, el, eh)[0]], [
        (lambda lp, o, a, el, eh: clipped(lp, o, a, el, el), "eps_low on both sides"),
        (lambda lp, o, a, el, eh: -(lp - o).exp() * a[:, None], "no clipping"),
        (lambda lp, o, a, el, eh: torch.minimum(-(lp - o).exp() * a[:, None],
                                                -(lp - o).exp().clamp(1 - el, 1 + eh) * a[:, None]), "pessimistic"),
        (lambda lp, o, a, el, eh: clipped(lp, o, a, 0.2, 0.28), "eps_low=0.1"),   # the first case's clip hard-coded
        (lambda lp, o, a, el, eh: clipped(lp, o, a, eh, el), "swapped eps_low and eps_high"),
        (detached(clipped), "carries no gradient"),
        (lambda lp, o, a, el, eh: clipped(lp.detach(), o, a, el, eh) + 0 * lp, "gradient with respect to `logp`"),
        (in_place(clipped, 2), "changed its input `advantages` in place"),
    ]),
    ex.check_k3_kl: ([lambda lp, ref: (ref - lp).exp() - (ref - lp) - 1, lambda lp, ref: ref.exp() / lp.exp() - ref + lp - 1], [
        (lambda lp, ref: lp - ref, "k1"),
        (lambda lp, ref: (lp - ref).exp() - (lp - ref) - 1, "upside down"),
        (lambda lp, ref: 0.5 * (lp - ref) ** 2, "k2"),
        (lambda lp, ref: (ref - lp).exp() - (ref - lp), "forgot the -1"),
        (detached(lambda lp, ref: (ref - lp).exp() - (ref - lp) - 1), "carries no gradient"),
        (in_place(lambda lp, ref: (ref - lp).exp() - (ref - lp) - 1, 1), "changed its input `ref_logp` in place"),
    ]),
    ex.check_aggregate: ([aggregate, lambda x, m, kind: losses.aggregate(x, m, kind)], [
        (lambda x, m, kind: aggregate(x, torch.ones_like(m), kind), "padding counted"),
        (lambda x, m, kind: aggregate(x, m, "dapo" if kind == "grpo" else "grpo"), "other aggregation"),
        (lambda x, m, kind: aggregate(x, ((x * m) != 0).long(), kind) if kind == "dapo"
         else (((x * m).sum(-1) / ((x * m) != 0).sum(-1).clamp(min=1)).mean()), "non-zero losses"),
        (lambda x, m, kind: aggregate(x, m, kind) if kind == "grpo" else (x * m).sum() / x.shape[0], "number of sequences N"),
        (detached(aggregate), "carries no gradient"),
        (in_place(aggregate, 0), "changed its input `per_token` in place"),
    ]),
}


def losses_mask(ids, eos):
    from course_utils.rollout import completion_mask
    return completion_mask(ids, [eos])


@pytest.mark.parametrize("checker", list(CASES), ids=lambda c: c.__name__)
def test_checker_accepts_correct_answers(checker, capsys):
    assert len(CASES[checker][0]) >= 2          # different-but-correct answers keep passing
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
