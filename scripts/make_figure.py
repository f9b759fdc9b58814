"""The README's picture, from the outputs of ``make demo``: a test view's ground truth beside the blended render
(IDW-Sample with the estimated registration) and the Nearest baseline, and the cameras the registration rendered
from, per NeRF, in the common frame.

    python scripts/make_figure.py [--demo-dir outputs/demo] [--output docs/figures/demo.png]
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import tyro  # noqa: E402
from PIL import Image  # noqa: E402

from nerfuser_ns.blend_settings import SHARE_PALETTE  # noqa: E402
from nerfuser_ns.files import atomic_path  # noqa: E402
from nerfuser_ns.registration.record import render_folders  # noqa: E402
from nerfuser_ns.spec import read_registered_nerfs  # noqa: E402
from nerfuser_ns.viewer import read_render_folder, short_name  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class MakeFigure:
    demo_dir: Path = ROOT / "outputs/demo"
    """What make demo wrote (registration.json, fused/<transforms>/<method>/test_*.png, summary.json)."""
    scene_dir: Path = ROOT / "demo/scene"
    """The demo scene (its test images are the ground truth)."""
    view: int = 0
    """Which test view to show."""
    output: Path = ROOT / "docs/figures/demo.png"
    """Where to write the PNG."""


def main(cfg: MakeFigure) -> None:
    test = json.loads((cfg.scene_dir / "test" / "transforms.json").read_text())
    gt = Image.open(cfg.scene_dir / "test" / test["frames"][cfg.view]["file_path"]).convert("RGB")
    summary = json.loads((cfg.demo_dir / "summary.json").read_text())
    psnr = summary["blending"]["estimated"]["methods"]
    panels = [("ground truth", gt)]
    for method, label in (("idw-sample", "IDW-Sample, registered by us"), ("nearest", "Nearest")):
        image = Image.open(cfg.demo_dir / "fused" / "estimated" / method / f"test_{cfg.view:03d}.png")
        panels.append((f"{label}\nPSNR {psnr[method]['psnr']:.2f} dB over the test views", image))
    entries = read_registered_nerfs(cfg.demo_dir / "registration.json", check_runs=False)
    folders = render_folders(cfg.demo_dir / "registration.json")

    fig = plt.figure(figsize=(13, 3.5), dpi=110)
    for k, (title, image) in enumerate(panels):
        ax = fig.add_subplot(1, 4, k + 1)
        ax.imshow(np.asarray(image))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(1, 4, 4, projection="3d")
    for i, (entry, where) in enumerate(zip(entries, folders, strict=True)):
        cams = read_render_folder(where.folder, entry.nerf_to_common)
        colour = SHARE_PALETTE[i % len(SHARE_PALETTE)].numpy()
        centres = cams.c2w[:, :3, 3]
        ax.scatter(*centres.T, s=6, color=colour, label=short_name(entry.name))
        ax.scatter(*entry.origin, s=40, color=colour, marker="x")
    ax.set_title("registration cameras, common frame", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_xticks([]), ax.set_yticks([]), ax.set_zticks([])
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    cfg.output.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(cfg.output) as tmp:
        fig.savefig(tmp, format="png")
    print(f"wrote {cfg.output}")


if __name__ == "__main__":
    main(tyro.cli(MakeFigure))
