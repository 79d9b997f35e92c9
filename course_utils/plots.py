"""Training curves from the metrics log, as one PNG a learner can read at a glance."""

from __future__ import annotations

from pathlib import Path

# Panels drawn only when their metric is switched on (not all zeros): the entropy weight with an
# entropy bonus, the KL with a reference model.
OPTIONAL = {"entropy_weight", "kl"}
PANELS = [  # (title, [(metric key, label)])
    ("reward", [("reward_mean", "mean reward")]),
    ("pass rates", [("pass_length", "length"), ("pass_digits", "digit sum"), ("pass_both", "both"),
                    ("first_round_pass_both", "both, before dynamic sampling's selection")]),
    ("distance to target length (chars)", [("chars_abs_error", "mean |chars - target|")]),
    ("completion length (tokens)", [("completion_tokens", "mean")]),
    ("advantages", [("adv_abs_mean", "mean |A|"), ("adv_std", "std A")]),
    ("groups without signal", [("zero_std_frac", "zero-std groups"), ("truncated_frac", "truncated"),
                               ("distinct_frac", "distinct completions (share)")]),
    ("entropy", [("entropy", "token entropy")]),
    ("entropy weight (extension)", [("entropy_weight", "weight")]),
    ("KL to reference / clipping", [("kl", "k3 KL"), ("clip_fraction", "clip fraction")]),
]


def plot_metrics(records: list[dict], path: Path) -> Path | None:
    """Draw every panel whose metrics were logged; returns the PNG path (None if no records)."""
    if not records:
        return None
    import matplotlib

    matplotlib.use("Agg")  # no display needed; notebooks show the saved PNG
    import matplotlib.pyplot as plt

    def logged(key: str) -> bool:
        values = [r[key] for r in records if r.get(key) is not None]
        return bool(values) and (key not in OPTIONAL or any(v != 0 for v in values))

    panels = [(t, [(k, lbl) for k, lbl in series if logged(k)]) for t, series in PANELS]
    panels = [(t, s) for t, s in panels if s]
    cols = 3
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 2.8 * rows), squeeze=False)
    for ax, (title, series) in zip(axes.flat, panels):
        for key, label in series:
            points = [(r["step"], r[key]) for r in records if r.get(key) is not None]
            if points:
                ax.plot(*zip(*points), marker="." if len(points) < 40 else None, label=label)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        if len(series) > 1:
            ax.legend(fontsize=8)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
