"""The evaluation's report: PMD tables as Markdown and CSV (with each model's ratio to the baselines),
the noise sweep as CSV and as a PNG plot (matplotlib). The scores come from ``aniformer.evaluate``.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence

from aniformer.evaluate import BASELINES, COPY_DRIVER, SKINNED, STATIC_TARGET, TRANSFER


def ratio_rows(table: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Each model row (not a baseline; the skinned transfer counts as one) of ``table`` divided by the deformation
    transfer alone, by the skinned transfer and by the better trivial baseline (min of copy-driver and static
    target), where those rows are present."""
    models = [name for name in table if name not in BASELINES]
    references = {}
    if TRANSFER in table:
        references["transfer"] = table[TRANSFER]
    if SKINNED in table:
        references[SKINNED] = table[SKINNED]
    if COPY_DRIVER in table and STATIC_TARGET in table:
        references["min(copy-driver, static target)"] = {
            s: min(table[COPY_DRIVER][s], table[STATIC_TARGET][s]) for s in table[COPY_DRIVER]}
    return {f"{name} ÷ {label}": {s: table[name][s] / reference[s] if reference[s] > 0 else math.nan for s in reference}
            for label, reference in references.items() for name in models if name != label}


def _fmt(value: float) -> str:
    return f"{value:.2f}" if math.isfinite(value) else "n/a"


def table_markdown(table: dict[str, dict[str, float]], splits: Sequence[str], descriptions: dict[str, str] | None = None,
                   title: str | None = "PMD (×10⁻⁴, lower is better)", notes: Sequence[str] = (),
                   ratios: bool = False) -> str:
    """Rows: contenders; columns: splits; the best of each column in bold. ``ratios``: then each model's
    ratio to the transfer alone and to the better trivial baseline (``ratio_rows``)."""
    best = {s: min((row[s] for row in table.values() if math.isfinite(row[s])), default=math.nan) for s in splits}
    lines = [f"**{title}**", ""] if title else []
    lines += ["| method | " + " | ".join(splits) + " |", "|---|" + "---:|" * len(splits)]
    for name, row in table.items():
        cells = [f"**{_fmt(row[s])}**" if row[s] == best[s] and len(table) > 1 else _fmt(row[s]) for s in splits]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    for name, row in (ratio_rows(table) if ratios else {}).items():
        lines.append(f"| {name} | " + " | ".join(_fmt(row[s]) for s in splits) + " |")
    if descriptions:
        lines += [""] + [f"- `{s}`: {descriptions[s]}" for s in splits if s in descriptions]
    if notes:
        lines += [""] + [f"{n}" for n in notes]
    return "\n".join(lines) + "\n"


def table_csv(table: dict[str, dict[str, float]], splits: Sequence[str]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["method", *splits])
    for name, row in table.items():
        writer.writerow([name, *(f"{row[s]:.6g}" for s in splits)])
    return out.getvalue()


def sweep_csv(sweep: dict[str, dict[float, float]]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["method", "noise_m", "pmd_x1e4"])
    for name, row in sweep.items():
        for level, value in row.items():
            writer.writerow([name, f"{level:g}", f"{value:.6g}"])
    return out.getvalue()


def plot_sweep(sweep: dict[str, dict[float, float]], path, split: str) -> None:
    """PMD vs noise amplitude, one line per contender (log y when the values span > 30x)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    values = []
    for name, row in sweep.items():
        levels = sorted(row)
        ax.plot([lv * 1000 for lv in levels], [row[lv] for lv in levels], marker="o", label=name)
        values += [row[lv] for lv in levels]
    positive = [v for v in values if v > 0 and math.isfinite(v)]
    if positive and max(positive) / min(positive) > 30:
        ax.set_yscale("log")
    ax.set_xlabel("uniform noise on driving vertices, ± mm")
    ax.set_ylabel("PMD (×10⁻⁴)")
    ax.set_title(f"robustness to driver noise ({split})", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    try:
        fig.savefig(path, format="png")
    finally:
        plt.close(fig)
