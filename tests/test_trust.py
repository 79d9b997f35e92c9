"""The trust-region lesson's formulas against independent computations, and its checkers: they
accept correct answers written in different ways and name each plausible wrong answer."""
import pytest
import torch

from course_utils import losses, trust
from course_utils.exercises import ExerciseError
from course_utils.trust_exercises import (check_clip_fraction, check_fisher_matrix,
                                          check_importance_weighted_surrogate)

D = torch.float64
SEQ = trust.SequencePolicy(T=3, V=2)


def _theta(n, seed, scale=1.0):
    return scale * torch.randn(n, generator=torch.Generator().manual_seed(seed), dtype=D)


POLICIES = [(trust.bandit_log_probs, _theta(4, 0)), (trust.bandit_log_probs, _theta(2, 1, 3.0)),
            (SEQ.log_probs, _theta(SEQ.n_params, 2))]


# --- the Fisher matrix, three ways ------------------------------------------------------------

@pytest.mark.parametrize("log_prob_fn, theta", POLICIES)
def test_fisher_is_the_hessian_of_the_kl_at_zero(log_prob_fn, theta):
    def kl_at(delta):
        return trust.kl(log_prob_fn(theta), log_prob_fn(theta + delta))

    hessian = torch.autograd.functional.hessian(kl_at, torch.zeros_like(theta))
    assert torch.allclose(trust.fisher_matrix(log_prob_fn, theta), hessian, atol=1e-10)


@pytest.mark.parametrize("log_prob_fn, theta", POLICIES)
def test_fisher_matches_finite_differences_of_the_kl(log_prob_fn, theta):
    """KL(theta || theta + delta) = 1/2 delta^T F delta + O(|delta|^3): the second difference
    of the KL along e_i + e_j recovers F_ij."""
    d, h = len(theta), 1e-4
    kl_at = lambda delta: float(trust.kl(log_prob_fn(theta), log_prob_fn(theta + delta)))  # noqa: E731
    eye = torch.eye(d, dtype=D)
    F_fd = torch.empty(d, d, dtype=D)
    for i in range(d):
        for j in range(d):
            F_fd[i, j] = (kl_at(h * (eye[i] + eye[j])) - kl_at(h * eye[i]) - kl_at(h * eye[j])) / h ** 2
    assert torch.allclose(trust.fisher_matrix(log_prob_fn, theta), F_fd, atol=1e-4)


def test_bandit_fisher_has_the_closed_form_and_the_natural_gradient_is_the_reward_gap():
    """Softmax with logits (theta, 0): F = (diag pi - pi pi^T) without the last row and column,
    and F^-1 grad J = r_k - r_K, whatever pi is: the natural gradient does not shrink as the
    policy becomes deterministic, the vanilla gradient pi_k (r_k - J) does."""
    theta = torch.tensor([5.0, -1.0, 0.3], dtype=D)
    reward = torch.tensor([0.2, 1.0, 0.5, 0.0], dtype=D)
    pi = trust.bandit_log_probs(theta).exp()
    closed = (torch.diag(pi) - torch.outer(pi, pi))[:3, :3]
    F = trust.fisher_matrix(trust.bandit_log_probs, theta)
    assert torch.allclose(F, closed, atol=1e-12)
    g = trust.exact_gradient(trust.bandit_log_probs, theta, reward)
    assert torch.allclose(g, (pi * (reward - pi @ reward))[:3], atol=1e-12)
    assert torch.allclose(trust.natural_gradient(F, g, 0.0), reward[:3] - reward[3], atol=1e-8)


def test_the_natural_step_is_invariant_to_a_linear_reparametrization_and_the_vanilla_is_not():
    theta = _theta(4, 3)
    reward = torch.rand(5, generator=torch.Generator().manual_seed(4), dtype=D)
    A = torch.eye(4, dtype=D) + 0.8 * _theta(16, 5).view(4, 4)           # theta = A phi
    phi = torch.linalg.solve(A, theta)
    by_phi = lambda p: trust.bandit_log_probs(A @ p)                      # noqa: E731
    g_theta = trust.exact_gradient(trust.bandit_log_probs, theta, reward)
    g_phi = trust.exact_gradient(by_phi, phi, reward)
    natural_theta = trust.natural_gradient(trust.fisher_matrix(trust.bandit_log_probs, theta), g_theta, 0.0)
    natural_phi = trust.natural_gradient(trust.fisher_matrix(by_phi, phi), g_phi, 0.0)
    assert torch.allclose(A @ natural_phi, natural_theta, atol=1e-9)
    assert not torch.allclose(A @ g_phi, g_theta, atol=1e-3)


def test_the_kl_step_sits_on_the_edge_of_the_quadratic_kl_ball_and_near_the_true_one():
    theta = _theta(SEQ.n_params, 6, 0.5)
    reward = torch.rand(2 ** 3, generator=torch.Generator().manual_seed(7), dtype=D)
    F = trust.fisher_matrix(SEQ.log_probs, theta)
    g = trust.exact_gradient(SEQ.log_probs, theta, reward)
    step = trust.kl_step(F, g, 1e-4, damping=1e-6)
    assert float(0.5 * step @ F @ step) == pytest.approx(1e-4, rel=1e-3)
    true_kl = float(trust.kl(SEQ.log_probs(theta), SEQ.log_probs(theta + step)))
    assert true_kl == pytest.approx(1e-4, rel=0.05)


# --- importance sampling -------------------------------------------------------------------------

def test_sequence_weights_are_unbiased_and_their_second_moment_is_the_product_over_tokens():
    """For T tokens drawn independently, E_old[w] = 1 and E_old[w^2] = (sum_x p^2 / q)^T: the
    weight's variance grows exponentially with the length."""
    q = torch.tensor([0.4, 0.3, 0.2, 0.1], dtype=D)
    p = torch.tensor([0.25, 0.25, 0.25, 0.25], dtype=D)
    for T in (1, 2, 3):
        policy = trust.SequencePolicy(T=T, V=4)
        seqs = policy.sequences
        q_seq, p_seq = q[seqs].prod(-1), p[seqs].prod(-1)
        w = trust.sequence_weights(p[seqs].log(), q[seqs].log(), torch.ones(len(seqs), T, dtype=D))
        assert float((q_seq * w).sum()) == pytest.approx(1.0, abs=1e-12)
        assert float((q_seq * w ** 2).sum()) == pytest.approx(float((p ** 2 / q).sum()) ** T, rel=1e-10)
        assert torch.allclose(w, p_seq / q_seq)


def test_clip_fraction_agrees_with_the_loss_s_own_count():
    g = torch.Generator().manual_seed(8)
    old = -torch.rand(7, 6, generator=g) * 2
    new = old + 0.5 * torch.randn(7, 6, generator=g)
    adv = torch.randn(7, generator=g)
    mask = (torch.arange(6) < torch.randint(1, 7, (7,), generator=g)[:, None]).float()
    _, stats = losses.grpo_loss(new, old, adv, mask, eps_low=0.2, eps_high=0.28)
    assert trust.clip_fraction(new, old, adv, mask, 0.2, 0.28) == pytest.approx(stats["clip_fraction"], abs=1e-7)


# --- the checkers: correct variants accepted -------------------------------------------------------

def fisher_by_jacobian(log_prob_fn, theta):
    J = torch.autograd.functional.jacobian(log_prob_fn, theta)
    p = log_prob_fn(theta).exp()
    return (J * p[:, None]).T @ J


def fisher_by_loop(log_prob_fn, theta):
    """Correct, written differently: one backward per outcome."""
    theta = theta.detach().requires_grad_(True)
    logp = log_prob_fn(theta)
    F = torch.zeros(len(theta), len(theta), dtype=theta.dtype)
    for k in range(len(logp)):
        (s,) = torch.autograd.grad(logp[k], theta, retain_graph=True)
        F += logp[k].exp().detach() * torch.outer(s, s)
    return F


def fisher_by_loop_in_float32(log_prob_fn, theta):
    """Correct, built in float32 (the default dtype when the lesson's cell is re-run later):
    right to float32's precision."""
    return fisher_by_loop(log_prob_fn, theta).float()


def fisher_by_kl_hessian(log_prob_fn, theta):
    """Correct, written differently: the Hessian of KL(pi_theta || pi_theta+delta) at delta = 0."""
    base = log_prob_fn(theta).detach()
    return torch.autograd.functional.hessian(
        lambda d: trust.kl(base, log_prob_fn(theta + d)), torch.zeros_like(theta))


@pytest.mark.parametrize("answer", [fisher_by_jacobian, fisher_by_loop, fisher_by_kl_hessian,
                                    fisher_by_loop_in_float32, trust.fisher_matrix])
def test_fisher_checker_accepts_correct_answers(answer):
    check_fisher_matrix(answer)


def weight_detached(logp_new, logp_old, rewards, mask):
    """Correct, written differently: the weight as a constant, times the score function."""
    w = torch.exp(((logp_new - logp_old) * mask).sum(-1)).detach()
    return w * rewards * (logp_new * mask).sum(-1)


@pytest.mark.parametrize("answer", [trust.importance_weighted_surrogate, weight_detached])
def test_importance_checker_accepts_correct_answers(answer):
    check_importance_weighted_surrogate(answer)


def clip_fraction_by_loss(logp_new, logp_old, advantages, mask, eps_low, eps_high):
    """Correct, written differently: where the clipped branch of the loss is the larger one."""
    per_token, clipped = losses.clipped_surrogate(logp_new, logp_old, advantages, eps_low, eps_high)
    return float((clipped.float() * mask).sum() / mask.sum())


@pytest.mark.parametrize("answer", [trust.clip_fraction, clip_fraction_by_loss])
def test_clip_fraction_checker_accepts_correct_answers(answer):
    check_clip_fraction(answer)


# --- the checkers: each mistake named -----------------------------------------------------------

def _fisher_wrong(kind):
    def answer(log_prob_fn, theta):
        J = torch.autograd.functional.jacobian(log_prob_fn, theta)
        logp = log_prob_fn(theta)
        F = (J * logp.exp()[:, None]).T @ J
        return {"unweighted": J.T @ J, "logp": (J * logp[:, None]).T @ J,
                "mean": torch.outer(logp.exp() @ J, logp.exp() @ J), "diag": torch.diag(torch.diag(F)),
                "sign": -F, "zeros": torch.zeros_like(F), "squeezed": F.squeeze()}[kind]
    return answer


WRONG_FISHER = [("unweighted", "every outcome counts the same"), ("logp", "log-probabilities"),
                ("mean", "expected\\* score"), ("zeros", "all zeros"), ("diag", "only the diagonal"),
                ("sign", "sign is flipped"), ("squeezed", "squeeze")]


@pytest.mark.parametrize("kind, diagnosis", WRONG_FISHER, ids=[k for k, _ in WRONG_FISHER])
def test_fisher_checker_names_each_mistake(kind, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_fisher_matrix(_fisher_wrong(kind))


def test_fisher_checker_refuses_an_answer_that_changes_theta():
    def in_place(log_prob_fn, theta):
        F = trust.fisher_matrix(log_prob_fn, theta)
        theta.zero_()
        return F

    with pytest.raises(ExerciseError, match="changed its input `theta` in place"):
        check_fisher_matrix(in_place)


def _is_wrong(kind):
    def answer(logp_new, logp_old, rewards, mask):
        delta = (logp_new - logp_old) * mask
        return {"per-token sum": (torch.exp(delta) * mask).sum(-1) * rewards,
                "per-token mean": (torch.exp(delta) * mask).sum(-1) / mask.sum(-1) * rewards,
                "no weight": (logp_new * mask).sum(-1) * rewards,
                "inverted": torch.exp(-delta.sum(-1)) * rewards,
                "padding": torch.exp((logp_new - logp_old).sum(-1)) * rewards,
                "mean": (torch.exp(delta.sum(-1)) * rewards).mean(),
                "detached": (torch.exp(delta.sum(-1)) * rewards).detach()}[kind]
    return answer


def _is_hidden_wrong(kind):
    """Answers right on narrow checks: a clipped weight, gradient through the padding, and a
    slice that assumes right padding of one width."""
    def answer(logp_new, logp_old, rewards, mask):
        if kind == "clamped":
            log_w = ((logp_new - logp_old) * mask).sum(-1).clamp(-1.0, 1.0)
            return torch.exp(log_w) * rewards
        if kind == "padding gradient":   # the weight from the real tokens, the score from all
            w = torch.exp(((logp_new - logp_old) * mask).sum(-1)).detach()
            return w * rewards * logp_new.sum(-1)
        T = int(mask.sum(-1).max())       # "the real tokens are the first T columns"
        delta = (logp_new - logp_old)[:, :T]
        return torch.exp(delta.sum(-1)) * rewards
    return answer


@pytest.mark.parametrize("kind", ["clamped", "padding gradient", "right padding assumed"])
def test_importance_checker_refuses_answers_a_narrow_check_would_pass(kind):
    with pytest.raises(ExerciseError):
        check_importance_weighted_surrogate(_is_hidden_wrong(kind))


WRONG_IS = [("per-token sum", "sum of per-token ratios"), ("per-token mean", "mean of per-token ratios"),
            ("no weight", "no importance weight"), ("inverted", "weight is inverted"),
            ("padding", "padding is counted"), ("mean", "one value per sequence"),
            ("detached", "carries no gradient")]


@pytest.mark.parametrize("kind, diagnosis", WRONG_IS, ids=[k for k, _ in WRONG_IS])
def test_importance_checker_names_each_mistake(kind, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_importance_weighted_surrogate(_is_wrong(kind))


def _clip_wrong(kind):
    def answer(logp_new, logp_old, advantages, mask, eps_low, eps_high):
        ratio, A = torch.exp(logp_new - logp_old), advantages[:, None]
        over = mask if kind != "padding" else torch.ones_like(mask)
        hi = eps_low if kind == "eps_low" else eps_high
        if kind == "typed":
            eps_low, hi = 0.2, 0.2
        x = ratio.log() if kind == "log" else ratio
        if kind == "both sides":
            flags = (ratio > 1 + eps_high) | (ratio < 1 - eps_low)
        elif kind == "zero":
            flags = ((A >= 0) & (ratio > 1 + eps_high)) | ((A <= 0) & (ratio < 1 - eps_low))
        else:
            flags = ((A > 0) & (x > 1 + hi)) | ((A < 0) & (x < 1 - eps_low))
        return float((flags.float() * over).sum() / over.sum())
    return answer


WRONG_CLIP = [("typed", "bounds are typed in"), ("both sides", "every ratio outside"), ("zero", "A = 0 are counted"),
              ("padding", "padding is counted"), ("eps_low", "eps_low is used on both sides"),
              ("log", "log-ratio is compared")]


@pytest.mark.parametrize("kind, diagnosis", WRONG_CLIP, ids=[k for k, _ in WRONG_CLIP])
def test_clip_fraction_checker_names_each_mistake(kind, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_clip_fraction(_clip_wrong(kind))


def test_clip_fraction_checker_refuses_an_answer_that_changes_its_inputs():
    def in_place(logp_new, logp_old, advantages, mask, eps_low, eps_high):
        logp_new -= logp_old
        return trust.clip_fraction(logp_new, torch.zeros_like(logp_old), advantages, mask, eps_low, eps_high)

    with pytest.raises(ExerciseError, match="changed its input `logp_new` in place"):
        check_clip_fraction(in_place)
