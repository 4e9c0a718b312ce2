"""The evaluation report: a Markdown table of metrics and PNG plots (motion / velocity /
acceleration curves as in DiffSHEG's figure 13, speed histograms, mouth against speech).
Plots need matplotlib (`pip install matplotlib`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import DiffshegError


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise DiffshegError("the report's plots need matplotlib: `pip install matplotlib`, "
                            "or evaluate with --no-plots") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_curves(curves: dict[str, dict[str, np.ndarray]], fps: float, path: Path) -> Path:
    """One panel per curve kind (motion, velocity, acceleration), one line per source."""
    plt = _pyplot()
    kinds = ("motion", "velocity", "acceleration")
    fig, axes = plt.subplots(len(kinds), 1, figsize=(10, 7), sharex=True)
    for ax, kind in zip(axes, kinds):
        for label, c in curves.items():
            ax.plot(np.arange(len(c[kind])) / fps, c[kind], label=label, linewidth=0.8)
        ax.set_ylabel(kind)
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("gesture: frame-wise channel mean (normalised)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_histograms(values: dict[str, np.ndarray], xlabel: str, path: Path, bins: int = 40) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    top = max(float(np.percentile(v, 99)) for v in values.values())
    for label, v in values.items():
        ax.hist(v, bins=bins, range=(0, top), density=True, histtype="step", label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("density")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_series(series: dict[str, tuple[np.ndarray, np.ndarray]], ylabel: str, path: Path) -> Path:
    """Lines of (times, values), each scaled to its own 0..1 range so shapes compare."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(10, 3.5))
    for label, (t, v) in series.items():
        span = float(np.ptp(v)) or 1.0
        ax.plot(t, (v - v.min()) / span, label=label, linewidth=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def markdown_table(rows: list[tuple[str, object, object]], columns: tuple[str, str]) -> str:
    lines = [f"| metric | {columns[0]} | {columns[1]} |", "|---|---|---|"]
    lines += [f"| {name} | {_cell(a)} | {_cell(b)} |" for name, a, b in rows]
    return "\n".join(lines)


def write_report(path: Path, title: str, notes: list[str], table: str, plots: list[Path]) -> Path:
    body = [f"# {title}", "", *[f"- {n}" for n in notes], "", table, ""]
    body += [f"![{p.stem}]({p.name})" for p in plots]
    path.write_text("\n".join(body) + "\n", encoding="utf-8")
    return path
