"""PNG figures for a CMVAE evaluation: plotting only, from arrays the evaluator has already computed.

Kept apart from evaluate.py so the numbers and the pictures can change
independently; matplotlib runs on the Agg backend (no display needed).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

UNITS = {"d": "m", "theta": "deg", "psi": "deg"}


def image_grid(
    rows: Sequence[np.ndarray], path: Path, title: str, row_labels: Sequence[str] = (), col_labels: Sequence[str] = ()
) -> Path:
    """Save a grid of uint8 frames: ``rows[r][c]`` is one (64, 64, 3) image."""
    n_rows, n_cols = len(rows), max(len(row) for row in rows)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(1.3 * n_cols + 0.8, 1.3 * n_rows + 0.6), squeeze=False)
    for r, row in enumerate(rows):
        for c in range(n_cols):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if c < len(row):
                ax.imshow(row[c])
            else:
                ax.axis("off")
            if c == 0 and r < len(row_labels):
                ax.set_ylabel(row_labels[r], fontsize=8)
            if r == 0 and c < len(col_labels):
                ax.set_title(col_labels[c], fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def state_scatter(predicted: np.ndarray, labels: np.ndarray, names: Sequence[str], path: Path) -> Path:
    """Predicted against true value for each label, with the identity line."""
    fig, axes = plt.subplots(1, len(names), figsize=(4 * len(names), 4), squeeze=False)
    for i, (ax, name) in enumerate(zip(axes[0], names, strict=True)):
        ax.scatter(labels[:, i], predicted[:, i], s=3, alpha=0.4)
        lo, hi = float(labels[:, i].min()), float(labels[:, i].max())
        ax.plot([lo, hi], [lo, hi], color="black", linewidth=0.8)
        ax.set_xlabel(f"true {name} ({UNITS.get(name, '')})")
        ax.set_ylabel(f"predicted {name}")
    fig.suptitle("State decoders on the evaluation set")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def drift_bars(drift: np.ndarray, path: Path) -> Path:
    """Mean |mu_clean - mu_noisy| per latent dimension; z[0..2] are the state-bearing ones."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    colours = ["tab:red" if i < 3 else "tab:gray" for i in range(len(drift))]
    ax.bar([f"z[{i}]" for i in range(len(drift))], drift, color=colours)
    ax.set_ylabel("mean |mu clean - mu noisy|")
    ax.set_title("Latent drift under image noise")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def mask_overlay(frames: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Frames (N, 64, 64, 3) uint8 with a grid of dolphin probabilities (N, k, k) in [0, 1] tinted red over them."""
    scale = frames.shape[1] // cells.shape[1]
    alpha = 0.6 * np.repeat(np.repeat(cells, scale, axis=1), scale, axis=2)[..., None]
    red = np.array([255.0, 0.0, 0.0])
    return ((1.0 - alpha) * frames + alpha * red).round().astype(np.uint8)
