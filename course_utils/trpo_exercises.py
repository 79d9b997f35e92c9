"""Checkers for lesson 4's exercise 4.2, TRPO's step without forming F: the Fisher-vector
product by double backward, conjugate gradients, and the backtracking line search.

They work as the other checkers do (``trust_exercises.py``): seeded policies of several shapes,
``course_utils.trust`` as the reference, inputs checked for in-place changes, and the plausible
mistakes named. Two things are particular to a matrix-free method: an answer that builds F (a
Jacobian, a Hessian, or one backward pass per outcome) is refused, and a line-search mistake is
named only when the answer matches that mistake on every case, since on one case several
mistakes can give the same step.
"""

from __future__ import annotations

from typing import Callable

import torch

from . import trust
from .exercises import ExerciseError, _as_tensor, _close, _run
from .trust_exercises import _policies


# ----------------------------------------------------------------------------------------------
# TRPO's step, matrix-free: Fisher-vector products, conjugate gradients, the line search
# ----------------------------------------------------------------------------------------------


class _NoFullMatrix:
    """While active, the functions that build a Jacobian or Hessian raise, and the backward
    passes are counted: an answer that forms F (or A) explicitly is not matrix-free, and at a
    language model's size it would not fit. F v by double backward takes two or three backward
    passes, whatever the number of outcomes; F built from the scores takes one per outcome
    (``grad_calls``). An answer that imports ``jacobian`` under its own name before the checker
    runs escapes the first test, not the second."""
    TARGETS = [(torch.autograd.functional, "jacobian"), (torch.autograd.functional, "hessian"),
               (torch.func, "jacrev"), (torch.func, "jacfwd"), (torch.func, "hessian"),
               (trust, "fisher_matrix")]

    def __init__(self, name: str):
        self.name, self.saved, self.grad_calls = name, [], 0

    def __enter__(self):
        def refuse(*args, **kwargs):
            raise ExerciseError(f"{self.name}: this builds a full Jacobian or Hessian (F itself). "
                                f"The point is never to form F: get F v from two backward passes "
                                f"through the KL (torch.autograd.grad with create_graph=True)")

        def counted(original):
            def wrapper(*args, **kwargs):
                self.grad_calls += 1
                return original(*args, **kwargs)
            return wrapper

        for module, attr in self.TARGETS:
            self.saved.append((module, attr, getattr(module, attr)))
            setattr(module, attr, refuse)
        for module, attr in ((torch.autograd, "grad"), (torch.Tensor, "backward")):
            self.saved.append((module, attr, getattr(module, attr)))
            setattr(module, attr, counted(getattr(module, attr)))
        return self

    def __exit__(self, *exc):
        for module, attr, original in self.saved:
            setattr(module, attr, original)
        return False


def _fvp_mistakes(log_prob_fn, theta, v) -> dict[str, torch.Tensor]:
    scores = torch.autograd.functional.jacobian(log_prob_fn, theta)
    p = log_prob_fn(theta).exp()
    F = scores.T @ (p[:, None] * scores)
    return {
        "every outcome counts the same: this is sum_x s(x) s(x)^T v without the weights pi(x); F is "
        "an expectation (differentiate the KL, which carries the weights, instead of summing "
        "outer products of scores)": scores.T @ (scores @ v),
        "the sign is flipped: F v is the Hessian of the KL (a minimum at theta' = theta) times v":
            -(F @ v),
        "this is twice F v: the KL's Hessian at theta' = theta is F itself, no factor 2":
            2 * (F @ v),
    }


def check_fisher_vector_product(fn: Callable) -> None:
    """``fn(log_prob_fn, theta, v)`` -> F v [d], without forming F."""
    name = "fisher_vector_product"
    gen = torch.Generator().manual_seed(5)
    for label, log_prob_fn, theta in _policies():
        for _ in range(2):   # two directions per policy
            v = torch.randn(len(theta), generator=gen, dtype=torch.float64)
            with _NoFullMatrix(name) as guard:
                got = _as_tensor(name, _run(name, fn, dict(log_prob_fn=log_prob_fn, theta=theta, v=v)))
            outcomes = len(log_prob_fn(theta))
            if outcomes > 4 and guard.grad_calls >= outcomes:
                raise ExerciseError(f"{name}: {guard.grad_calls} backward passes for one F v on {label} "
                                    f"({outcomes} outcomes): one per outcome builds F from the scores. "
                                    f"Matrix-free, F v takes two backward passes through the KL, "
                                    f"however many outcomes there are")
            want = trust.fisher_matrix(log_prob_fn, theta) @ v
            if got.shape != want.shape:
                raise ExerciseError(f"{name}: on {label} the result has shape {tuple(got.shape)}; F v is "
                                    f"a vector like theta, {tuple(want.shape)}")
            if _close(got.detach(), want, 1e-8):
                continue
            if float(got.detach().abs().max()) <= 1e-10 * float(want.abs().max()):
                raise ExerciseError(
                    f"{name}: F v is zero on {label}. Two usual causes: the KL's fixed side is not "
                    f"detached, so it is KL(pi_theta' || pi_theta') = 0 for every theta' (compute "
                    f"log_prob_fn(theta) once and .detach() it); or only one backward pass was "
                    f"taken: the KL's gradient is 0 at theta' = theta, and F v is the derivative "
                    f"of that gradient along v (a second torch.autograd.grad, of grad . v)")
            for message, value in _fvp_mistakes(log_prob_fn, theta, v).items():
                if _close(got.detach(), value, 1e-8):
                    raise ExerciseError(f"{name}: {message} (on {label})")
            diff = (got.detach() - want).abs().max().item()
            raise ExerciseError(f"{name}: differs from F v by up to {diff:.3g} on {label}")
    print(f"✓ {name}: correct and matrix-free (bandits with 2, 3 and 6 arms, sequence policies of "
          f"2 and 3 tokens, two directions each)")


def _spd(d: int, g: torch.Generator, rank: int | None = None) -> torch.Tensor:
    B = torch.randn(d, rank or d, generator=g, dtype=torch.float64)
    return B @ B.T / d


def _counting(A: torch.Tensor) -> tuple[Callable, list]:
    calls = []

    def product(x: torch.Tensor) -> torch.Tensor:
        calls.append(1)
        return A @ x
    return product, calls


def _cg_variant(A: torch.Tensor, b: torch.Tensor, iters: int, beta: str) -> torch.Tensor:
    """CG with a wrong conjugation coefficient: negated, inverted, or the direction rebuilt from
    the residual before it is updated."""
    x, r = torch.zeros_like(b), b.clone()
    p, rr = r.clone(), b @ b
    for _ in range(iters):
        Ap = A @ p
        alpha = rr / (p @ Ap)
        x = x + alpha * p
        r_new = r - alpha * Ap
        rr_new = r_new @ r_new
        coefficient = {"negated": -rr_new / rr, "inverted": rr / rr_new, "stale": rr_new / rr}[beta]
        p = (r if beta == "stale" else r_new) + coefficient * p
        r, rr = r_new, rr_new
    return x


def _steepest_descent(A: torch.Tensor, b: torch.Tensor, iters: int) -> torch.Tensor:
    x, r = torch.zeros_like(b), b.clone()
    for _ in range(iters):
        Ar = A @ r
        x, r = x + (r @ r) / (r @ Ar) * r, r - (r @ r) / (r @ Ar) * Ar
    return x


def check_conjugate_gradient(fn: Callable) -> None:
    """``fn(matrix_vector_product, b, iters)`` -> x with A x = b, A symmetric positive definite
    and given only as the function x -> A x, after ``iters`` conjugate-gradient iterations from 0."""
    name = "conjugate_gradient"
    gen = torch.Generator().manual_seed(6)
    seq = trust.SequencePolicy(T=2, V=3)
    theta = torch.randn(seq.n_params, generator=gen, dtype=torch.float64)
    F = trust.fisher_matrix(seq.log_probs, theta)
    # (label, A, iters): enough iterations to converge, then too few (the answer must be CG's own
    # iterate, not a solve), a 1 x 1 system, and a damped singular Fisher matrix whose clustered
    # spectrum lets 10 iterations solve a 24-dimensional system
    cases = [("a well-conditioned 4 x 4 system, 4 iterations", _spd(4, gen) + 0.5 * torch.eye(4, dtype=torch.float64), 4),
             ("an 8 x 8 system stopped after 3 iterations", _spd(8, gen) + 0.1 * torch.eye(8, dtype=torch.float64), 3),
             ("a 1 x 1 system", torch.tensor([[2.5]], dtype=torch.float64), 1),
             ("a damped Fisher matrix (24 parameters, rank 8), 10 iterations",
              F + 1e-3 * torch.eye(len(F), dtype=torch.float64), 10)]
    for label, A, iters in cases:
        b = torch.randn(len(A), generator=gen, dtype=torch.float64)
        product, calls = _counting(A)
        got = _as_tensor(name, _run(name, fn, dict(matrix_vector_product=product, b=b, iters=iters)))
        want = trust.conjugate_gradient(lambda x: A @ x, b, iters)
        if got.shape != want.shape:
            raise ExerciseError(f"{name}: on {label} the result has shape {tuple(got.shape)}, expected "
                                f"{tuple(want.shape)}")
        if len(calls) > iters + 1:
            converged = _close(got.detach(), torch.linalg.solve(A, b), 1e-7)
            raise ExerciseError(f"{name}: {len(calls)} matrix-vector products for {iters} iterations on "
                                f"{label}. CG needs one per iteration and stops after `iters`; "
                                + ("running it to convergence, or a solve that builds the matrix, "
                                   "ignores iters, which is what bounds TRPO's cost" if converged else
                                   "calling it once per coordinate builds the matrix, which the "
                                   "method exists to avoid"))
        if _close(got.detach(), want, 1e-7):
            continue
        mistakes = {
            "the result is b itself: the iterations never updated x": b,
            "each search direction is the residual itself: that is steepest descent. CG makes the "
            "next direction conjugate to the last, p = r + (r_new . r_new / r . r) p":
                _steepest_descent(A, b, iters),
            "this is one fewer iteration than asked": trust.conjugate_gradient(lambda x: A @ x, b, iters - 1),
            "this is one more iteration than asked": trust.conjugate_gradient(lambda x: A @ x, b, iters + 1),
            "the conjugation coefficient has the wrong sign: beta = +(r_new . r_new) / (r . r)":
                _cg_variant(A, b, iters, "negated"),
            "the conjugation coefficient is inverted: beta = (r_new . r_new) / (r . r), the new "
            "residual over the old": _cg_variant(A, b, iters, "inverted"),
            "the next direction is built from the residual before its update: update r first, "
            "then p = r_new + beta p": _cg_variant(A, b, iters, "stale"),
        }
        if iters < len(A):
            mistakes[f"this is the exact solution; after {iters} iterations CG has not reached it "
                     f"(the checker asks for CG's own iterate)"] = torch.linalg.solve(A, b)
        for message, value in mistakes.items():
            if _close(got.detach(), value, 1e-7):
                raise ExerciseError(f"{name}: {message} (on {label})")
        residual = (A @ got.detach() - b).norm().item() / b.norm().item()
        raise ExerciseError(f"{name}: differs from CG's iterate on {label}; relative residual "
                            f"|A x - b| / |b| = {residual:.3g}")
    print(f"✓ {name}: correct (4 systems up to 24 x 24, converged and stopped early, one product "
          f"per iteration)")


def _trpo_variant(log_prob_fn, theta, surrogate, max_kl, cg_iters, damping, backtrack, max_backtracks,
                  fvp: str = "right", direction: str = "natural", scale: str = "kl ball",
                  search: str = "both", fallback: str = "theta", kl_side: str = "old || new",
                  fractions: str = "backtrack**k"):
    """trust.trpo_step, or one of the plausible mistakes (the arguments name them)."""
    theta = theta.detach()
    start = theta.clone().requires_grad_(True)
    value = surrogate(start)
    (g,) = torch.autograd.grad(value, start)
    if fvp == "unweighted":
        scores = torch.autograd.functional.jacobian(log_prob_fn, theta)
        product = lambda v: scores.T @ (scores @ v) + damping * v   # noqa: E731
    elif fvp == "zero":
        product = lambda v: damping * v                             # noqa: E731
    else:
        d = 0.0 if fvp == "undamped" else damping
        product = lambda v: trust.fisher_vector_product(log_prob_fn, theta, v) + d * v   # noqa: E731
    x = g.clone() if direction.startswith("gradient") else trust.conjugate_gradient(product, g, cg_iters)
    if direction == "negated":
        x = -x
    curvature = {"gradient": lambda: g @ product(x),   # x^T (F + damping) x for the gradient
                 "gradient, undamped": lambda: g @ trust.fisher_vector_product(log_prob_fn, theta, g),
                 "natural": lambda: g @ x, "negated": lambda: -(g @ x)}[direction]()
    if scale == "undamped":
        curvature = x @ trust.fisher_vector_product(log_prob_fn, theta, x)
    factor = {"kl ball": torch.sqrt(2 * max_kl / curvature), "no 2": torch.sqrt(max_kl / curvature),
              "undamped": torch.sqrt(2 * max_kl / curvature),
              "none": torch.tensor(1.0, dtype=g.dtype)}[scale]
    delta = factor * x
    log_p = log_prob_fn(theta)
    candidate = theta + delta
    with torch.no_grad():
        for k in range(max_backtracks if search != "none" else 1):
            fraction = {"k+1": backtrack ** (k + 1), "linear": backtrack * k}.get(fractions, backtrack ** k)
            candidate = theta + fraction * delta
            if search == "none":
                return candidate
            new = log_prob_fn(candidate)
            kl_value = trust.kl(log_p, new) if kl_side == "old || new" else trust.kl(new, log_p)
            kl_ok, improved = kl_value <= max_kl, surrogate(candidate) > value
            if (kl_ok and improved) if search == "both" else kl_ok if search == "kl" else improved:
                return candidate
    return candidate if fallback == "last" else theta.clone()


# the mistakes the TRPO checker names, each a variant of the reference (_trpo_variant's arguments)
TRPO_MISTAKES = {
    "there is no line search: the full step is taken even where its true KL exceeds max_kl or "
    "the surrogate got worse. Try theta + backtrack**k * delta for k = 0, 1, ... and keep the first "
    "that passes both tests": dict(search="none"),
    "the line search checks only that the surrogate improved; it must also check the true KL, "
    "which the quadratic model underestimates far from a near-deterministic start":
        dict(search="surrogate"),
    "the line search checks only the KL; it must also check that the surrogate improved (a step "
    "scaled to the KL ball can overshoot a nearby maximum)": dict(search="kl"),
    "the step follows the plain gradient g, scaled to the KL ball; TRPO's direction is "
    "x = (F + damping I)^-1 g, from conjugate gradients on g": dict(direction="gradient"),
    "the step follows the plain gradient g, scaled with the undamped g^T F g; TRPO's direction is "
    "x = (F + damping I)^-1 g, from conjugate gradients on g": dict(direction="gradient, undamped"),
    "the step goes downhill (along -x): the surrogate is to be maximized, so the step is "
    "+sqrt(2 max_kl / g.x) x": dict(direction="negated"),
    "the line search tries backtrack**(k + 1): its first candidate must be the full step, "
    "backtrack**0 = 1": dict(fractions="k+1"),
    "the line search tries backtrack * k (0, then backtrack, 2 backtrack, ...); the fractions are "
    "powers, backtrack**k": dict(fractions="linear"),
    "the step is x = (F + damping I)^-1 g itself, not scaled to the KL ball: multiply it by "
    "sqrt(2 max_kl / g.x), so that 1/2 delta^T (F + damping I) delta = max_kl": dict(scale="none"),
    "the factor 2 is missing: 1/2 delta^T (F + damping I) delta = max_kl gives "
    "delta = sqrt(2 max_kl / g.x) x": dict(scale="no 2"),
    "the step is scaled with the undamped F (1/2 x^T F x); scale it with the damped matrix CG "
    "solved, 1/2 delta^T (F + damping I) delta = max_kl, i.e. delta = sqrt(2 max_kl / g.x) x":
        dict(scale="undamped"),
    "when no step passes the line search, the last one tried is returned; TRPO keeps theta "
    "(return it unchanged)": dict(fallback="last"),
    "the KL is measured the other way round; the constraint is KL(pi_theta || pi_new), the old "
    "policy first (trust.kl(log_prob_fn(theta), log_prob_fn(new)))": dict(kl_side="new || old"),
    "the damping is missing from the Fisher-vector product: CG solves (F + damping I) x = g, so "
    "add damping * v to F v": dict(fvp="undamped"),
    "the Fisher-vector product weights every outcome the same (sum_x s s^T v, without pi(x)); "
    "use your fisher_vector_product, which differentiates the KL": dict(fvp="unweighted"),
    "the Fisher-vector product is zero (the outer product of the expected score, E[s] = 0), so CG "
    "returns g / damping: use your fisher_vector_product": dict(fvp="zero"),
}


def _entropy_regularized_maximum(policy, reward, beta):
    """The objective J + beta * H(pi) and a point near its maximum (natural-gradient ascent from
    the uniform policy, then a small seeded nudge): a step scaled to the KL ball overshoots it."""
    def objective(th):
        logp = policy.log_probs(th)
        return (logp.exp() * (reward - beta * logp)).sum()

    theta = torch.zeros(policy.n_params, dtype=torch.float64)
    for _ in range(100):
        start = theta.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(objective(start), start)
        theta = theta + 0.5 * trust.natural_gradient(trust.fisher_matrix(policy.log_probs, theta), g, 1e-3)
    nudge = 0.05 * torch.randn(policy.n_params, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    return objective, theta + nudge


def _trpo_cases():
    """(label, log_prob_fn, theta, surrogate, keyword arguments) for the TRPO checker. With the
    defaults the reference keeps the full step on the first case, half of it on the second
    (the full step's true KL is about 14 times max_kl, and at half the step KL(new || old), the
    wrong direction, is still above it), an eighth on the third (the surrogate falls for the
    longer steps though their KL is within the ball), and nothing on the fourth (one try)."""
    gen = torch.Generator().manual_seed(7)
    seq, small = trust.SequencePolicy(T=3, V=2), trust.SequencePolicy(T=2, V=2)

    def per_token(policy, theta, n, gen):
        """The per-token surrogate on n samples from pi_theta (lesson 4, section 4)."""
        x = policy.sample(theta, n, gen)
        reward = torch.rand(policy.V ** policy.T, generator=gen, dtype=torch.float64)
        index = (x * policy.V ** torch.arange(policy.T - 1, -1, -1)).sum(-1)
        advantage = reward[index] - reward[index].mean()
        logp_old = policy.token_log_probs(theta, x).detach()
        return lambda th: (torch.exp(policy.token_log_probs(th, x) - logp_old) * advantage[:, None]).sum(-1).mean()

    seq_gen = torch.Generator().manual_seed(2)
    peaked_seq = 2.0 * torch.randn(seq.n_params, generator=seq_gen, dtype=torch.float64)
    # lesson 4's near-deterministic bandit start: most of the probability on one of the worst arms
    logits = 0.3 * torch.randn(5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    logits[3] += 7.0
    sharp_bandit = logits[:4] - logits[4]
    bandit_reward = torch.tensor([1.0, 0.75, 0.5, 0.25, 0.0], dtype=torch.float64)
    bandit_objective = lambda th: trust.objective(trust.bandit_log_probs, th, bandit_reward)   # noqa: E731
    regularized, near_maximum = _entropy_regularized_maximum(small, torch.rand(4, generator=gen, dtype=torch.float64), 0.3)
    return [
        ("a 3-token policy whose full step passes, per-token surrogate on 64 samples", seq.log_probs,
         peaked_seq, per_token(seq, peaked_seq, 64, seq_gen), dict(max_kl=0.01)),
        ("a near-deterministic bandit (the full step's true KL far above max_kl)", trust.bandit_log_probs,
         sharp_bandit, bandit_objective, dict(max_kl=0.05)),
        ("an entropy-regularized objective near its maximum", small.log_probs, near_maximum,
         regularized, dict(max_kl=0.05)),
        ("the near-deterministic bandit with one try allowed (nothing passes)", trust.bandit_log_probs,
         sharp_bandit, bandit_objective, dict(max_kl=0.05, max_backtracks=1)),
        ("non-default arguments (cg_iters 3, damping 0.01, backtrack 0.8)", trust.bandit_log_probs,
         sharp_bandit, bandit_objective,
         dict(max_kl=0.05, cg_iters=3, damping=1e-2, backtrack=0.8, max_backtracks=15)),
    ]


TRPO_DEFAULTS = dict(cg_iters=10, damping=1e-3, backtrack=0.5, max_backtracks=10)


def check_trpo_step(fn: Callable) -> None:
    """``fn(log_prob_fn, theta, surrogate, max_kl, cg_iters, damping, backtrack, max_backtracks)``
    -> the new theta after one TRPO update (``trust.trpo_step``)."""
    name = "trpo_step"
    cases = _trpo_cases()
    answers, wants = [], []
    for label, log_prob_fn, theta, surrogate, kwargs in cases:
        kw = {**TRPO_DEFAULTS, **kwargs}
        args = dict(log_prob_fn=log_prob_fn, theta=theta, surrogate=surrogate, max_kl=kw["max_kl"],
                    **{k: kw[k] for k in TRPO_DEFAULTS})     # in the signature's order
        with _NoFullMatrix(name):
            got = _as_tensor(name, _run(name, fn, args)).detach()
        if got.shape != theta.shape:
            raise ExerciseError(f"{name}: on {label} the result has shape {tuple(got.shape)}; return the "
                                f"new parameters, shaped like theta {tuple(theta.shape)}")
        answers.append(got)
        wants.append(trust.trpo_step(log_prob_fn, theta, surrogate, **kw))
    if all(_close(a, w, 1e-6) for a, w in zip(answers, wants)):
        print(f"✓ {name}: correct (the full step accepted, the KL violated and backtracked, the "
              f"surrogate overshot, nothing accepted, non-default arguments)")
        return
    # a mistake is named when the answer matches that variant on every case
    for message, flags in TRPO_MISTAKES.items():
        if all(_close(a, _trpo_variant(f, th, s, **{**TRPO_DEFAULTS, **kw}, **flags), 1e-6)
               for a, (_, f, th, s, kw) in zip(answers, cases)):
            raise ExerciseError(f"{name}: {message}")
    defaults = [trust.trpo_step(f, th, s, **{**TRPO_DEFAULTS, "max_kl": kw["max_kl"]}) for _, f, th, s, kw in cases]
    if all(_close(a, d, 1e-6) for a, d in zip(answers, defaults)):
        raise ExerciseError(f"{name}: the answer ignores the arguments it is given (cg_iters, damping, "
                            f"backtrack, max_backtracks) and uses the defaults; pass them through")
    for argument, default in TRPO_DEFAULTS.items():
        if all(_close(a, trust.trpo_step(f, th, s, **{**TRPO_DEFAULTS, **kw, argument: default}), 1e-6)
               for a, (_, f, th, s, kw) in zip(answers, cases)):
            raise ExerciseError(f"{name}: the answer does not follow its argument {argument}: on "
                                f"every case it does what {argument}={default} does; use the value "
                                f"it is given")
    label, _, theta, _, _ = cases[next(i for i, (a, w) in enumerate(zip(answers, wants)) if not _close(a, w, 1e-6))]
    i = [c[0] for c in cases].index(label)
    raise ExerciseError(f"{name}: on {label} the new theta differs from TRPO's by up to "
                        f"{(answers[i] - wants[i]).abs().max().item():.3g} (it moved "
                        f"{(answers[i] - theta).norm().item():.3g}, TRPO's step {(wants[i] - theta).norm().item():.3g})")
