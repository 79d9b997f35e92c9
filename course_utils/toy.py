"""Small problems where the exact answer is known, for the lessons.

* A softmax bandit: J(theta) = sum_a pi_theta(a) r(a), with the exact gradient in closed form.
* A tiny character-level policy for the course's rule task: given a prompt (target length L,
  target digit sum S) it writes characters from ``VOCAB`` until it emits EOS. The same rule
  checker as the real task (``course_utils.rewards``) scores it, so everything learned on this
  toy carries over. It trains in seconds on a CPU, so lessons can compare methods over seeds.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from . import losses, rewards
from .rollout import completion_mask

# ----------------------------------------------------------------------------------------------
# A bandit with an exact gradient
# ----------------------------------------------------------------------------------------------


def bandit_objective(theta: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
    """J(theta) = sum_a softmax(theta)_a r_a: the expected reward, computed exactly."""
    return (torch.softmax(theta, -1) * reward).sum(-1)


def bandit_exact_gradient(theta: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
    """dJ/dtheta_k = pi_k (r_k - J), from d pi_a / d theta_k = pi_a (1[a = k] - pi_k)."""
    pi = torch.softmax(theta, -1)
    return pi * (reward - (pi * reward).sum(-1, keepdim=True))


# ----------------------------------------------------------------------------------------------
# The character task
# ----------------------------------------------------------------------------------------------

VOCAB = list("0123456789ab")
EOS = len(VOCAB)                     # token id of end-of-sequence
VOCAB_SIZE = len(VOCAB) + 1
LENGTHS = range(2, 9)                # target lengths a prompt may ask for
DIGIT_SUMS = range(1, 19)            # target digit sums a prompt may ask for


def decode(tokens: torch.Tensor, mask: torch.Tensor) -> list[str]:
    """Characters up to (not including) EOS."""
    return ["".join(VOCAB[t] for t, m in zip(row.tolist(), mrow.tolist()) if m and t != EOS)
            for row, mrow in zip(tokens, mask)]


def random_prompts(n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """[n, 2] prompts (target length, target digit sum), uniform over the allowed ranges."""
    L = torch.randint(LENGTHS.start, LENGTHS.stop, (n,), generator=generator)
    S = torch.randint(DIGIT_SUMS.start, DIGIT_SUMS.stop, (n,), generator=generator)
    return torch.stack([L, S], -1)


def score_texts(texts: list[str], prompts: torch.Tensor, kind: str = "shaped") -> torch.Tensor:
    """Rewards from the course's rule checker, targets from the prompts."""
    fn = rewards.get_reward_fn(kind)
    values = fn(prompts=None, completions=texts, target_chars=prompts[:, 0].tolist(),
                target_digit_sum=prompts[:, 1].tolist())
    return torch.tensor(values)


class CharPolicy(nn.Module):
    """pi_theta(token_t | prompt, tokens_<t): a GRU over characters, started from the prompt."""

    def __init__(self, hidden: int = 64, max_len: int = 10):
        super().__init__()
        self.max_len = max_len
        self.length_embedding = nn.Embedding(LENGTHS.stop, hidden)
        self.sum_embedding = nn.Embedding(DIGIT_SUMS.stop, hidden)
        self.token_embedding = nn.Embedding(VOCAB_SIZE + 1, hidden)  # + a start token
        self.gru = nn.GRU(hidden, hidden, batch_first=True)
        self.head = nn.Linear(hidden, VOCAB_SIZE)

    def _initial_state(self, prompts: torch.Tensor) -> torch.Tensor:
        """The GRU's starting state encodes the prompt (target length, target digit sum)."""
        h0 = torch.tanh(self.length_embedding(prompts[:, 0]) + self.sum_embedding(prompts[:, 1]))
        return h0.unsqueeze(0).contiguous()

    def _logits(self, prompts: torch.Tensor, inputs: torch.Tensor) -> torch.Tensor:
        out, _ = self.gru(self.token_embedding(inputs), self._initial_state(prompts))
        return self.head(out)

    @torch.no_grad()
    def sample(self, prompts: torch.Tensor, generator: torch.Generator | None = None,
               greedy: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Sample one sequence per prompt. Returns (tokens [N, T], completion mask [N, T])."""
        n = prompts.shape[0]
        h = self._initial_state(prompts)
        token = torch.full((n,), VOCAB_SIZE)  # start token
        tokens = []
        for _ in range(self.max_len):
            out, h = self.gru(self.token_embedding(token).unsqueeze(1), h)
            logits = self.head(out[:, 0])
            token = logits.argmax(-1) if greedy else torch.multinomial(
                torch.softmax(logits, -1), 1, generator=generator).squeeze(-1)
            tokens.append(token)
        tokens = torch.stack(tokens, -1)
        return tokens, completion_mask(tokens, [EOS])

    def log_probs(self, prompts: torch.Tensor, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Teacher-forced log pi(token_t | ...) [N, T] with autograd, and the entropy [N, T]."""
        start = torch.full((tokens.shape[0], 1), VOCAB_SIZE)
        logits = self._logits(prompts, torch.cat([start, tokens[:, :-1]], -1))
        logp = F.log_softmax(logits, -1)
        return logp.gather(-1, tokens.unsqueeze(-1)).squeeze(-1), losses.token_entropy(logits)


def train_toy(method: str, steps: int = 200, prompts_per_step: int = 16, group_size: int = 8,
              lr: float = 3e-3, seed: int = 0, reward: str = "shaped",
              eval_every: int = 10, updates_per_batch: int = 1, eps_low: float = 0.2,
              eps_high: float = 0.2) -> dict[str, list[float]]:
    """Train a fresh CharPolicy with one method on the same budget of samples per step.

    method: "reinforce" (no baseline), "batch_mean", "rloo" (leave-one-out within the group),
    or "grpo" (group mean and std, in GRPO's clipped objective averaged over each completion's
    tokens; with one update per batch the ratio is 1 and the clip never binds). The other three
    use the REINFORCE loss summed over tokens. Every method sees prompts_per_step x group_size samples per
    step, so the comparison is on equal terms. Returns the curves: mean training reward and the
    held-out greedy pass rate (both constraints) every ``eval_every`` steps.

    ``updates_per_batch`` > 1 (GRPO only) reuses each batch for several updates, as PPO does:
    pi_old is then the sampling policy, the ratio moves away from 1 and the clip
    [1 - eps_low, 1 + eps_high] binds (``eps_low = eps_high = inf`` switches it off). The curves
    then also hold, per step, the clip fraction (mean over the updates) and the KL from the
    sampling policy to the updated one (the k3 estimate over the batch's tokens, after the last
    update).
    """
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    policy = CharPolicy()
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    held_out = random_prompts(256, torch.Generator().manual_seed(10_000 + seed))
    if updates_per_batch > 1 and method != "grpo":
        raise ValueError("updates_per_batch > 1 needs the clipped objective: method='grpo'")
    history: dict[str, list[float]] = {"step": [], "reward": [], "eval_step": [], "eval_pass": [],
                                       "clip_fraction": [], "kl_to_sampler": []}
    for step in range(steps):
        prompts = random_prompts(prompts_per_step, gen).repeat_interleave(group_size, 0)
        tokens, mask = policy.sample(prompts, gen)
        r = score_texts(decode(tokens, mask), prompts, reward)
        if method == "reinforce":
            weights = r
        elif method == "batch_mean":
            weights = r - losses.batch_mean_baseline(r)
        elif method == "rloo":
            weights = r - losses.leave_one_out_baseline(r, group_size)
        elif method == "grpo":
            weights, _ = losses.group_advantages(r, group_size)
        else:
            raise ValueError(f"unknown method {method!r}")
        if method == "grpo":  # the objective of lesson 5, section 1: ratio, clip and 1/|o_i|
            old = None
            clipped = 0.0
            for _ in range(updates_per_batch):
                logp, _ = policy.log_probs(prompts, tokens)
                old = logp.detach() if old is None else old   # pi_old: the sampling policy
                loss, stats = losses.grpo_loss(logp, old, weights, mask, loss_type="grpo",
                                               eps_low=eps_low, eps_high=eps_high)
                clipped += stats["clip_fraction"] / updates_per_batch
                opt.zero_grad()
                loss.backward()
                opt.step()
            with torch.no_grad():
                logp, _ = policy.log_probs(prompts, tokens)
            history["clip_fraction"].append(clipped)
            # k3 of KL(pi_old || pi_theta) on tokens drawn from pi_old: r - 1 - log r, r = pi/pi_old
            history["kl_to_sampler"].append(losses.masked_mean(losses.k3_kl(old, logp), mask))
        else:
            logp, _ = policy.log_probs(prompts, tokens)
            loss = losses.reinforce_loss(logp, weights, mask)
            opt.zero_grad()
            loss.backward()
            opt.step()
        history["step"].append(step + 1)
        history["reward"].append(float(r.mean()))
        if (step + 1) % eval_every == 0 or step == 0:
            history["eval_step"].append(step + 1)
            history["eval_pass"].append(evaluate_toy(policy, held_out))
    history["policy"] = policy  # type: ignore[assignment]
    return history


@torch.no_grad()
def evaluate_toy(policy: CharPolicy, prompts: torch.Tensor) -> float:
    """Greedy pass rate (both constraints) on the given prompts."""
    tokens, mask = policy.sample(prompts, greedy=True)
    return float(score_texts(decode(tokens, mask), prompts, "binary").mean())
