"""Appearance matching (ours) on the practitioner's path: one scene as two cases of ``bench_practitioner.py``, its
captures as rendered and with their own exposure and white balance, each scored by ``ns-eval`` with appearance matching
off and on (the ``fuse`` stage gives the default's, the ``matched`` / ``unmatched`` stages the other).

Example::

    python scripts/bench_practitioner.py --cases street:1 --stages scene colmap train register fuse matched unmatched
    python scripts/bench_practitioner.py --cases street:1 --appearance-jitter 0.38 --appearance-bracket \\
        --stages scene colmap train register fuse matched unmatched
    python scripts/report_practitioner_appearance.py --plain outputs/practitioner/street-1 \\
        --differing outputs/practitioner/street-1-bracket0.38 --output reports/bench_practitioner_appearance.md
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from nerfuser_ns.bench.practitioner_cases import BLEND_COLUMNS, appearance_evals, blend_table
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import read_registration

WITHIN_DB = 0.3
"""The target: matched blends of the differing captures within this of the same scene without differences."""
DEFAULT_MEAN_DB, DEFAULT_WORST_DB = -0.05, -0.15
"""The rule (fixed before these runs) for matching on by default: on captures without differences, matching moves
the blend methods by a mean >= -0.05 dB and none by less than -0.15 dB."""


@dataclass
class ReportAppearance:
    plain: Path
    """Case folder of the scene as rendered (no colour differences)."""
    differing: Path
    """Case folder of the same scene with per-capture exposure and white balance."""
    output: Path
    """Markdown report (a .json beside it)."""


def _case(folder: Path) -> dict:
    """A case's unmatched and matched scores and its registration's colour maps."""
    out: dict = {"folder": str(folder)}
    evals = appearance_evals(folder)
    for label, setting in (("unmatched", False), ("matched", True)):
        if setting not in evals:
            raise SystemExit(f"report_practitioner_appearance: {folder} has no {label} ns-eval; run "
                             f"bench_practitioner.py with --stages fuse {label} on that case")  # fmt: skip
        table = blend_table(evals[setting])
        out[label] = {k: [table["blend_psnr"][k], table["blend_ssim"][k]] for k, _ in BLEND_COLUMNS}
    reg = read_registration(folder / "registration.json")
    out["maps"] = [None if n.get("colour_to_reference") is None
                   else np.diag(np.asarray(n["colour_to_reference"])[:, :3]).round(3).tolist()
                   for n in reg["nerfs"]]  # fmt: skip
    out["reference_colour"] = reg.get("reference_colour")
    gains = folder / "appearance.json"
    out["gains"] = json.loads(gains.read_text())["gains"] if gains.is_file() else None
    return out


def main(cfg: ReportAppearance) -> None:
    plain, diff = _case(cfg.plain), _case(cfg.differing)
    keys = [(k, name) for k, name in BLEND_COLUMNS if plain["unmatched"][k][0] is not None]
    blends = [k for k, _ in keys if k != "nerf"]
    lines = [
        "# Appearance matching (ours) on the practitioner's path",
        "",
        f"Command: `python {' '.join(sys.argv)}`, on two cases of `scripts/bench_practitioner.py` (COLMAP-posed "
        "captures, stock nerfacto with CPU-sized options, `ns-nerfuser-register` with every default): the scene as "
        f"rendered ({cfg.plain}) and the same scene and seed with per-capture exposure and white balance "
        f"({cfg.differing}). Each scored by `ns-eval` with `--pipeline.model.appearance-matching False` and "
        "`True` (one of them the fused model's default when the case ran). Test views: in the first (reference) "
        "capture's appearance.",
        "",
    ]
    if diff["gains"] is not None:
        g0 = np.asarray(diff["gains"][0])
        for i, g in enumerate(diff["gains"]):
            lines.append(f"- capture {i}: linear gains {np.round(g, 3).tolist()}; true map to the reference "
                         f"{np.round(g0 / np.asarray(g), 3).tolist()}; fitted {diff['maps'][i]}")  # fmt: skip
    lines.append(f"- without differences, fitted maps (truth: the identity): {plain['maps']}")
    for label, case in (("as rendered", plain), ("differing", diff)):
        rc = case["reference_colour"] or {}
        lines.append(f"- reference colour ({label}): "
                     + (f"{np.diag(np.asarray(rc['map'])[:, :3]).round(3).tolist()} from {rc.get('views')} views"
                        if rc.get("map") is not None else f"none ({rc.get('skipped')})"))  # fmt: skip
    lines += ["", "| method | as rendered, unmatched | as rendered, matched | differing, unmatched | differing, "
              "matched | matched - as rendered | matched - as rendered matched | differing: matched - unmatched |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    fmt = lambda v: f"{v[0]:.2f} / {v[1]:.3f}"  # noqa: E731
    within, plain_effect = [], {}
    for k, name in keys:
        pu, pm, du, dm = plain["unmatched"][k], plain["matched"][k], diff["unmatched"][k], diff["matched"][k]
        lines.append(f"| {name} | {fmt(pu)} | {fmt(pm)} | {fmt(du)} | {fmt(dm)} | {dm[0] - pu[0]:+.2f} dB | "
                     f"{dm[0] - pm[0]:+.2f} dB | {dm[0] - du[0]:+.2f} dB |")  # fmt: skip
        within.append(abs(dm[0] - pu[0]) <= WITHIN_DB or dm[0] > pu[0])
        if k in blends:
            plain_effect[k] = pm[0] - pu[0]
    effects = np.array(list(plain_effect.values()))
    default_ok = bool(effects.mean() >= DEFAULT_MEAN_DB and effects.min() >= DEFAULT_WORST_DB)
    lines += [
        "",
        "PSNR (dB) / SSIM.",
        "",
        f"Target (matched blends of the differing captures within {WITHIN_DB} dB of the scene as rendered, every "
        f"method, or above it): {'met' if all(within) else 'NOT met'}.",
        "",
        "Matching on the captures without differences, per blend method: "
        + ", ".join(f"{dict(keys)[k]} {v:+.2f}" for k, v in plain_effect.items())
        + f" dB (mean {effects.mean():+.3f}, worst {effects.min():+.2f}). The rule fixed before these runs for "
        f"turning matching on by default (mean >= {DEFAULT_MEAN_DB} dB, none below {DEFAULT_WORST_DB} dB): "
        f"{'met' if default_ok else 'NOT met'}.",
        "",
    ]
    write_text_atomic(cfg.output, "\n".join(lines))
    write_text_atomic(cfg.output.with_suffix(".json"), json.dumps(
        {"plain": plain, "differing": diff, "target_met": all(within), "default_rule_met": default_ok}, indent=2
    ) + "\n")  # fmt: skip
    print("\n".join(lines))


if __name__ == "__main__":
    main(tyro.cli(ReportAppearance))
