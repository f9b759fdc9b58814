"""The render-free checks' refusals judged against the truth: every pose source of a practitioner case that the camera
check or the model check refused (``sampling_choice.tried_before`` of its registration file), registered again from
the same renders and SfM without that check. Per refusal: the refused link against the stored truth (was it a failure
by the paper's rule, so the refusal right?), what the remaining checks (the other render-free check, the cross-render
NCC and depth) said of it, and each of the SfM's models' own link against the truth::

    python scripts/check_refusals.py \\
        --cases drive:21=outputs/practitioner/drive-21-checked street:21=outputs/practitioner/street-21-checked \\
        --report reports/check_refusals.md

A case is ``LAYOUT:SEED=FOLDER[,REGISTRATION]`` (a case folder of ``scripts/bench_practitioner.py``; the registration
file may be a refused one, e.g. ``registration_rejected.json``). The registrations again write
``registration_no_<check>_check_<source>_<mode>.json`` (or, refused, ``..._rejected.json``, whose ``refused`` says why)
into the case folder and reuse its ``registration_work`` folder: a case's renders and SfM are not made again, only
the direct alignment and the self-check run (minutes per refusal on a CPU).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import tyro
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.bench.practitioner_cases import (
    capture_ground_truth,
    case_layout,
    case_registration,
    library_commit,
    refusing_check,
    register_command,
)
from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import RegistrationConfig, read_registration
from nerfuser_ns.registration.render_cache import ViewSet
from nerfuser_ns.registration.self_check import model_links
from nerfuser_ns.registration.sfm import SfMResult, other_models

RENDER_FREE = ("camera", "model")
"""The render-free checks (keys of ``practitioner_cases.REFUSAL_CHECKS``); ``--no-<check>-check`` turns one off."""


@dataclass
class CheckRefusals:
    """Register each camera- or model-check refusal of the cases again without that check; judge both by the truth."""

    cases: list[str]
    """``LAYOUT:SEED=FOLDER[,REGISTRATION]`` (the case folder, the registration file in it)."""
    report: Path
    """Markdown report (a JSON of the rows beside it)."""
    again: bool = False
    """Also register each refusal again with this checkout's library and every check on (but the camera check where it
    refused): what the checks say now (``registration_now_<commit>_<source>_<mode>.json``, made once per commit)."""


@dataclass
class Row:
    case: str
    check: str
    """The check that refused (one of :data:`RENDER_FREE`)."""
    source: str
    mode: str
    refusal: str
    """The check's line, up to its suggestion."""
    r_err_deg: float
    t_err: float
    s_err: float
    link_failure: bool
    """The refused link is a failure by the paper's rule (5 deg, 0.2, 0.1): the refusal was right."""
    checks_without: str
    """What the registration without that check said: ``passed`` or its refusal line."""
    self_check: dict | None
    """The cross-render check's figures (NCC, depth) of the registration without that check."""
    self_check_alone: str | None
    """Where the other render-free check refused it too: what the registration without either said (``passed`` or
    its refusal line), else None."""
    models: list[dict]
    """Per SfM model (the largest first): views per NeRF and its link against the truth (None where it links fewer
    than two NeRFs)."""
    now: str | None = None
    """With ``--again``: what this checkout's library said (``passed`` or its refusal line), else None."""
    now_link: dict | None = None
    """... its link's worst NeRF against the truth (a refused one's too)."""
    now_model_check: dict | None = None
    """... its record's ``model_check`` (the other SfM models' links scored by cross-rendering), where it has one."""


def refusals(record: dict) -> list[dict]:
    """The pose sources a render-free check refused (each ``{"check", "source", "mode", "error"}``): those tried
    before the recorded one, and the record's own when it is a solution such a check refused
    (``rejected_registration.json`` of a registration run with one pose source)."""
    tried = [dict(t) for t in (record.get("sampling_choice") or {}).get("tried_before") or []]
    refused = record.get("refused", "")
    if refused:
        settings = record["settings"]
        tried.append({"source": settings["sampling"]["source"], "mode": settings["mode"], "error": refused})
    out = []
    for t in tried:
        if (check := refused_by(t["error"])) is not None:
            out.append({"check": check, **{k: t[k] for k in ("source", "mode", "error")}})
    return out


def verdict(link_failure: bool, refused: bool) -> str:
    """A check's verdict on a link against the truth: right (refused a failure, passed a success) or wrong."""
    if refused:
        return "right (refused a failure)" if link_failure else "wrong (refused a success)"
    return "wrong (passed a failure)" if link_failure else "right (passed a success)"


def refused_by(line: str) -> str | None:
    """The render-free check (one of :data:`RENDER_FREE`) whose refusal ``line`` is, else None."""
    check = refusing_check(line)
    return check if check in RENDER_FREE else None


def _register_again(
    layout, case_dir: Path, refusal: dict, checks_off: list[str], console: Console, tag: str | None = None
) -> tuple[Path, str]:
    """``ns-nerfuser-register`` on the case's runs with the refusal's source and mode, ``checks_off`` off: the record
    it wrote (or refused) and ``passed`` or its refusal line. ``tag``: the files' name in place of the checks off."""
    source, mode = refusal["source"], refusal["mode"]
    tag = tag or f"no_{'_'.join(sorted(checks_off))}_check"
    stem = case_dir / f"registration_{tag}_{source}_{mode}"
    output, rejected = stem.with_suffix(".json"), Path(f"{stem}_rejected.json")
    if output.is_file():
        return output, "passed"
    if rejected.is_file():
        return rejected, read_registration(rejected)["refused"]
    work = case_dir / "registration_work"
    cmd = register_command(layout, case_dir, output, "--work-dir", str(work), "--sampling.source", source, "--mode",
                           mode, *[f"--no-{c}-check" for c in checks_off])  # fmt: skip
    console.print(f"[dim]$ {' '.join(cmd)}[/]")
    started = time.time()
    log = Path(f"{stem}.log")
    with open(log, "w") as f:
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONWARNINGS": "ignore"})
    if proc.returncode == 0:
        return output, "passed"
    in_work = work / "rejected_registration.json"
    if not (in_work.is_file() and in_work.stat().st_mtime >= started):
        raise SystemExit(f"{log}: ns-nerfuser-register failed without a refused solution (exit {proc.returncode})")
    shutil.copyfile(in_work, rejected)
    return rejected, read_registration(rejected)["refused"]


def _sfm_of(case_dir: Path, record: dict) -> SfMResult:
    """The SfM the record's renders went into (the work folder's SfM whose images are the record's render folders)."""
    folders = {Path(n["render_folder"]).name for n in record["nerfs"]}
    for result in sorted((case_dir / "registration_work" / "sfm").glob("*/result.json")):
        data = json.loads(result.read_text())
        if {name.split("/")[0] for name in data["c2w"]} == folders:
            return SfMResult(**{k: v for k, v in data.items() if k in SfMResult.__dataclass_fields__})
    raise SystemExit(f"{case_dir / 'registration_work' / 'sfm'}: no SfM over the render folders {sorted(folders)}")


def _models(views: list[ViewSet], sfm: SfMResult, truth: np.ndarray, ref: int) -> list[dict]:
    """Every SfM model's link against the truth, the largest (the registration's, before its refinement) first."""
    cfg = RegistrationConfig()
    largest = {n: np.asarray(c, dtype=np.float64) for n, c in sfm.c2w.items()}
    out = []
    for m, links in enumerate(model_links(views, sfm, cfg, [largest, *other_models(sfm)])):
        row: dict = {"model": m, "views": links.num_views, "views_per_nerf": links.views_per_nerf, "link": None}
        if ref in links.T_to_model and len(links.T_to_model) >= 2:
            T = {i: sim3.invert_sim3(links.T_to_model[ref]) @ T_i for i, T_i in links.T_to_model.items() if i != ref}
            row["link"] = {views[i].name: _errors(T_i, truth[i]) for i, T_i in T.items()}
        out.append(row)
    return out


def _errors(T: np.ndarray, T_true: np.ndarray) -> dict:
    e = sim3.sim3_errors(T, T_true)
    return {"r_err_deg": float(e.r_err_deg), "t_err": float(e.t_err), "s_err": float(e.s_err),
            "failure": bool(e.is_failure())}  # fmt: skip


def _worst_link(record: dict, truth: np.ndarray) -> dict:
    """A record's link against the truth: its worst NeRF's errors, ``failure`` where any NeRF's link fails."""
    ref = record["reference"]["index"]
    T = np.stack([np.asarray(n["T_to_reference"], dtype=np.float64) for n in record["nerfs"]])
    errs = [_errors(T[i], truth[i]) for i in range(len(T)) if i != ref]
    return {**max(errs, key=lambda e: e["r_err_deg"]), "failure": any(e["failure"] for e in errs)}


def measure(spec: str, console: Console, again: bool = False) -> list[Row]:
    case, case_dir, registration_path = case_registration(spec)
    layout = case_layout(case)
    record = read_registration(registration_path)
    truth = sim3.to_reference_frame(
        np.stack([g["nerf_to_world"] for g in capture_ground_truth(layout, case_dir, optimized=False)])
    )
    commit = library_commit() if again else None
    rows = []
    for refusal in refusals(record):
        path, said = _register_again(layout, case_dir, refusal, [refusal["check"]], console)
        alone = None
        if (other := refused_by(said)) is not None:  # the other render-free check refused it: and the self-check?
            path, alone = _register_again(layout, case_dir, refusal, [refusal["check"], other], console)
        again_record = read_registration(path)
        worst = _worst_link(again_record, truth)
        views = [ViewSet.from_folder(n["render_folder"], name=n["name"]) for n in again_record["nerfs"]]
        row = Row(
            f"{case} ({case_dir.name})", refusal["check"], refusal["source"], refusal["mode"],
            refusal["error"].split("; ")[0],
            worst["r_err_deg"], worst["t_err"], worst["s_err"], worst["failure"], said,
            (again_record.get("pairs") or [{}])[0].get("self_check"), alone,
            _models(views, _sfm_of(case_dir, again_record), truth, ref=again_record["reference"]["index"]),
        )  # fmt: skip
        if commit is not None:
            off = ["camera"] if refusal["check"] == "camera" else []
            now_path, row.now = _register_again(layout, case_dir, refusal, off, console, tag=f"now_{commit}")
            now_record = read_registration(now_path)
            row.now_link, row.now_model_check = _worst_link(now_record, truth), now_record.get("model_check")
        rows.append(row)
        console.print(rows[-1])
    if not rows:
        console.print(f"[yellow]{registration_path}: no pose source was refused by the camera or model check[/]")
    return rows


def _now_cell(r: Row) -> str:
    """What the checks of this checkout said (``--again``): passed or refused, the verdict, the model contests."""
    if r.now is None or r.now_link is None:
        return "-"
    refused = r.now != "passed"
    cell = f"{'refused' if refused else 'passed'} at {r.now_link['r_err_deg']:.2f} deg: " + verdict(
        r.now_link["failure"], refused)
    for c in (r.now_model_check or {}).get("contests", []):
        if "registration_ncc" in c:
            cell += (f"; another model {c['r_err_deg']:.1f} deg away, NCC {c['model_ncc']:.2f} against "
                     f"{c['registration_ncc']:.2f}: {c['verdict']}")  # fmt: skip
    return cell


def _models_cell(models: list[dict]) -> str:
    cells = []
    for m in models:
        if m["link"] is None:
            cells.append(f"{m['views_per_nerf']}: links < 2 NeRFs")
            continue
        e = max(m["link"].values(), key=lambda x: x["r_err_deg"])
        cells.append(f"{m['views_per_nerf']}: {e['r_err_deg']:.2f} deg, s {e['s_err']:.3f}")
    return "; ".join(cells)


def main(cfg: CheckRefusals) -> None:
    console = Console()
    rows = [r for spec in cfg.cases for r in measure(spec, console, cfg.again)]
    lines = [
        "# The render-free checks' refusals against the truth",
        "",
        f"`python scripts/check_refusals.py {' '.join(sys.argv[1:])}`",
        "",
        "Each pose source the camera or the model check refused, registered again from the same renders and SfM "
        "without that check: the link (against the stored truth; the paper's rule 5 deg, 0.2, 0.1), the check's "
        "verdict on it, what the remaining checks said (where the other render-free check refused it too, what the "
        "cross-render check said with both off: *alone*), and each SfM model's own link (views per NeRF; the largest "
        "first, before the refinement). NCC and depth are the cross-render check's last run."
        + (" *Now*: registered again with this checkout's library, every check on but the camera check where it "
           "refused (the model check's contests: the other model's link and the registration's cross-rendered on the "
           "same views)." if cfg.again else ""),
        "",
        "| case | refused by | source | link r / t / s | its verdict | the other checks | their verdict | NCC | "
        "depth | SfM models' links |" + (" now |" if cfg.again else ""),
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |" + (" --- |" if cfg.again else ""),
    ]
    for r in rows:
        sc = r.self_check or {}
        ncc = f"{sc['ncc']:.2f}" if sc.get("ncc") is not None else "-"
        depth = (f"{sc['depth_i_in_j']:+.3f} / {sc['depth_j_in_i']:+.3f}"
                 if sc.get("depth_i_in_j") is not None else "-")  # fmt: skip
        passed = r.checks_without == "passed"
        others = "passed" if passed else r.checks_without[:160]
        if r.self_check_alone is not None:
            alone = r.self_check_alone == "passed"
            others += (f"; alone: {'passed' if alone else r.self_check_alone[:120]}, "
                       f"{verdict(r.link_failure, not alone)}")  # fmt: skip
        lines.append(
            f"| {r.case} | {r.check} check | {r.source} ({r.mode}) | {r.r_err_deg:.2f} deg / {r.t_err:.3f} / "
            f"{r.s_err:.3f} | "
            f"{verdict(r.link_failure, True)} | {others} | "
            f"{verdict(r.link_failure, not passed)} | {ncc} | {depth} | {_models_cell(r.models)} |"
            + (f" {_now_cell(r)} |" if cfg.again else "")
        )
    write_text_atomic(cfg.report.with_suffix(".json"), json.dumps([asdict(r) for r in rows], indent=1) + "\n")
    write_text_atomic(cfg.report, "\n".join(lines) + "\n")
    console.print(f"wrote {cfg.report}")


if __name__ == "__main__":
    main(tyro.cli(CheckRefusals))
