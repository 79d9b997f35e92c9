"""The learner tracks' own arithmetic (the experiments themselves run, shrunk, in lesson 8)."""
import math

import pytest

from course_utils import tracks


def test_exact_grouping_matches_what_can_be_derived_by_hand():
    result = tracks.exact_grouping(group_size=8, batches=20_000, seed=0)
    dr = result["estimators"]["per-prompt mean only (Dr. GRPO)"]
    # the group mean includes the sample itself, so within each prompt the average estimate is
    # exactly (G - 1) / G of that prompt's gradient: the best rescaling is G / (G - 1) = 8/7
    assert dr["rescale"] == pytest.approx(8 / 7, rel=0.03)
    assert dr["direction_error"] < 0.05 and dr["cosine"] > 0.998
    grpo = result["estimators"]["per-prompt mean and std (GRPO)"]
    # dividing by each group's std reweights prompts: a direction error beyond Monte Carlo noise
    assert grpo["direction_error"] > 2 * dr["direction_error"]
    assert max(grpo["weight_per_prompt"]) / min(grpo["weight_per_prompt"]) > 1.1
    # per-prompt baselines are less noisy than one baseline for the whole batch
    batch = result["estimators"]["whole-batch mean only"]
    assert dr["noise_to_signal"] < batch["noise_to_signal"]


def test_the_verdict_needs_two_standard_errors():
    assert "no difference detected" in tracks.differs([1.0, 1.2, 0.8], [1.1, 0.9, 1.0])
    assert "a real difference" in tracks.differs([1.0, 1.01, 0.99], [2.0, 2.01, 1.99])
    assert tracks.differs([1.0], [2.0]) == "too few seeds to tell"


def test_steps_to_threshold_uses_the_moving_average(tmp_path):
    import json
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps({"step": i + 1, "reward_mean": v}) + "\n"
                                                    for i, v in enumerate([0.1, 0.9, 0.2, 0.7, 0.8, 0.9])))
    # 3-step averages: 0.1, 0.5, 0.4, 0.6, 0.567, 0.8 (the single 0.9 at step 2 is not enough)
    assert tracks.steps_to(tmp_path, "reward_mean", 0.6, smooth=3) == 4
    assert tracks.steps_to(tmp_path, "reward_mean", 0.61, smooth=3) == 6
    assert math.isinf(tracks.steps_to(tmp_path, "reward_mean", 0.95))
