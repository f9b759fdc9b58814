"""One table of the practitioner cases from the records the benchmark wrote, with one summary line over all of them.

``scripts/bench_practitioner.py --report X.md`` writes its case records beside the report (``X.json``); the cases of a
library version are spread over several reports (fresh seeds run one at a time). This collects them::

    python scripts/tally_practitioner.py --records reports/bench_practitioner_current.json \\
        reports/bench_practitioner_oc4.json ... --report reports/bench_practitioner_tally.md

Reads the JSON records only (no case folder, no model): the figures are the ones the reports state. A case found in
several files is taken from the last one given.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro

from nerfuser_ns.bench.practitioner_cases import (
    AUTO_COLUMN,
    BLEND_COLUMNS,
    REFUSAL_CHECKS,
    blend_gains,
    refusals_scored,
    summarise,
    unregistered_verdict,
)
from nerfuser_ns.files import write_text_atomic


@dataclass
class TallyPractitioner:
    """Every practitioner case of the given records in one table."""

    records: list[Path]
    """JSON records written by ``scripts/bench_practitioner.py --report`` (a list of case records each)."""
    report: Path
    """Write the markdown table here."""


def collect(paths: list[Path]) -> list[tuple[dict, Path]]:
    """The case records of ``paths`` with the file each came from, in first-seen order; the last file wins a case."""
    found: dict[str, tuple[dict, Path]] = {}
    for path in paths:
        try:
            records = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"{path}: not a readable practitioner record file ({e})") from None
        if not isinstance(records, list) or not all(isinstance(r, dict) and "case" in r for r in records):
            raise SystemExit(f"{path}: expected a list of case records (scripts/bench_practitioner.py --report)")
        for r in records:
            found[r["case"]] = (r, path)
    return list(found.values())


OTHER_TRUTHS = ("errors_optimized", "errors_pose", "errors_content")
"""The record keys of the registration's errors against the other truths, in the order of the tally's columns."""


def _fmt(x: float | None, digits: int) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def refusal_lines(records: list[dict]) -> list[str]:
    """The table of each check's refusals against the truth (``practitioner_cases.refusals_scored``)."""
    refusals = refusals_scored(records)
    lines = ["", "Each check's refusals against the stored truth: every pose source an automatic choice tried before "
             "the one it kept (or refused last) that a check refused, the refused link judged by the paper's rule "
             "(its worst NeRF; a refusal of a failure is right, of a success wrong). A refused case's last refusal "
             "is not in its record; *unscored*: records written before refused links were kept. *After a right "
             "refusal*: what the case kept in the end (the next pose source's link, a success or a failure, or "
             "nothing); *the successes*: the refused link's r_err, then the kept one's.", "",
             "| check | refusals | of failures (right) | after a right refusal: success / failure / refused | "
             "of successes (wrong) | the successes (case: refused -> kept r_err deg) | unscored |",
             "|" + " --- |" * 7]  # fmt: skip
    for check in REFUSAL_CHECKS:
        found = [r for r in refusals if r.check == check]
        if not found:
            continue
        right = [r for r in found if r.failure is True]
        after = " / ".join(str(sum(r.outcome == o for r in right)) for o in ("success", "failure", "refused"))
        wrong = [r for r in found if r.failure is False]
        lines.append(f"| {check} | {len(found)} | {len(right)} | {after} | {len(wrong)} | "
                     + ", ".join(f"{r.case}: {r.r_err_deg:.2f} -> {_fmt(r.kept_r_err_deg, 2)}" for r in wrong)
                     + f" | {sum(r.failure is None for r in found)} |")  # fmt: skip
    return lines


def per_layout(by_layout: dict[str, list[dict]], errors: str) -> list[str]:
    """One summary line per layout against the truth ``errors`` names, over its cases scored with it (a drive's
    stored truth leaves the roll about its near-straight path loose; the pose truth fixes it)."""
    return [f"- {summarise(cases, errors).line(f'{layout}: ')}" for layout, cases in by_layout.items()
            if any(r["registration"].get(errors) for r in cases)]  # fmt: skip


def write_tally(rows: list[tuple[dict, Path]], path: Path) -> None:
    lines = ["# The practitioner's path: every case in one table", "",
             "Collected by `python scripts/tally_practitioner.py " + " ".join(sys.argv[1:]) + "` from the records "
             "each report wrote (one row per case; r/t/s against the stored COLMAP truth, blend PSNR from `ns-eval` "
             "on the world-posed test views with the estimated registration). COLMAP columns: the worst capture "
             "of the case. *r_err (cam.-opt.)*: the same registration against the camera-optimised truth (each run's "
             "NeRF frame tied to the world through its camera-optimised training poses instead of its stored ones: "
             "without the part of the error that is nerfacto's camera optimiser moving the cameras, and with them "
             "the content, off the COLMAP frame). *r_err (pose tie)*: against the pose truth (each capture tied by its "
             "views' rotations as well as their centres, which fixes the roll of a near-collinear drive; '-' for "
             "records scored before it was). *r_err (content)*: against the content truth (each run registered to "
             "the exact scene placed by its stored truth, `--stages content`: where its trained content lies, "
             "with that registration's own error; '-' where the stage did not run).", "",
             "| case | r_err (deg) | t_err | s_err | ok | r_err (cam.-opt.) | r_err (pose tie) | r_err (content) | "
             "COLMAP rot noise (deg) | COLMAP bend (deg) | Nearest | IDW-Sample | registered at | report |",
             "|" + " --- |" * 14]  # fmt: skip
    for r, src in rows:
        noise = max(c["colmap_rot_err_deg_median"] for c in r["captures"])
        bend = max(c.get("colmap_bend_deg", float("nan")) for c in r["captures"])
        b = r.get("blend_psnr") or {}
        link = f"[{src.stem}]({src.with_suffix('.md').name})"
        errs = r["registration"]["errors"]
        if errs is None:
            lines.append(f"| {r['case']} | {unregistered_verdict(r['registration'])} | | | FAIL | "
                         f"{' | '.join('-' for _ in OTHER_TRUTHS)} | "
                         f"{noise:.3f} | {bend:.2f} | - | - | {r.get('registered_at_commit')} | {link} |")  # fmt: skip
            continue
        other = [{e["nerf"]: e["r_err_deg"] for e in r["registration"].get(key) or []} for key in OTHER_TRUTHS]
        for e in errs:
            lines.append(f"| {r['case']} | {e['r_err_deg']:.4f} | {e['t_err']:.5f} | {e['s_err']:.5f} | "
                         f"{'FAIL' if e['failure'] else 'ok'} | "
                         f"{' | '.join(_fmt(o.get(e['nerf']), 4) for o in other)} | {noise:.3f} | {bend:.2f} | "
                         f"{_fmt(b.get('nearest'), 2)} | {_fmt(b.get('idw_sample'), 2)} | "
                         f"{r.get('registered_at_commit')} | {link} |")  # fmt: skip
    records = [r for r, _ in rows]
    summary = summarise(records)
    lines += ["", "Per layout:", ""]
    by_layout = {layout: [r for r in records if r["spec"].startswith(layout + ":")]
                 for layout in sorted({r["spec"].rsplit(":", 1)[0] for r in records})}  # fmt: skip
    for layout, cases in by_layout.items():
        lines.append("- " + summarise(cases).line(f"{layout}: "))
    lines += ["", summarise(records, "errors_optimized").line("Against the camera-optimised truth, "), "",
              *per_layout(by_layout, "errors_optimized")]  # fmt: skip
    for key, truth in (("errors_pose", "pose"), ("errors_content", "content")):
        if any(r["registration"].get(key) for r in records):
            lines += ["", summarise(records, key).line(f"Against the {truth} truth (the cases scored with it), "), "",
                      *per_layout(by_layout, key)]  # fmt: skip
    gains = {layout: blend_gains(cases) for layout, cases in by_layout.items()}
    columns = [(k, name) for k, name in [*BLEND_COLUMNS, AUTO_COLUMN] if any(k in g for g in gains.values())]
    lines += ["", "Blend methods per layout (PSNR minus IDW-Sample's, dB: median (lowest to highest) over the cases "
              "registered without a failure, and the cases where the method scored highest). *Auto* is the method "
              "`auto` (ours, the default) renders each case with under its current rule: IDW-Sample where every "
              "capture's cameras look at a centre, IDW-2D where every capture was filmed by a rig, coverage "
              "otherwise; as each report recorded it from the registration file when recorded under this rule, else "
              "what the case's layout's cameras give under it (IDW-Sample around objects, IDW-2D for the drive's "
              "rig, coverage on every other layout; `reports/blend_choice_rig.md`). Drives run before the rig rule "
              "rendered with coverage.", "",
              "| layout | " + " | ".join(name for _, name in columns) + " |", "|" + " --- |" * (len(columns) + 1)]
    for layout, g in gains.items():
        if g:
            cells = ["-" if k not in g else f"best {g[k].best}/{g[k].cases}" if k == "idw_sample" else g[k].cell()
                     for k, _ in columns]  # fmt: skip
            lines.append(f"| {layout} | " + " | ".join(cells) + " |")
    lines += refusal_lines(records)
    blends = summary.idw_sample_over_nearest
    covered, auto = summary.coverage_over_nearest, summary.auto_over_nearest
    lines += ["", f"IDW-Sample >= Nearest on {sum(blends)} of {len(blends)} cases with a blend; Coverage (ours) >= "
              f"Nearest on {sum(covered)} of the {len(covered)} that scored it; Auto (ours, the default) >= Nearest "
              f"on {sum(auto)} of {len(auto)}.", "",
              "Targets (defaults only): " + "; ".join(f"{t}: {'met' if ok else 'NOT met'}"
                                                     for t, ok in summary.targets()) + ".",
              "", summary.line(), ""]  # fmt: skip
    write_text_atomic(path, "\n".join(lines))


def main(cfg: TallyPractitioner) -> None:
    write_tally(collect(cfg.records), cfg.report)
    print(f"tally: {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(TallyPractitioner))
