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


def test_the_verdict_is_paired_by_seed():
    assert "no difference detected" in tracks.differs([1.0, 1.2, 0.8], [1.1, 0.9, 1.0])
    # arms that differ by the same amount on every seed: unpaired, the seeds' spread would hide it
    a = [0.2, 0.9, 0.5, 0.1, 0.7, 0.4]
    text = tracks.differs([x + 0.05 + 0.001 * i for i, x in enumerate(a)], a)
    assert text.endswith("excludes 0: a difference") and "per-seed differences" in text
    assert tracks.differs([1.0], [2.0]) == "too few seeds to tell"
    with pytest.raises(ValueError, match="same seeds"):
        tracks.differs([1.0, 2.0], [1.0, 2.0, 3.0])


@pytest.mark.parametrize("track", sorted(tracks.VERDICTS))
def test_stored_track_verdicts_are_recomputed_from_their_results(track, tmp_path):
    """Each stored report's comparison lines are what the paired helper says about its stored
    per-seed values: re-rendering changes nothing, and is idempotent."""
    import shutil
    from pathlib import Path

    stored = Path(__file__).resolve().parents[1] / "notebooks" / "results" / "tracks" / track
    copy = tmp_path / track
    shutil.copytree(stored, copy)
    assert tracks.rerender_verdicts(track, copy) == (stored / "report.md").read_text()
    assert tracks.rerender_verdicts(track, copy) == (stored / "report.md").read_text()
    assert "standard errors" not in (stored / "report.md").read_text()   # no unpaired verdict left


def test_steps_to_threshold_uses_the_moving_average(tmp_path):
    import json
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps({"step": i + 1, "reward_mean": v}) + "\n"
                                                    for i, v in enumerate([0.1, 0.9, 0.2, 0.7, 0.8, 0.9])))
    # 3-step averages: 0.1, 0.5, 0.4, 0.6, 0.567, 0.8 (the single 0.9 at step 2 is not enough)
    assert tracks.steps_to(tmp_path, "reward_mean", 0.6, smooth=3) == 4
    assert tracks.steps_to(tmp_path, "reward_mean", 0.61, smooth=3) == 6
    assert math.isinf(tracks.steps_to(tmp_path, "reward_mean", 0.95))


# --- the retrieval track ---------------------------------------------------------------------

def test_the_score_function_splits_into_the_retriever_s_and_the_generator_s_gradient():
    import torch

    from course_utils import retrieval

    g = torch.Generator().manual_seed(0)
    for K, Y in ((2, 2), (3, 5), (6, 3)):
        phi, theta = torch.randn(K, generator=g, dtype=torch.float64), torch.randn(K, Y, generator=g, dtype=torch.float64)
        reward = torch.rand(Y, generator=g, dtype=torch.float64)
        for part, exact in zip(retrieval.score_function_parts(phi, theta, reward),
                               retrieval.exact_gradients(phi, theta, reward)):
            assert torch.allclose(part, exact, atol=1e-14)


def test_baselines_what_each_part_may_subtract():
    """Group mean: both parts shrink by (G-1)/G (lesson 3). Leave-one-out: unbiased. A
    per-document mean: the generator's part stays unbiased, the retriever's loses its signal.
    The cross-document estimate: unbiased, and less noisy than leave-one-out."""
    result = tracks.exact_retrieval(batches=20_000, group=8, seed=1)
    rows = result["baselines"]
    assert result["split_error"] < 1e-14
    for part in ("retriever", "generator"):
        assert rows["group mean"][part]["bias"] == pytest.approx(1 / 8, abs=4 * rows["group mean"][part]["bias_se"])
        assert rows["leave-one-out"][part]["bias"] < 4 * rows["leave-one-out"][part]["bias_se"]
    assert rows["per-document mean"]["generator"]["bias"] < 4 * rows["per-document mean"]["generator"]["bias_se"]
    assert rows["per-document mean"]["retriever"]["bias"] > 0.5
    cross = rows["cross-document (retriever only)"]["retriever"]
    assert cross["bias"] < 4 * cross["bias_se"]
    assert cross["noise"] < rows["leave-one-out"]["retriever"]["noise"]


def test_the_per_document_baseline_leaves_out_the_rollout_itself():
    import torch

    from course_utils import retrieval

    r = torch.tensor([[1.0, 0.0, 1.0, 0.5]])
    d = torch.tensor([[0, 0, 1, 0]])
    # rollout 0: the others with document 0 are rollouts 1 and 3; rollout 2 is alone (baseline 0)
    assert retrieval.baseline_values(r, d, 2, "per-document mean").tolist() == [[0.25, 0.75, 0.0, 0.5]]


@pytest.mark.parametrize("target_chars", [20, 32, 48])
def test_the_passing_example_document_passes_the_checker_for_every_target(target_chars):
    for digit_sum in range(0, 19):
        reply = tracks.valid_reply(target_chars, digit_sum)
        assert tracks.train.rewards.check(reply, target_chars, digit_sum).passed, (reply, digit_sum)


def test_rerendering_a_report_without_its_comparison_lines_is_refused(tmp_path):
    (tmp_path / "result.json").write_text('{"final_reward": {}}')
    (tmp_path / "report.md").write_text("a table, and no verdict\n")
    with pytest.raises(ValueError, match="no comparison line"):
        tracks.rerender_verdicts("grouping", tmp_path)
