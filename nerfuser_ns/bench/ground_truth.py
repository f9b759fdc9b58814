"""Ground-truth scoring of a registration result: the paper's r/t/s errors and its failure rule.

Scoring is applied to a registration record (what ``ns-nerfuser-register`` writes) after the fact; the registration
itself never sees the truth. The truth is each NeRF's frame -> world SIM(3): from a generated scene's
``ground_truth.json`` (the capture frame, composed with the run's dataparser map) or from one JSON file per NeRF.

Command line (writes a scored copy, never the input)::

    python -m nerfuser_ns.bench.ground_truth registration.json --gt-transforms a.json b.json
    python -m nerfuser_ns.bench.ground_truth registration.json --ground-truth scene/ --gt-captures capture_a capture_b
"""

from __future__ import annotations

import copy
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tyro
from jaxtyping import Float
from rich.console import Console
from rich.table import Table
from rich.text import Text

from nerfuser_ns import runs, sim3
from nerfuser_ns.registration import RegistrationError, RegistrationResult, read_registration, write_registration
from nerfuser_ns.spec import FusionSpecError, validate_sim3

FAILURE_RULE = "NaN, r_err > 5 deg, t_err > 0.2 (reference units) or s_err = |log s| > 0.1"


def _f(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def ground_truth_errors(
    T_to_ref: Float[np.ndarray, "k 4 4"], gt_nerf_to_world: Sequence[np.ndarray], reference: int
) -> list[dict]:
    """Paper's r/t/s errors of every ``T_i->ref`` against ground truth ``inv(W_ref) W_i`` (t in reference units)."""
    W = sim3.to_homogeneous(np.asarray(gt_nerf_to_world, dtype=np.float64))
    out = []
    for i in range(len(T_to_ref)):
        T_true = sim3.relative_sim3(W[reference], W[i])
        e = sim3.sim3_errors(T_to_ref[i], T_true)
        out.append({"r_err_deg": _f(e.r_err_deg), "t_err": _f(e.t_err), "s_err": _f(e.s_err),
                    "failure": bool(e.is_failure()), "T_to_reference_true": T_true.tolist()})  # fmt: skip
    return out


def reference_index(record: dict) -> int:
    """The reference NeRF of a record: as recorded, or (a hand-written file) the first whose transform is identity."""
    if "reference" in record:
        return int(record["reference"]["index"])
    identity = [i for i, n in enumerate(record["nerfs"]) if np.allclose(n["T_to_reference"], np.eye(4), atol=1e-9)]
    if not identity:
        raise RegistrationError("the registration names no reference NeRF and none of its transforms is identity; "
                                'add "reference": {"index": i, "name": "..."}')  # fmt: skip
    return identity[0]


def score_registration(record: RegistrationResult | dict, gt_nerf_to_world: Sequence[np.ndarray]) -> dict:
    """The record of a registration (the typed result or its record) with ``ground_truth`` errors per NeRF and overall
    (``failure``: any NeRF failed); the input is left as it was."""
    if isinstance(record, RegistrationResult):
        record = record.to_record()
    nerfs = record["nerfs"]
    if len(gt_nerf_to_world) != len(nerfs):
        raise RegistrationError(f"ground truth given for {len(gt_nerf_to_world)} NeRFs, the registration has "
                                f"{len(nerfs)}")  # fmt: skip
    ref = reference_index(record)
    T_to_ref = np.stack([np.asarray(n["T_to_reference"], dtype=np.float64) for n in nerfs])
    errors = ground_truth_errors(T_to_ref, gt_nerf_to_world, ref)
    scored = copy.deepcopy(record)
    for n, g in zip(scored["nerfs"], errors, strict=True):
        if isinstance(n.get("T_to_reference"), np.ndarray):
            n["T_to_reference"] = n["T_to_reference"].tolist()
        n["ground_truth"] = g
    scored["ground_truth"] = {"failure": any(g["failure"] for i, g in enumerate(errors) if i != ref),
                              "rule": FAILURE_RULE}  # fmt: skip
    return scored


def load_ground_truth_captures(path: Path, captures: Sequence[str]) -> list[np.ndarray]:
    """``capture_to_world`` of the named captures from a generated scene's ground_truth.json."""
    path = Path(path)
    path = path / "ground_truth.json" if path.is_dir() else path
    try:
        gt = json.loads(path.read_text())
        table = {c["name"]: np.asarray(c["capture_to_world"], dtype=np.float64) for c in gt["captures"]}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise RegistrationError(f"{path}: not a readable ground_truth.json ({type(e).__name__}: {e})") from None
    missing = [c for c in captures if c not in table]
    if missing:
        raise RegistrationError(f"{path}: no capture named {missing[0]!r}; it has {sorted(table)}")
    return [table[c] for c in captures]


def nerf_to_world_from_captures(
    capture_to_world: Sequence[np.ndarray], data_to_nerf: Sequence[np.ndarray | None]
) -> list[np.ndarray]:
    """A run's NeRF frame is its dataset (capture) frame mapped by the dataparser: world <- capture <- NeRF."""
    return [c2w if d2n is None else c2w @ np.linalg.inv(d2n) for c2w, d2n in zip(capture_to_world, data_to_nerf,
                                                                                    strict=True)]  # fmt: skip


def read_gt_transforms(paths: Sequence[Path]) -> list[np.ndarray]:
    """One JSON file per NeRF: its NeRF-frame -> world SIM(3), a 3x4 or 4x4 list or ``{"nerf_to_world": ...}``."""
    out = []
    for path in paths:
        try:
            data = json.loads(Path(path).read_text())
            T = np.asarray(data["nerf_to_world"] if isinstance(data, dict) else data, dtype=np.float64)
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise RegistrationError(f"{path}: unreadable ground-truth transform ({type(e).__name__})") from None
        try:  # a "truth" that is not a SIM(3) (sheared, mirrored) would score every result wrong
            out.append(validate_sim3(T, f"{path}: nerf_to_world"))
        except FusionSpecError as e:
            raise RegistrationError(str(e)) from None
    return out


def print_scores(record: dict, console: Console) -> None:
    table = Table(title=f"Ground truth, in the frame of {record['nerfs'][reference_index(record)]['name']}")
    for col in ("NeRF", "r_err (deg)", "t_err", "s_err", "ok"):
        table.add_column(col, justify="left" if col == "NeRF" else "right")
    for n in record["nerfs"]:
        g = n["ground_truth"]
        cells = ["-" if g[k] is None else format(g[k], spec)
                 for k, spec in (("r_err_deg", ".4f"), ("t_err", ".2e"), ("s_err", ".2e"))]  # fmt: skip
        table.add_row(n["name"], *cells, "[red]FAIL[/]" if g["failure"] else "[green]ok[/]")
    console.print(table)
    if record["ground_truth"]["failure"]:
        console.print("[bold yellow]ground truth: the registration is a failure by the paper's rule[/]")


@dataclass
class ScoreCommand:
    """Score a registration file against ground truth and write the scored copy."""

    registration: tyro.conf.Positional[Path]
    """The registration file (as ns-nerfuser-register wrote it)."""
    ground_truth: Path | None = None
    """ground_truth.json of a generated scene (needs --gt-captures)."""
    gt_captures: list[str] = field(default_factory=list)
    """With --ground-truth: the capture each NeRF was trained on, in the registration's order."""
    gt_transforms: list[Path] = field(default_factory=list)
    """Instead of --ground-truth: per NeRF, a JSON file with its NeRF-frame -> world SIM(3)."""
    output: Path | None = None
    """Where to write the scored record (default: <registration stem>_scored.json beside it)."""

    def truth(self, record: dict) -> list[np.ndarray]:
        k = len(record["nerfs"])
        if (self.ground_truth is None) == (not self.gt_transforms):
            raise RegistrationError("pass either --ground-truth with --gt-captures or --gt-transforms")
        if self.gt_transforms:
            if len(self.gt_transforms) != k:
                raise RegistrationError(f"--gt-transforms has {len(self.gt_transforms)} files for {k} NeRFs")
            return read_gt_transforms(self.gt_transforms)
        if len(self.gt_captures) != k:
            raise RegistrationError(f"--gt-captures names {len(self.gt_captures)} captures for {k} NeRFs")
        capture_to_world = load_ground_truth_captures(self.ground_truth, self.gt_captures)
        data_to_nerf = [None if n.get("config") is None else runs.read_dataparser_transform(n["config"])
                        for n in record["nerfs"]]  # fmt: skip
        return nerf_to_world_from_captures(capture_to_world, data_to_nerf)

    def main(self, console: Console | None = None) -> dict:
        console = console or Console()
        output = self.output or self.registration.with_name(self.registration.stem + "_scored.json")
        if output.absolute() == self.registration.absolute():
            raise RegistrationError(f"--output {output} is the input registration file; write the scores elsewhere")
        record = read_registration(self.registration)
        scored = score_registration(record, self.truth(record))
        write_registration(scored, output)
        print_scores(scored, console)
        console.print(f"[bold green]wrote[/] {output}")
        return scored


def entrypoint() -> None:
    try:
        ScoreCommand.main(tyro.cli(ScoreCommand))
    except (RegistrationError, runs.RunLoadError) as e:
        # soft_wrap: one line however long the paths (a wrapped message reads as several errors); the message as
        # plain text (no markup: paths and matrices hold brackets)
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        Console(stderr=True, soft_wrap=True).print(Text.assemble(("error: ", "bold red"), (message, "red")),
                                                   highlight=False)  # fmt: skip
        sys.exit(1)


if __name__ == "__main__":
    entrypoint()
