"""Writing a benchmark's figure: laid out, saved under a temporary name, renamed, closed."""

from __future__ import annotations

from pathlib import Path


def save_figure(fig, path: Path, dpi: int = 110) -> None:
    """Save a matplotlib figure as PNG at path (a reader never sees half a file) and close it."""
    import matplotlib.pyplot as plt

    tmp = path.with_name(f".{path.stem}.part.png")
    fig.tight_layout()
    fig.savefig(tmp, dpi=dpi)
    tmp.replace(path)
    plt.close(fig)
