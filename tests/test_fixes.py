"""The levers against reward hacking and signal loss (issue 11): the sharp reward, DAPO's dynamic
sampling and overlong filtering. Each is checked for numbers: exact values, batch size,
gradients against a second computation, and bitwise resume."""
import pytest
import torch

from course_utils import rewards, train
from course_utils.config import load_config
from course_utils.data import Prompt
from course_utils.losses import group_advantages
from course_utils.rollout import completion_logprobs, concat_rollouts, rollout


# --- the sharp reward ----------------------------------------------------------------------------

@pytest.mark.parametrize("text, target_chars, target_sum, expected", [
    ("a" * 32, 32, 0, 1.0),                                       # both exact
    ("a" * 31, 32, 0, 2 / 3 * (0.5 * 32 / 33 + 0.5)),             # one character short: no pass
    ("a" * 30, 32, 0, 2 / 3 * (0.5 * 32 / 34 + 0.5)),             # the 30-character template
    ("12" + "a" * 30, 32, 3, 1.0),                                # digits 1 + 2 = 3
    ("9" + "a" * 31, 32, 7, 2 / 3 * (0.5 + 0.5 * 7 / 9)),          # exact length alone earns no bonus
    ("", 4, 2, 2 / 3 * (0.5 * 0.5 + 0.5 * 0.5)),
    ("a" * 130, 32, 0, 2 / 3 * (0.5 / (1 + 98 / 32) + 0.5)),
])
def test_sharp_reward_by_hand(text, target_chars, target_sum, expected):
    got = rewards.sharp_reward(None, [text], target_chars=[target_chars], target_digit_sum=[target_sum])
    assert got == [pytest.approx(expected)]


def test_sharp_reward_is_one_exactly_when_binary_is_and_ranks_a_hit_clearly_above_a_near_miss():
    g = torch.Generator().manual_seed(0)
    texts = ["".join(chr(int(c)) for c in torch.randint(48, 123, (int(n),), generator=g))
             for n in torch.randint(0, 40, (400,), generator=g)]
    chars = [int(x) for x in torch.randint(1, 40, (400,), generator=g)]
    sums = [int(x) for x in torch.randint(0, 30, (400,), generator=g)]
    sharp = rewards.sharp_reward(None, texts, target_chars=chars, target_digit_sum=sums)
    binary = rewards.binary_reward(None, texts, target_chars=chars, target_digit_sum=sums)
    assert all((s == 1.0) == (b == 1.0) for s, b in zip(sharp, binary))
    assert all(0 < s <= 1 for s in sharp)
    # the 30-character template: the shaped reward pays it 0.97, the sharp one 0.65
    two_short = dict(target_chars=[32], target_digit_sum=[0])
    assert rewards.shaped_reward(None, ["a" * 30], **two_short)[0] > 0.96
    assert rewards.sharp_reward(None, ["a" * 30], **two_short)[0] < 0.65
    # far misses stay ordered (the relative part): 100 characters over beats 120 over
    far = rewards.sharp_reward(None, ["a" * 132, "a" * 152], **{k: v * 2 for k, v in two_short.items()})
    assert far[0] > far[1]


# --- joining rollouts ----------------------------------------------------------------------------

def test_concatenated_rollouts_give_the_same_logprobs_and_gradients(tiny_model, tokenizer):
    """Dynamic sampling trains on groups picked from different sampling rounds, re-padded to a
    common width. Padding must change nothing: values and gradients as for each part alone."""
    gens = [torch.Generator().manual_seed(s) for s in (1, 2)]
    a = rollout(tiny_model, tokenizer, ["One two three four five six", "Hi"], group_size=3,
                max_new_tokens=7, eos_ids=[tokenizer.eos_token_id], generator=gens[0])
    b = rollout(tiny_model, tokenizer, ["A much longer prompt than the others, with more words"],
                group_size=3, max_new_tokens=4, eos_ids=[tokenizer.eos_token_id], generator=gens[1])
    picked = [a.select_groups([1]), b, a.select_groups([0])]
    joined = concat_rollouts(picked, tokenizer.pad_token_id)
    assert joined.completion_ids.shape[0] == 9 and joined.texts == [t for p in picked for t in p.texts]

    def lp_and_grad(ro):
        tiny_model.zero_grad()
        lp, _ = completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                    ro.completion_mask, group_size=3)
        (lp * ro.completion_mask).sum().backward()
        return lp, torch.cat([p.grad.flatten().clone() for p in tiny_model.parameters()])

    lp_joined, grad_joined = lp_and_grad(joined)
    grad_parts = 0
    for k, part in enumerate(picked):
        lp, grad = lp_and_grad(part)
        rows = slice(3 * k, 3 * k + 3)
        T = part.completion_ids.shape[1]
        assert torch.allclose(lp * part.completion_mask, lp_joined[rows, :T] * joined.completion_mask[rows, :T], atol=1e-5)
        assert (joined.completion_mask[rows, T:] == 0).all()
        assert torch.allclose(part.logprobs, joined.logprobs[rows, :T])
        grad_parts = grad_parts + grad
    err = (grad_joined - grad_parts).norm() / grad_parts.norm()
    assert err < 1e-5, err


# --- dynamic sampling ----------------------------------------------------------------------------

def _prompts(sums):
    return [Prompt(text=f"Prompt number {i} says {'more ' * i}", snippet=str(i), target_chars=48,
                   target_digit_sum=s) for i, s in enumerate(sums)]


def _flat_on_odd_targets(prompts, completions, target_digit_sum, **kw):
    """A reward with no signal for prompts whose target is odd: their groups are all 0.5."""
    return [0.5 if s % 2 else float(len(c) % 5) for c, s in zip(completions, target_digit_sum)]


def test_dynamic_sampling_keeps_the_batch_size_and_only_groups_with_signal(monkeypatch):
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", _flat_on_odd_targets)
    policy = train.setup(load_config("smoke", dynamic_sampling=True, max_sampling_rounds=5))
    first = _prompts([3, 4])          # one group without signal (odd), one with
    fresh = {1: _prompts([5, 7]), 2: _prompts([6, 9]), 3: _prompts([8, 8])}
    asked = []

    def refill(k):
        asked.append(k)
        return fresh[k]

    ro, kept, sampled, rounds, _ = train.sample_batch(policy, first, refill)
    assert [p.target_digit_sum for p in kept] == [4, 6]   # round 2 supplied the second one
    assert asked == [1, 2] and rounds == 3 and sampled == 6
    assert ro.completion_ids.shape[0] == 2 * policy.cfg.group_size
    r = torch.tensor(train.score([p for p in kept for _ in range(4)], ro.texts, "shaped")["rewards"])
    assert group_advantages(r, 4)[1] == 0                   # no zero-std group was kept


def test_dynamic_sampling_fills_a_short_batch_with_groups_without_signal(monkeypatch):
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", _flat_on_odd_targets)
    policy = train.setup(load_config("smoke", dynamic_sampling=True, max_sampling_rounds=2))
    ro, kept, sampled, rounds, _ = train.sample_batch(policy, _prompts([3, 5]), lambda k: _prompts([7, 4]))
    # 2 rounds: one group with signal (target 4) found; the batch is filled with the first spare
    assert [p.target_digit_sum for p in kept] == [4, 3] and sampled == 4 and rounds == 2
    metrics = train.grpo_step(policy, _prompts([3, 5]), refill=lambda k: _prompts([7, 4]))
    assert metrics["zero_std_frac"] == 0.5 and metrics["groups_sampled"] == 4


def test_dynamic_sampling_off_samples_once_and_needs_no_refill():
    policy = train.setup(load_config("smoke"))
    ro, kept, sampled, rounds, _ = train.sample_batch(policy, _prompts([3, 4]))
    assert (sampled, rounds) == (2, 1) and ro.completion_ids.shape[0] == 8


def test_dynamic_sampling_with_accumulation_gives_the_full_batch_gradient(monkeypatch):
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", _flat_on_odd_targets)
    grads = []
    for accum in (1, 2):
        policy = train.setup(load_config("smoke", dynamic_sampling=True, grad_accum=accum))
        policy.optimizer.step = lambda *a, **k: None
        metrics = train.grpo_step(policy, _prompts([3, 4]), refill=lambda k: _prompts([5, 6]))
        assert metrics["groups_sampled"] == 4 and metrics["zero_std_frac"] == 0
        grads.append(torch.cat([p.grad.flatten() for p in policy.model.parameters()]))
    assert grads[0].abs().max() > 0
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-8)


def test_dynamic_sampling_resumes_bitwise(resume_pair, monkeypatch):
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", _flat_on_odd_targets)
    (ra, rb), (a, b) = resume_pair(dynamic_sampling=True, overlong_filter=True, digit_sum_min=3,
                                   digit_sum_max=6)
    assert sum(r["groups_sampled"] for r in ra) > 4 * 2      # refills happened
    strip = lambda rs: [{k: v for k, v in r.items() if "time" not in k and k != "tokens_per_s"} for r in rs]
    assert strip(ra) == strip(rb)
    assert all(torch.equal(a[k], b[k]) for k in a)


def _always_varied(prompts, completions, **kw):
    """Rewards 0, 1, 2, ... inside every group: no group is ever without signal."""
    return [float(i % 4) for i in range(len(completions))]


def test_dynamic_sampling_that_never_triggers_leaves_the_run_bitwise_unchanged(tmp_path, monkeypatch):
    """Until some group's rewards are all equal, a run with dynamic sampling is the run without
    it, step for step: the ablation's reading of a seed on which it never triggered rests on this."""
    from safetensors.torch import load_file

    from course_utils import checkpoint
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", _always_varied)
    runs = {}
    for on in (True, False):
        out = tmp_path / f"ds-{on}"
        train.train(load_config("smoke", dynamic_sampling=on, out_dir=str(out)), progress=False)
        runs[on] = (checkpoint.MetricsLog(out / "metrics.jsonl").read(),
                    load_file(str(out / "checkpoint" / "model.safetensors")))
    (log_on, params_on), (log_off, params_off) = runs[True], runs[False]
    assert all(r["groups_sampled"] == 2 and r["sampling_rounds"] == 1 for r in log_on)
    assert all(torch.equal(params_on[k], params_off[k]) for k in params_on)
    same = lambda rs: [{k: v for k, v in r.items() if "time" not in k and k != "tokens_per_s"} for r in rs]  # noqa: E731
    assert same(log_on) == same(log_off)


def test_refill_batches_are_seeded_by_step_and_round():
    cfg = load_config("smoke")
    prompts = _prompts(range(3, 13))
    a, b = train.refill_batch(5, 1, prompts, cfg), train.refill_batch(5, 1, prompts, cfg)
    assert a == b and len(a) == cfg.prompts_per_step
    assert train.refill_batch(5, 2, prompts, cfg) != a or train.refill_batch(6, 1, prompts, cfg) != a


# --- overlong filtering --------------------------------------------------------------------------

def test_overlong_filter_gives_truncated_completions_no_gradient(monkeypatch):
    """With every completion truncated (max_new_tokens=1, no EOS yet), the filtered loss has no
    token left: the gradient is exactly zero. Without the filter it is not."""
    monkeypatch.setitem(train.rewards.REWARDS, "shaped",
                        lambda prompts, completions, **kw: [float(i % 3) for i in range(len(completions))])
    norms = {}
    for flag in (False, True):
        policy = train.setup(load_config("smoke", overlong_filter=flag, max_new_tokens=1))
        policy.optimizer.step = lambda *a, **k: None
        metrics = train.grpo_step(policy, _prompts([3, 4]))
        assert metrics["truncated_frac"] == 1.0
        norms[flag] = sum(float(p.grad.norm()) for p in policy.model.parameters() if p.grad is not None)
    assert norms[False] > 0 and norms[True] == 0.0


def test_overlong_filter_equals_dropping_the_truncated_rows_from_the_loss(tiny_model, tokenizer):
    """The filtered loss (GRPO aggregation, N counts every sequence) against a hand computation
    over the finished rows only."""
    from course_utils.losses import grpo_loss
    g = torch.Generator().manual_seed(3)
    ro = rollout(tiny_model, tokenizer, ["Some words here", "More"], group_size=4, max_new_tokens=6,
                 eos_ids=[tokenizer.eos_token_id], generator=g)
    ro.truncated = torch.tensor([1, 0, 0, 1, 0, 1, 0, 0]).bool()  # which rows count as cut off
    adv = torch.randn(8, generator=g)
    lp, _ = completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                ro.completion_mask, group_size=4)
    keep = (~ro.truncated).float()
    lp = lp.detach().requires_grad_()
    loss, _ = grpo_loss(lp, lp.detach(), adv, ro.completion_mask * keep[:, None], loss_type="grpo")
    m = ro.completion_mask.float()
    # on-policy the ratio is 1: the loss is -mean(A) over the finished rows (N counts all rows),
    # and its gradient with respect to a token's log-prob is -A / (N |o_i|) there, 0 elsewhere
    assert torch.allclose(loss, -(keep * adv).sum() / 8, atol=1e-6)
    loss.backward()
    expected = -(keep * adv / m.sum(-1))[:, None] * m / 8
    assert torch.allclose(lp.grad, expected, atol=1e-7)
    assert (lp.grad[ro.truncated] == 0).all()


# --- what the evaluation reports -----------------------------------------------------------------

def test_evaluation_splits_targets_by_kind_and_counts_distinct_completions(monkeypatch):
    policy = train.setup(load_config("smoke"))
    prompts = [Prompt(text=f"Text {i}", snippet=f"s{i % 2}", target_chars=3, target_digit_sum=t)
               for i, t in enumerate([5, 11, 7, 12, 3])]
    fixed = iter(["a5b", "a5b", "xy7", "39z", "3ab"])  # what the "model" writes, prompt by prompt

    def fake_rollout(model, tokenizer, texts, **kw):
        class R:
            pass
        r = R()
        r.texts = [next(fixed) for _ in texts]
        return r

    monkeypatch.setattr(train, "rollout", fake_rollout)
    ev = train.evaluate(policy.model, policy.tokenizer, prompts, policy.cfg, policy.eos_ids, greedy=True)
    # one-digit targets 5, 7, 3: "a5b" passes, "xy7" passes, "3ab" passes -> 3 of 3
    # two-digit targets 11, 12: "a5b" fails (5), "39z" passes (12) -> 1 of 2
    assert (ev["n_one_digit"], ev["n_two_digit"]) == (3, 2)
    assert ev["pass_both_one_digit"] == 1.0 and ev["pass_both_two_digit"] == 0.5
    assert ev["pass_both"] == pytest.approx(4 / 5)
    assert ev["distinct_completions"] == 4 and ev["distinct_snippets"] == 2


# --- the ablation runner -------------------------------------------------------------------------

def test_ablation_runs_every_arm_and_reports_each_number_from_its_runs(tmp_path, monkeypatch):
    import json

    from course_utils import ablation
    monkeypatch.setattr(ablation, "RUNS", tmp_path / "runs")
    result = ablation.ablation([0, 1], tmp_path / "out")
    assert set(result["arms"]) == set(ablation.ARMS)
    stored = json.loads((tmp_path / "out" / "result.json").read_text())
    report = (tmp_path / "out" / "report.md").read_text()
    for arm, row in stored["arms"].items():
        assert len(row["runs"]) == 2 and arm in report
        for run in row["runs"]:
            assert 0 <= run["pass_both"] <= 1 and run["steps"] >= 1 and run["seconds"] > 0
    assert (tmp_path / "out" / "curves.png").exists()
    # the second call reuses the finished runs: nothing is trained again
    monkeypatch.setattr(ablation.train, "train", lambda *a, **k: pytest.fail("retrained a finished run"))
    ablation.ablation([0, 1], tmp_path / "out2")
    # report only: seed 2 never ran, so every arm reports the seeds it has, and trains nothing
    partial = ablation.ablation([0, 1, 2], tmp_path / "out3", train_missing=False)
    assert all(len(row["runs"]) == 2 for row in partial["arms"].values())
    assert "| 0, 1 |" in (tmp_path / "out3" / "report.md").read_text()


def test_until_something_passes_sharp_gives_the_advantages_of_shaped():
    """GRPO standardizes each group, so a common factor cancels: while no completion passes,
    training on 'sharp' is training on 'shaped'."""
    g = torch.Generator().manual_seed(1)
    texts = ["7" * int(n) + " x" * int(k) for n, k in torch.randint(0, 12, (16, 2), generator=g)]
    texts = [t for t in texts if len(t.strip()) != 32][:16]
    kw = dict(target_chars=[32] * len(texts), target_digit_sum=[7] * len(texts))
    G = 4
    n = len(texts) // G * G
    # eps (1e-4 in training, added to the std) is the one thing not scaled by 2/3: set it tiny
    sharp = torch.tensor(rewards.sharp_reward(None, texts, **kw), dtype=torch.float64)[:n]
    shaped = torch.tensor(rewards.shaped_reward(None, texts, **kw), dtype=torch.float64)[:n]
    a_sharp, _ = group_advantages(sharp, G, eps=1e-12)
    a_shaped, _ = group_advantages(shaped, G, eps=1e-12)
    assert torch.allclose(a_sharp, a_shaped, atol=1e-9)
    assert a_shaped.abs().max() > 0.5


def test_diagnosis_of_the_stored_reward_hacking_run():
    """lesson 7's table of signs, checked against the stored files read independently."""
    import json
    from pathlib import Path

    from course_utils import ablation
    run = Path(__file__).resolve().parents[1] / "notebooks" / "results" / "cpu-shaped"
    d = ablation.diagnose(run)
    steps = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    texts = [s["completion"] for s in json.loads((run / "summary.json").read_text())["after"]["greedy"]["samples"]]
    entropy = [r["entropy"] for r in steps]
    first_low = min(i + 1 for i in range(len(entropy)) if sum(entropy[max(0, i - 2):i + 1]) / len(entropy[max(0, i - 2):i + 1]) < 0.5)
    assert d["collapse_step"] == first_low and d["steps"] == len(steps)
    assert d["distinct"] == len(set(texts)) < len(texts) / 4          # a template
    assert d["top_count"] == max(texts.count(t) for t in texts)
    assert d["top_chars"] == len(d["top_completion"].strip()) != 32   # a near miss
    assert d["pass_both"] == 0.0 and d["zero_std_max"] > 0.5


def test_dynamic_sampling_logs_the_pass_rate_before_selection(monkeypatch):
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", _flat_on_odd_targets)
    policy = train.setup(load_config("smoke", dynamic_sampling=True))
    metrics = train.grpo_step(policy, _prompts([3, 4]), refill=lambda k: _prompts([5, 6]))
    assert 0.0 <= metrics["first_round_pass_both"] <= 1.0 and metrics["sampling_rounds"] == 2


def _steps(n=6, **values):
    base = dict(distinct_frac=1.0, entropy=2.0, truncated_frac=0.0, first_round_pass_both=0.0,
                pass_length=0.0)
    return [{**base, **values} for _ in range(n)]


def test_first_pass_step_is_the_first_step_that_sampled_a_pass():
    from course_utils import ablation
    steps = [dict(step=i + 1, first_round_pass_both=p) for i, p in enumerate([0, 0, 0.03, 0, 0.5])]
    assert ablation.first_pass_step(steps) == 3
    assert ablation.first_pass_step(steps[:2]) is None


@pytest.mark.parametrize("values, ending", [
    (dict(distinct_frac=0.25, entropy=0.2), "collapsed onto one sentence"),     # both at the edge
    (dict(distinct_frac=0.26, entropy=0.05), "still exploring"),                # still varied
    (dict(distinct_frac=0.1, entropy=0.21), "still exploring"),                 # not settled
    (dict(truncated_frac=0.9, entropy=3.0), "filling the token cap"),
    (dict(truncated_frac=0.89), "still exploring"),
    (dict(distinct_frac=0.1, entropy=0.1, truncated_frac=1.0), "collapsed onto one sentence"),
])
def test_probe_outcome_names_the_ending_by_its_rule(values, ending):
    from course_utils import ablation
    assert ablation.probe_outcome(_steps(**values)) == ending
    # only the last 5 steps count: a different start changes nothing
    assert ablation.probe_outcome(_steps(3, entropy=5.0, distinct_frac=1.0) + _steps(5, **values)) == ending


def test_probes_table_reads_every_stored_probe():
    """Each row's numbers are the stored files' own, read independently here."""
    import json
    import statistics
    from pathlib import Path

    from course_utils import ablation
    folder = Path(__file__).resolve().parents[1] / "notebooks" / "results" / "probes"
    table = ablation.probes(folder).splitlines()[2:]
    runs = sorted(p for p in folder.iterdir() if (p / "metrics.jsonl").exists())
    assert len(table) == len(runs) >= 5
    for row, run in zip(table, runs):
        steps = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        config = json.loads((run / "config.json").read_text())
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1] == str(config["seed"]) and cells[2] == f"{len(steps)} of {config['max_steps']}"
        sampled = statistics.mean(r["first_round_pass_both"] for r in steps[-5:])
        assert cells[3] == f"{sampled:.1%}"
        summary = json.loads((run / "summary.json").read_text())
        assert ("after" in summary) == (not cells[8].startswith("not evaluated"))


def test_the_lessons_reading_of_the_ablation_matches_its_stored_results():
    """Lesson 7, sections 6.2 and 6.3 state these in words; the stored result.json must bear
    them out (and the issue's bar: a 3-seed mean of at least 50% for the main job)."""
    import json
    from pathlib import Path

    from course_utils import ablation
    from course_utils.config import PRESETS
    results = Path(__file__).resolve().parents[1] / "notebooks" / "results"
    stored = json.loads((results / "ablation" / "result.json").read_text())
    runs = {name: arm["runs"] for name, arm in stored["arms"].items()}
    passed = {name: [r["pass_both"] for r in rs] for name, rs in runs.items()}
    full, ds, sharp = (passed[a] for a in ablation.ARMS)
    assert all(len(v) == 3 for v in passed.values()) and set(passed) == set(ablation.ARMS)
    # half of the held-out prompts on average, not on every seed; the one that passes few
    # prompts sampled its first pass earlier than one of the other two
    assert sum(full) / 3 >= 0.5 and min(full) < 0.2
    first = [r["first_pass_step"] for r in runs[ablation.FULL]]
    weakest = full.index(min(full))
    assert any(first[weakest] < f for i, f in enumerate(first) if i != weakest)
    # 6.3's probes: the temperature-0.7 run that fills the token cap passes more held-out
    # prompts than two of the recipe's three seeds, not more than all of them
    probe = json.loads((results / "probes" / "temperature-0.7-seed1" / "summary.json").read_text())
    noise = probe["after"]["greedy"]["pass_both"]
    assert sum(noise > f for f in full) == 2
    assert sorted(r["pass_both_one_digit"] for r in runs[ablation.FULL])[1:] == [1.0, 1.0]
    # dynamic sampling: the same held-out pass rate on every seed, not always the same policy;
    # on one seed it never triggered
    assert ds == full
    assert any(a["distinct_completions"] != b["distinct_completions"]
               for a, b in zip(runs["with dynamic sampling"], runs[ablation.FULL]))
    ds_runs = runs["with dynamic sampling"]
    assert any(r["groups_sampled"] == r["steps"] * PRESETS["cpu"]["prompts_per_step"] for r in ds_runs)
    assert any(r["groups_sampled"] > r["steps"] * PRESETS["cpu"]["prompts_per_step"] for r in ds_runs)
    # the sharp reward on top of dynamic sampling: no better on any seed, worse on two
    assert all(s <= d for s, d in zip(sharp, ds)) and sum(s < d for s, d in zip(sharp, ds)) == 2
    # the verdicts are paired and recomputed from the per-seed values, not typed: dynamic
    # sampling identical on every seed, the sharp reward's difference not detectable by 3 seeds
    assert stored["verdicts"] == ablation.comparisons(stored)
    ds_line, _, sharp_line, _, sharp_vs_ds, _ = stored["verdicts"]
    assert "minus the arm 'with dynamic sampling'," in sharp_vs_ds and "no difference detected" in sharp_vs_ds
    assert ds_line.endswith("identical on every seed")
    assert "no difference detected" in sharp_line and "2 df" in sharp_line
    # two-digit passes: within a run, all write the same fixed number
    digits = lambda text: "".join(c for c in text if c.isdigit())  # noqa: E731
    assert all(len({digits(c) for c in r["two_digit_pass_completions"]}) <= 1
               for rs in runs.values() for r in rs)
    # 6.2, the budget: no run sampled a pass in its first ten steps; against cpu-shaped, twice
    # the learning rate, a tighter token cap, and half as many steps again
    assert min(r["first_pass_step"] or 10**6 for rs in runs.values() for r in rs) > 10
    shaped = json.loads((results / "cpu-shaped" / "config.json").read_text())
    cpu = PRESETS["cpu"]
    assert cpu["lr"] == 2 * shaped["lr"] and cpu["max_new_tokens"] < shaped["max_new_tokens"]
    assert cpu["max_steps"] == 1.5 * shaped["train_prompts"] / shaped["prompts_per_step"]


def test_the_stored_ablation_report_is_its_result_rerendered(tmp_path):
    """report.md (rendered into lesson 7 and the README) is exactly what --rerender makes of the
    stored result.json: no verdict or figure in it was edited by hand."""
    import json
    import shutil
    from pathlib import Path

    from course_utils import ablation
    stored = Path(__file__).resolve().parents[1] / "notebooks" / "results" / "ablation"
    shutil.copytree(stored, tmp_path / "ablation")
    assert ablation.main(["--rerender", "--out", str(tmp_path / "ablation")]) == 0
    assert (tmp_path / "ablation" / "report.md").read_text() == (stored / "report.md").read_text()
    assert json.loads((tmp_path / "ablation" / "result.json").read_text()) == \
        json.loads((stored / "result.json").read_text())
    with pytest.raises(SystemExit, match="needs"):
        ablation.main(["--rerender", "--out", str(tmp_path / "nowhere")])


def test_ablation_comparisons_skip_seeds_without_the_target_and_missing_arms():
    from course_utils import ablation

    def run(p, two):
        return dict(pass_both=p, pass_both_two_digit=two)

    result = {"arms": {
        ablation.FULL: dict(dirs=["x/seed0", "x/seed1", "x/seed2"],
                            runs=[run(0.5, 0.1), run(0.6, float("nan")), run(0.7, 0.3)]),
        "with dynamic sampling": dict(dirs=["y/seed0", "y/seed1", "y/seed2"],
                                      runs=[run(0.5, 0.2), run(0.7, float("nan")), run(0.9, 0.3)])}}
    both, two = ablation.comparisons(result)
    assert "seeds 0, 1, 2:" in both
    assert "seeds 0, 2 (no such target on seed(s) 1)" in two
    del result["arms"][ablation.FULL]
    assert ablation.comparisons(result) == []      # nothing to compare against: no KeyError


def test_template_probe_sentences_hold_for_every_stored_run():
    """Lesson 7, 6.4's sentences on the template-lever tuning runs, checked on their files: the
    table and the list are the files' own; at the main job's length the template is gone (most
    held-out completions distinct, all starting with a digit) but not the length; the longer
    run learned the length and a new template that passes no two-digit target; no sampled
    completion of either passed a two-digit target; in the longer run the two-digit share grew,
    the entropy ended below its target with the adaptive weight at its cap."""
    import json
    from pathlib import Path

    from course_utils import ablation
    folder = Path(__file__).resolve().parents[1] / "notebooks" / "results" / "template-probes"
    runs = sorted(p for p in folder.iterdir() if (p / "summary.json").exists())
    table = ablation.template_probes(folder).splitlines()[2:]
    logs = ablation.template_probe_logs(folder).splitlines()
    assert len(runs) == len(table) == len(logs) == 2
    short, long = runs
    # the shorter run is, step for step, the start of the longer one (the lesson says so)
    untimed = lambda rows: [{k: v for k, v in r.items() if "time" not in k and k != "tokens_per_s"}  # noqa: E731
                            for r in rows]
    read = lambda run: [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]  # noqa: E731
    assert untimed(read(short)) == untimed(read(long))[:len(read(short))]
    for row, log, run in zip(table, logs, runs):
        after = json.loads((run / "summary.json").read_text())["after"]["greedy"]
        steps = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[3] == f"{after['pass_both']:.1%}" and cells[5] == f"{after['pass_both_two_digit']:.1%}"
        assert sum(r["passes_two_digit"] for r in steps) == 0 and ", 0 of them passing" in log
        assert after["pass_both_two_digit"] == 0.0
        texts = [s["completion"].strip() for s in after["samples"]]
        assert all(t[:1].isdigit() for t in texts)
        if run == short:   # not one sentence, but a format: short, digit first, an exclamation
            assert after["distinct_completions"] >= len(texts) / 2
            assert sum(t.endswith("!") for t in texts) >= len(texts) / 2
            assert after["pass_digits"] >= after["pass_length"] + 0.3
            assert max(r["entropy_weight"] for r in steps) == 0.0
        else:
            config = json.loads((run / "config.json").read_text())
            assert after["pass_length"] >= 0.95 and after["pass_both_one_digit"] == 1.0
            assert after["distinct_completions"] <= len(texts) / 4
            q = len(steps) // 4
            share = [sum(r["samples_two_digit"] for r in rows) for rows in (steps[:q], steps[-q:])]
            assert share[1] > share[0]
            assert max(r["entropy_weight"] for r in steps) == config["entropy_weight_max"]
            assert max(r["entropy"] for r in steps[-q:]) < config["entropy_target"]


def test_counted_probe_sentences_hold_for_every_stored_run():
    """Lesson 7, 6.4's sentences on the counted-credit runs, checked on their files: the bonus's
    step and cap raised and the KL runs longer; without the KL term sampled completions passed
    two-digit targets (neither template probe's did) and the digit sum passes on most held-out
    prompts, but few pass both, in made-up words; with it, each seed's greedy replies are one
    sentence of whole-word tokens with a number in a slot (a different sentence per seed, one
    seed dropping its full stop for two-digit numbers to keep the length): for most one-digit
    targets the target (or it followed by zeros), for two-digit ones never the target but a
    number whose digits add up to a two-digit target, never written by the base model, on seed 0
    two such numbers each serving its own target and elsewhere one, fewer numbers than targets,
    each passing only its own digit sum; some two-digit targets pass on some seed and none on
    one, whose number makes the reply a character too long; one of the preset's seeds in 6.3
    passed some two-digit target too."""
    import json
    import re
    from pathlib import Path

    from course_utils import ablation, models
    results = Path(__file__).resolve().parents[1] / "notebooks" / "results"
    folder = results / "counted-probes"
    runs = sorted(p for p in folder.iterdir() if (p / "summary.json").exists())
    table = ablation.template_probes(folder).splitlines()[2:]
    logs = ablation.template_probe_logs(folder).splitlines()
    assert len(runs) == len(table) == len(logs) >= 2
    read = lambda run, name: json.loads((run / name).read_text())  # noqa: E731
    steps = lambda run: [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]  # noqa: E731
    vocab = models.load_tokenizer("smollm2-135m-instruct").get_vocab()
    made_up = lambda text: [w for w in re.findall(r"[A-Za-z]+", text) if w not in vocab and "\u0120" + w not in vocab]  # noqa: E731
    no_kl = [r for r in runs if read(r, "config.json")["kl_coef"] == 0]
    kl = [r for r in runs if read(r, "config.json")["kl_coef"] > 0]
    assert len(no_kl) == 1 and [read(r, "config.json")["seed"] for r in no_kl] == [0]
    assert [read(r, "config.json")["seed"] for r in kl] == list(range(len(kl)))
    probes = [read(r, "config.json") for r in (results / "template-probes").iterdir() if r.is_dir()]
    for run in runs:
        config = read(run, "config.json")
        assert config["reward"] == "counted" and config["target_sampling"] == "prioritized"
        assert all(config["entropy_coef"] > p["entropy_coef"] and
                   config["entropy_weight_max"] > p["entropy_weight_max"] for p in probes)
        assert read(run, "summary.json")["before"]["greedy"]["pass_both_two_digit"] == 0
    assert all(read(r, "summary.json")["steps"] > read(no_kl[0], "summary.json")["steps"] for r in kl)
    # without the KL term
    (run,) = no_kl
    after = read(run, "summary.json")["after"]["greedy"]
    assert sum(r["passes_two_digit"] for r in steps(run)) > 0
    for probe in (results / "template-probes").iterdir():
        if probe.is_dir():
            assert sum(r["passes_two_digit"] for r in steps(probe)) == 0
    assert after["pass_digits"] > 0.5 and after["pass_both"] < 0.25 and after["pass_length"] < 0.25
    assert sum(bool(made_up(s["completion"])) for s in after["samples"]) > len(after["samples"]) / 2
    # with it
    two_digit_rates, sentences, stops_dropped, slot_numbers = [], set(), 0, {}
    for run in kl:
        config, summary = read(run, "config.json"), read(run, "summary.json")
        after, L = summary["after"]["greedy"], config["target_chars"]
        texts = [s["completion"].strip() for s in after["samples"]]
        assert not any(made_up(t) for t in texts)
        assert after["pass_both_one_digit"] > 0.5 and after["distinct_completions"] <= len(texts) / 4
        two_digit_rates.append(after["pass_both_two_digit"])
        by_target = {}
        for s in after["samples"]:
            by_target.setdefault(s["target_digit_sum"], []).append(s)
        tops = {t: ablation.top_completion(samples).strip() for t, samples in by_target.items()}
        # one sentence per seed, whatever the snippet, with a number in a slot
        assert all(len(re.findall(r"\d+", top)) == 1 for top in tops.values())
        numbers = {t: re.search(r"\d+", top).group() for t, top in tops.items()}
        frames = {re.sub(r"\d+", "N", top) for top in tops.values()}
        if len(frames) == 2:   # the seed that drops its full stop, for two-digit numbers only
            stops_dropped += 1
            assert {f.rstrip(".") for f in frames} == {f for f in frames if not f.endswith(".")}
            for t, top in tops.items():
                assert top.endswith(".") == (len(numbers[t]) == 1) and len(top) == L
        assert len({f.rstrip(".") for f in frames}) == 1
        sentences |= {f.rstrip(".") for f in frames}
        one_digit = [t for t in numbers if t < 10]
        assert sum(numbers[t].rstrip("0") == str(t) for t in one_digit) > len(one_digit) / 2
        before = [s["completion"] for k in ("greedy", "sampled") for s in summary["before"][k]["samples"]]
        written_before = {n for text in before for n in re.findall(r"\d+", text)}
        for target, number in numbers.items():
            if target < 10 and sum(map(int, number)) == target:
                assert number.rstrip("0") == str(target)
            if target >= 10:
                assert number != str(target) and sum(map(int, number)) in range(10, 13)
                assert number not in written_before
        two = {numbers[t] for t in numbers if t >= 10}
        slot_numbers[config["seed"]] = two
        assert all(any(numbers[t] == n and sum(map(int, n)) == t for t in numbers) for n in two)
        assert len(two) < len([t for t in numbers if t >= 10])
        # a number serves only the target its digits add up to (and at the target length)
        for target, samples in by_target.items():
            fits = sum(map(int, numbers[target])) == target and len(tops[target]) == L
            top_rows = [s for s in samples if s["completion"].strip() == tops[target]]
            assert all((s["digit_sum"] == target and s["n_chars"] == L) == fits for s in top_rows)
        if after["pass_both_two_digit"] == 0:   # the seed whose only number is a character long
            assert all(len(tops[t]) == L + 1 and sum(map(int, numbers[t])) >= 10 for t in numbers if t >= 10)
    assert len(sentences) == len(kl) and stops_dropped == 1
    assert 0.0 == min(two_digit_rates) < max(two_digit_rates) < 1.0
    # seed 0: two numbers, each in the slot of a target its digits add up to; elsewhere one
    assert len(slot_numbers[0]) == 2 and all(len(v) == 1 for k, v in slot_numbers.items() if k)
    # one of the preset's seeds in 6.3 passed a two-digit target too (by a fixed phrase)
    preset = read(results / "ablation", "result.json")["arms"][ablation.FULL]["runs"]
    assert any(r["pass_both_two_digit"] > 0 for r in preset)


def test_the_cpu_presets_token_cap_has_room_for_the_stored_runs_replies():
    """config.py's comment on the cpu preset: the stored main-job run's 32-character replies are
    9 tokens of SmolLM2's tokenizer, and with the end token they fit the 24-token cap."""
    import json
    from pathlib import Path

    from course_utils import models

    tokenizer = models.load_tokenizer("smollm2-135m-instruct")
    stored = Path(__file__).resolve().parents[1] / "notebooks" / "results" / "cpu" / "summary.json"
    replies = [s["completion"] for s in json.loads(stored.read_text())["after"]["greedy"]["samples"]
               if s["n_chars"] == 32]
    lengths = {len(tokenizer(r, add_special_tokens=False)["input_ids"]) for r in replies}
    assert replies and lengths == {9}
    assert max(lengths) + 1 <= load_config("cpu").max_new_tokens


# --- DAPO's overlong punishment ------------------------------------------------------------------

@pytest.mark.parametrize("lengths, truncated, max_len, buffer, expected", [
    # by hand: 0 up to max_len - buffer = 16 tokens, then -1/8 per token, -1 at the cap
    ([10, 16, 17, 20, 24, 24], [False] * 5 + [True], 24, 8, [0, 0, -0.125, -0.5, -1, -1]),
    ([3, 5, 6], [False, False, False], 6, 1, [0, 0, -1]),       # an EOS as the 6th token too (DAPO)
    # buffer 0 (the course's hard variant): only text cut off without an EOS
    ([24, 24, 9], [True, False, False], 24, 0, [-1, 0, 0]),
])
def test_overlong_punishment_by_hand(lengths, truncated, max_len, buffer, expected):
    got = train.rewards.overlong_punishment(lengths, truncated, max_len, buffer)
    assert got == pytest.approx(expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_overlong_punishment_matches_trl_soft_punishment(seed):
    """A second implementation: TRL 1.16's get_soft_overlong_punishment, on seeded lengths and
    caches. TRL's completion_ids are the sampled tokens, EOS included; a cut-off one has max_len."""
    trl_rewards = pytest.importorskip("trl.rewards")
    g = torch.Generator().manual_seed(seed)
    max_len = int(torch.randint(8, 64, (1,), generator=g))
    buffer = int(torch.randint(1, max_len, (1,), generator=g))
    lengths = torch.randint(1, max_len + 1, (40,), generator=g).tolist()
    truncated = [n == max_len and bool(torch.rand(1, generator=g) < 0.5) for n in lengths]
    ours = train.rewards.overlong_punishment(lengths, truncated, max_len, buffer)
    theirs = trl_rewards.get_soft_overlong_punishment(max_len, buffer)([[0] * n for n in lengths])
    assert ours == pytest.approx(theirs)


def test_overlong_punishment_refuses_a_buffer_that_covers_the_cap():
    with pytest.raises(ValueError, match="from 0 to max_len - 1"):
        train.rewards.overlong_punishment([3], [False], 4, 4)
    with pytest.raises(ValueError, match="lengths for"):
        train.rewards.overlong_punishment([3, 4], [False], 8, 2)


def test_overlong_penalty_is_added_to_the_reward_and_leaves_the_pass_flags(monkeypatch):
    """max_new_tokens=1 cuts every completion off: each reward drops by exactly overlong_penalty
    (what the advantages are computed from), and the rule's flags stay as they were."""
    monkeypatch.setitem(train.rewards.REWARDS, "shaped",
                        lambda prompts, completions, **kw: [float(i % 3) for i in range(len(completions))])
    seen = {}
    for penalty in (0.0, 0.7):
        policy = train.setup(load_config("smoke", overlong_penalty=penalty, max_new_tokens=1))
        policy.optimizer.step = lambda *a, **k: None
        prompts = _prompts([3, 4])
        real_score = train.score_rollout
        monkeypatch.setattr(train, "score_rollout",
                            lambda *a: seen.setdefault(penalty, real_score(*a)))
        metrics = train.grpo_step(policy, prompts)
        monkeypatch.setattr(train, "score_rollout", real_score)
        assert metrics["truncated_frac"] == 1.0
        assert ("overlong_mean" in metrics) == (penalty > 0)
    off, on = seen[0.0], seen[0.7]
    assert "overlong" not in off
    assert torch.allclose(on["rewards"], off["rewards"] - 0.7)
    assert torch.equal(on["passed"], off["passed"]) and torch.equal(on["length_ok"], off["length_ok"])
