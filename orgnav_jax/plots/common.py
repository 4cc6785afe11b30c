"""What every picture command shares: where a picture goes and how it is written."""

from __future__ import annotations

from pathlib import Path

from orgnav_jax.safe_write import check_output_file, is_own_png, write_png


def pyplot(agg: bool = True):
    """matplotlib.pyplot, switched to the Agg backend (files, no display) unless agg=False
    (a figure someone else made keeps their backend)."""
    # matplotlib on first use: heavy, and only drawing needs it (`import orgnav_jax.plots`
    # serves the tables and the curves' numbers too); Agg before pyplot picks a backend
    import matplotlib
    if agg:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # matplotlib on first use (above)
    return plt


def save_png(fig, out: Path, dpi: int = 120) -> Path:
    """Write a figure (safe_write.write_png: atomic, marked as ours, never over a file we
    did not write) and close it -> out."""
    try:
        return write_png(fig, out, dpi)
    finally:
        pyplot(agg=False).close(fig)


def default_out(run_dir: str | Path, name: str, out: str | Path | None) -> Path:
    """The one rule of the picture commands: --out, else RUN_DIR/NAME (the first run's
    directory for curves), checked before any work (write_png's rules)."""
    if out is not None and not str(out).strip():
        raise ValueError("--out is empty: expected a .png path")
    path = Path(out) if out is not None else Path(run_dir) / name
    if path.suffix.lower() != ".png":
        raise ValueError(f"--out {path}: expected a .png path (pictures are PNG files)")
    check_output_file(path, is_own_png, "a PNG written by orgnav_jax")
    return path
