"""Which prompts a step trains on: uniform over the pool, or weighted towards unsolved targets.

A prompt's difficulty here is its target digit sum: copying a one-digit target from the
instruction passes, a two-digit one (10-12 in the cpu preset) needs digits that add up to it.
With uniform sampling a solved target keeps taking its share of every batch while an unsolved
one gets the same few samples per step it got at the start. ``TargetPriority`` keeps a running
pass rate per target value from the groups it has sampled and draws the next batch's targets
with weight

    w(t) = floor + (1 - pass_rate(t))

(the prioritized sampling of Kimi k1.5, sec. 2.3.4, per target value instead of per problem), so
an unsolved target is drawn up to (1 + floor) / floor times as often as a solved one, and a
solved target is still seen, so what it learned is kept up. A target never sampled yet counts
as unsolved. The draw is seeded by (seed, step), and the pass rates are saved in each
checkpoint, so a resumed run draws exactly the batches an uninterrupted one would.

``hard_first_steps`` (a curriculum, hardest first) restricts the first ``hard_first_steps``
steps' draw to the targets that need the most digits, still weighted by w(t) among them. Why,
as a hypothesis for the runs to test: the easy targets are solved first by copying the target
into a reply whose length fits one digit ("N don't need..."), and once that shape is learned a
second digit makes the reply one character too long, so two-digit targets stay unsolved. A
shape learned on two-digit targets has room for two digits, and two digits can add up to any
target from 1 to 18. After the curriculum the easy targets, never seen, count as unsolved and
get the full weight. The restriction depends only on the step, so a resume stays exact.

``hard_first_ramp`` lets the other targets in gradually instead: at curriculum step k (counted
from 0) their weights are scaled by k / ``hard_first_steps``, so the first step draws the
hardest targets only and the easy ones reach their full weight as the curriculum ends. Why, as
a second hypothesis: in a run that switched them on all at once, the never-seen easy targets
took most of the next batches and the policy dropped the shape it had found for the hard ones.
"""

from __future__ import annotations

import torch

from . import data
from .rewards import digits_needed


class TargetPriority:
    """Running pass rate per target digit sum, and batches drawn by ``w(t)`` (module docstring)."""

    def __init__(self, prompts: list[data.Prompt], floor: float = 0.1, momentum: float = 0.8):
        if not floor > 0:
            raise ValueError(f"floor must be > 0 so every target keeps some weight, got {floor}")
        if not 0 <= momentum < 1:
            raise ValueError(f"momentum must be in [0, 1), got {momentum}")
        if not prompts:
            raise ValueError("prioritized sampling needs at least one training prompt")
        self.floor, self.momentum = floor, momentum
        self.by_target: dict[int, list[data.Prompt]] = {}
        for p in prompts:
            self.by_target.setdefault(p.target_digit_sum, []).append(p)
        self.targets = sorted(self.by_target)
        self.pass_rate: dict[int, float] = {t: 0.0 for t in self.targets}
        self.seen: dict[int, bool] = {t: False for t in self.targets}

    def weights(self) -> torch.Tensor:
        return torch.tensor([self.floor + 1.0 - self.pass_rate[t] for t in self.targets],
                            dtype=torch.float64)

    def hardest(self) -> list[int]:
        """The pool's targets that need the most digits (``rewards.digits_needed``)."""
        most = max(digits_needed(t) for t in self.targets)
        return [t for t in self.targets if digits_needed(t) == most]

    def batch(self, seed: int, step: int, size: int, only: list[int] | None = None,
              others_scale: float = 0.0) -> list[data.Prompt]:
        """``size`` prompts: each a target drawn by weight, then a prompt with that target.
        With ``only``, the other targets' weights are scaled by ``others_scale`` (0: ``only``'s
        targets alone)."""
        g = torch.Generator().manual_seed(seed * 1_000_003 + step)
        weights = self.weights()
        if only is not None:
            if not set(only) & set(self.targets):
                raise ValueError(f"only={only}: none of these targets is in the pool {self.targets}")
            if not 0 <= others_scale <= 1:
                raise ValueError(f"others_scale must be in [0, 1], got {others_scale}")
            weights = weights * torch.tensor([1.0 if t in only else others_scale for t in self.targets],
                                             dtype=weights.dtype)
        picks = torch.multinomial(weights, size, replacement=True, generator=g).tolist()
        out = []
        for k in picks:
            pool = self.by_target[self.targets[k]]
            out.append(pool[int(torch.randint(len(pool), (1,), generator=g))])
        return out

    def observe(self, prompts: list[data.Prompt], passed: torch.Tensor, group_size: int) -> None:
        """Update the pass rates from one step's groups (``passed`` holds G flags per prompt):
        one update per target value and step, from all of that step's samples of it, so the
        result does not depend on the order of the groups in the batch."""
        flags = passed.float().view(len(prompts), group_size)
        this_step: dict[int, list[float]] = {}
        for p, row in zip(prompts, flags):
            this_step.setdefault(p.target_digit_sum, []).extend(row.tolist())
        for t, values in this_step.items():
            if t not in self.pass_rate:
                continue
            rate = sum(values) / len(values)
            # the first observation replaces the prior of 0 rather than averaging with it
            m = self.momentum if self.seen[t] else 0.0
            self.pass_rate[t] = m * self.pass_rate[t] + (1 - m) * rate
            self.seen[t] = True

    def state_dict(self) -> dict:
        return dict(pass_rate=dict(self.pass_rate), seen=dict(self.seen))

    def load_state_dict(self, state: dict) -> None:
        """Restore the pass rates of this pool's targets; one the checkpoint never saw starts
        unseen, and one the pool no longer has is dropped."""
        for t in self.targets:
            if str(t) in state["pass_rate"] or t in state["pass_rate"]:
                key = t if t in state["pass_rate"] else str(t)
                self.pass_rate[t] = float(state["pass_rate"][key])
                self.seen[t] = bool(state["seen"][key])
