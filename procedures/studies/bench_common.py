"""Small pieces the benchmark modules share."""

from __future__ import annotations

import os


def save_figure(fig, out_dir: str, name: str, dpi: int = 110) -> str:
    """Lay out, write and close a matplotlib figure; returns the file's path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = os.path.join(out_dir, name)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
