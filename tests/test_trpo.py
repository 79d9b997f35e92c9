"""TRPO's matrix-free step (lesson 4, exercise 4.2): the library's Fisher-vector product,
conjugate gradients and line search against independent computations, and the three checkers:
they accept correct answers written in different ways and name each plausible wrong answer."""
import pytest
import torch

from course_utils import trust
from course_utils import trust_exercises as te
from course_utils.exercises import ExerciseError
from course_utils.trust_exercises import (check_conjugate_gradient, check_fisher_vector_product,
                                          check_trpo_step)

D = torch.float64


# --- the library against independent computations -------------------------------------------------

@pytest.mark.parametrize("case", range(5))
def test_the_fisher_vector_product_is_the_formed_matrix_times_v(case):
    label, log_prob_fn, theta = te._policies()[case]
    v = torch.randn(len(theta), generator=torch.Generator().manual_seed(case), dtype=D)
    want = trust.fisher_matrix(log_prob_fn, theta) @ v
    assert torch.allclose(trust.fisher_vector_product(log_prob_fn, theta, v), want, atol=1e-10), label


def test_conjugate_gradients_solve_a_damped_singular_fisher_system_in_rank_plus_one_iterations():
    seq = trust.SequencePolicy(T=2, V=3)          # 24 parameters, 9 outcomes: rank at most 8
    theta = torch.randn(seq.n_params, generator=torch.Generator().manual_seed(0), dtype=D)
    A = trust.fisher_matrix(seq.log_probs, theta) + 1e-3 * torch.eye(seq.n_params, dtype=D)
    b = torch.randn(seq.n_params, generator=torch.Generator().manual_seed(1), dtype=D)
    x = trust.conjugate_gradient(lambda v: A @ v, b, iters=9)
    assert torch.allclose(x, torch.linalg.solve(A, b), atol=1e-8, rtol=1e-8)
    assert not torch.allclose(trust.conjugate_gradient(lambda v: A @ v, b, iters=4), x, atol=1e-3)


def test_a_trpo_step_that_passes_its_line_search_is_kl_step():
    """The first checker case: the full step passes, and equals the step with F formed."""
    label, log_prob_fn, theta, surrogate, kw = te._trpo_cases()[0]
    new = trust.trpo_step(log_prob_fn, theta, surrogate, **kw)
    start = theta.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(surrogate(start), start)
    full = trust.kl_step(trust.fisher_matrix(log_prob_fn, theta), g, kw["max_kl"], damping=1e-3)
    assert torch.allclose(new - theta, full, atol=1e-9), label


def test_the_trpo_cases_exercise_what_their_labels_say():
    """The line search keeps the whole step, half, an eighth, nothing; and each decision has a
    margin, so an answer that differs from the reference by rounding decides the same."""
    cases = te._trpo_cases()
    kept = []
    for label, log_prob_fn, theta, surrogate, kw in cases[:4]:
        kw = {**te.TRPO_DEFAULTS, **kw}
        new = trust.trpo_step(log_prob_fn, theta, surrogate, **kw)
        start = theta.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(surrogate(start), start)
        full = trust.kl_step(trust.fisher_matrix(log_prob_fn, theta), g, kw["max_kl"], damping=kw["damping"])
        kept.append(round(float((new - theta).norm() / full.norm()), 6))
        for k in range(kw["max_backtracks"]):
            candidate = theta + kw["backtrack"] ** k * full
            kl = float(trust.kl(log_prob_fn(theta), log_prob_fn(candidate)))
            gain = float(surrogate(candidate) - surrogate(theta))
            assert abs(kl / kw["max_kl"] - 1) > 0.1 and abs(gain) > 1e-5, (label, k, kl, gain)
            if kl <= kw["max_kl"] and gain > 0:
                break
    assert kept == [1.0, 0.5, 0.125, 0.0]


def test_the_checkers_reference_variant_is_the_library():
    for label, log_prob_fn, theta, surrogate, kw in te._trpo_cases():
        kw = {**te.TRPO_DEFAULTS, **kw}
        assert torch.equal(te._trpo_variant(log_prob_fn, theta, surrogate, **kw),
                           trust.trpo_step(log_prob_fn, theta, surrogate, **kw)), label


def test_every_named_trpo_mistake_differs_from_the_reference_somewhere():
    """Otherwise the checker would accept it, and its message could never be shown."""
    cases = te._trpo_cases()
    for message, flags in te.TRPO_MISTAKES.items():
        assert any(not torch.allclose(te._trpo_variant(f, th, s, **{**te.TRPO_DEFAULTS, **kw}, **flags),
                                      trust.trpo_step(f, th, s, **{**te.TRPO_DEFAULTS, **kw}), atol=1e-6)
                   for _, f, th, s, kw in cases), message


# --- correct answers, written differently, are accepted -------------------------------------------

def fvp_reverse_kl(log_prob_fn, theta, v):
    """Correct: KL(pi_theta' || pi_theta) has the same Hessian at theta' = theta."""
    log_p = log_prob_fn(theta).detach()
    theta_new = theta.detach().clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(trust.kl(log_prob_fn(theta_new), log_p), theta_new, create_graph=True)
    (Fv,) = torch.autograd.grad(grad @ v, theta_new)
    return Fv


def fvp_by_hvp(log_prob_fn, theta, v):
    """Correct: autograd's Hessian-vector product of the KL, which never forms the Hessian."""
    log_p = log_prob_fn(theta).detach()
    return torch.autograd.functional.hvp(lambda t: trust.kl(log_p, log_prob_fn(t)), theta.detach(), v)[1]


def fvp_by_score_weighted_sum(log_prob_fn, theta, v):
    """Correct: E[s (s . v)] with one backward pass per outcome, F never formed."""
    theta = theta.detach().requires_grad_(True)
    logp = log_prob_fn(theta)
    out = torch.zeros_like(theta)
    for k in range(len(logp)):
        (s,) = torch.autograd.grad(logp[k], theta, retain_graph=True)
        out = out + logp[k].exp().detach() * s * (s @ v)
    return out


@pytest.mark.parametrize("answer", [trust.fisher_vector_product, fvp_reverse_kl, fvp_by_hvp,
                                    fvp_by_score_weighted_sum])
def test_fisher_vector_product_checker_accepts_correct_answers(answer):
    check_fisher_vector_product(answer)


def cg_with_tolerance(matrix_vector_product, b, iters):
    """Correct: stops when the residual is small relative to b (the checker's systems converge
    exactly, or are stopped by iters first)."""
    x, r = torch.zeros_like(b), b.clone()
    p, rr = r.clone(), b @ b
    for _ in range(iters):
        if rr.sqrt() < 1e-12 * b.norm():
            break
        Ap = matrix_vector_product(p)
        alpha = rr / (p @ Ap)
        x, r = x + alpha * p, r - alpha * Ap
        rr, rr_old = r @ r, rr
        p = r + rr / rr_old * p
    return x


def cg_with_explicit_residual(matrix_vector_product, b, iters):
    """Correct: the residual b - A x0 computed with one extra product (x0 = 0)."""
    x = torch.zeros_like(b)
    r = b - matrix_vector_product(x)
    p = r
    for _ in range(iters):
        Ap = matrix_vector_product(p)
        alpha = (r @ r) / (p @ Ap)
        x = x + alpha * p
        r_new = r - alpha * Ap
        if r_new.norm() == 0:
            break
        p = r_new + (r_new @ r_new) / (r @ r) * p
        r = r_new
    return x


@pytest.mark.parametrize("answer", [trust.conjugate_gradient, cg_with_tolerance, cg_with_explicit_residual])
def test_conjugate_gradient_checker_accepts_correct_answers(answer):
    check_conjugate_gradient(answer)


def trpo_with_func_grad(log_prob_fn, theta, surrogate, max_kl, cg_iters, damping, backtrack, max_backtracks):
    """Correct: g from torch.func.grad, the fractions listed first, float comparisons."""
    g = torch.func.grad(surrogate)(theta.detach())
    x = trust.conjugate_gradient(lambda v: fvp_by_hvp(log_prob_fn, theta, v) + damping * v, g, cg_iters)
    delta = x * (2 * max_kl / float(g @ x)) ** 0.5
    before, log_p = float(surrogate(theta)), log_prob_fn(theta).detach()
    for fraction in [backtrack ** k for k in range(max_backtracks)]:
        candidate = theta.detach() + fraction * delta
        if float(trust.kl(log_p, log_prob_fn(candidate))) <= max_kl and float(surrogate(candidate)) > before:
            return candidate.detach()
    return theta.detach().clone()


@pytest.mark.parametrize("answer", [trust.trpo_step, trpo_with_func_grad])
def test_trpo_step_checker_accepts_correct_answers(answer):
    check_trpo_step(answer)


# --- wrong answers are refused, by name -------------------------------------------------------------

def test_fisher_vector_product_checker_refuses_a_formed_fisher_matrix():
    with pytest.raises(ExerciseError, match="builds a full Jacobian or Hessian"):
        check_fisher_vector_product(lambda f, theta, v: te.trust.fisher_matrix(f, theta) @ v)
    # and the functions it blocks are restored afterwards
    assert torch.autograd.functional.jacobian(lambda t: t * 2, torch.ones(2)).shape == (2, 2)


def test_fisher_vector_product_checker_names_a_kl_whose_fixed_side_is_not_detached():
    def not_detached(log_prob_fn, theta, v):
        theta = theta.detach().clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(trust.kl(log_prob_fn(theta), log_prob_fn(theta)), theta, create_graph=True)
        return torch.autograd.grad(grad @ v, theta, allow_unused=True)[0] if grad.requires_grad else torch.zeros_like(theta)

    with pytest.raises(ExerciseError, match="not detached"):
        check_fisher_vector_product(not_detached)


def test_conjugate_gradient_checker_refuses_building_the_matrix():
    def build_then_solve(matrix_vector_product, b, iters):
        A = torch.stack([matrix_vector_product(e) for e in torch.eye(len(b), dtype=b.dtype)], 1)
        return torch.linalg.solve(A, b)

    with pytest.raises(ExerciseError, match="builds the matrix"):
        check_conjugate_gradient(build_then_solve)


def test_trpo_step_checker_refuses_an_answer_that_changes_theta():
    def in_place(log_prob_fn, theta, surrogate, max_kl, cg_iters, damping, backtrack, max_backtracks):
        new = trust.trpo_step(log_prob_fn, theta, surrogate, max_kl, cg_iters, damping, backtrack, max_backtracks)
        theta.copy_(new)
        return new

    with pytest.raises(ExerciseError, match="changed its input `theta` in place"):
        check_trpo_step(in_place)
