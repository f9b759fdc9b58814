"""Generate a synthetic multi-capture scene with exact ground truth (nerfstudio datasets + ground_truth.json).

Example:
    python scripts/make_scene.py --layout object-centric --output-dir data/scenes/object-centric \\
        --seed 0 --num-views 64 --width 192 --height 144
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro


@dataclass
class MakeSceneConfig:
    """Render a ground-truth scene: one nerfstudio dataset per capture (own frame), a world-frame test capture."""

    layout: Literal["object-centric", "street", "drive", "room", "row-houses"] = "object-centric"
    """Scene layout: an indoor room with two objects and one capture around each; a street with several
    overlapping captures along it; the same street driven through by a car with a surround camera rig, one
    capture per block of the drive and side-view test cameras between blocks (like the paper's Mission Bay split);
    a room of repeated structure (opposite walls alike, paired furniture) with one capture in each half; or the
    street lined by one house repeated every 3.5 m (repeated facades).
    """
    output_dir: Path = Path("data/scenes/object-centric")
    """Scene folder to create (replaced atomically if it already holds a generated scene)."""
    seed: int = 0
    """Random seed for geometry jitter, textures, camera placement and capture-frame yaws."""
    num_views: int = 64
    """Views per training capture (drive: a multiple of 8, the rig's cameras)."""
    num_test_views: int = 12
    """Views of the world-frame test capture."""
    num_captures: int = 3
    """Number of training captures (street and drive layouts; object-centric and room always have two)."""
    width: int = 192
    """Image width in pixels."""
    height: int = 144
    """Image height in pixels."""
    hfov_deg: float = 65.0
    """Horizontal field of view in degrees."""
    texels_per_metre: float = 128.0
    """Texture resolution in texels per metre (the street and drive layouts cap it at 48)."""
    symmetric: bool = False
    """Room layout: leave out its door, so the room is exactly symmetric under a half turn about its vertical axis."""
    supersample: int = 2
    """Anti-aliasing: rays per pixel along each axis (2 means 2x2)."""
    threads: int = 1
    """torch CPU threads for rendering. 1 is the robust choice: multi-threaded torch slows down 5-10x when other
    jobs share the CPU; raise it on an otherwise idle many-core machine."""


def main(config: MakeSceneConfig) -> None:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.text import Text

    try:
        from nerfuser_ns.bench.scenes import make_layout, write_scene
    except ImportError:  # run from a source checkout without installing the package
        sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
        from nerfuser_ns.bench.scenes import make_layout, write_scene

    console = Console(stderr=True)
    try:
        if isinstance(config.supersample, bool) or config.supersample < 1:
            raise ValueError(f"supersample must be an integer >= 1, got {config.supersample!r}")
        if config.threads < 1:
            raise ValueError(f"threads must be an integer >= 1, got {config.threads!r}")
        import torch

        torch.set_num_threads(config.threads)
        t0 = time.perf_counter()
        layout = make_layout(
            config.layout,
            seed=config.seed,
            num_views=config.num_views,
            num_test_views=config.num_test_views,
            num_captures=config.num_captures,
            width=config.width,
            height=config.height,
            hfov_deg=config.hfov_deg,
            texels_per_metre=config.texels_per_metre,
            symmetric=config.symmetric,
        )
        total = sum(c.num_views for c in layout.captures) + layout.test.num_views
        columns = (TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, console=console) as progress:
            task = progress.add_task("frames", total=total)
            out = write_scene(layout, config.output_dir, supersample=config.supersample,
                              progress=lambda: progress.advance(task))
    except ValueError as err:
        console.print(Text.assemble(("error: ", "bold red"), str(err)), soft_wrap=True)  # the message as written
        sys.exit(2)
    names = ", ".join(c.name for c in layout.captures)
    console.print(f"wrote {out} ({names}, test; {total} frames) in {time.perf_counter() - t0:.1f} s")


def entrypoint() -> None:
    main(tyro.cli(MakeSceneConfig))


if __name__ == "__main__":
    entrypoint()
