"""What every picture command shares: where a picture goes and how it is written."""

from __future__ import annotations

from pathlib import Path

from orgnav_jax.safe_write import check_output_file, is_own_png, write_png


def save_png(fig, out: Path, dpi: int = 120) -> Path:
    """Write a figure (safe_write.write_png: atomic, marked as ours, never over a file we
    did not write) and close it -> out."""
    import matplotlib.pyplot as plt
    try:
        return write_png(fig, out, dpi)
    finally:
        plt.close(fig)


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
