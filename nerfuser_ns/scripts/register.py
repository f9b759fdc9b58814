"""``ns-nerfuser-register``: register N >= 2 trained nerfstudio runs by re-rendering them (NeRFuser, Sec. 3.2).

Example::

    ns-nerfuser-register --configs outputs/a/nerfacto/run/config.yml outputs/b/nerfacto/run/config.yml \\
        --output registration.json

Writes one JSON file with every NeRF's SIM(3) into the reference NeRF's frame (the first by default), the pairwise
transforms, the settings, diagnostics and timings. Bad inputs print one red line and exit with status 1, writing
no output (a solution the checks refused is kept, marked, in the work folder for inspection).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import tyro
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from nerfuser_ns.files import write_text_atomic
from nerfuser_ns.registration import (
    RegistrationConfig,
    RegistrationError,
    RegistrationFailed,
    capture_findings,
    register,
    work_dir_for,
    write_registration,
)
from nerfuser_ns.renderers import NerfstudioRenderer
from nerfuser_ns.runs import RunLoadError, check_dataset_folder, check_device, default_device, run_names
from nerfuser_ns.scripts.cli import parse
from nerfuser_ns.spec import fusion_spec_text

CONSOLE = Console(width=120)
ERR_CONSOLE = Console(stderr=True, soft_wrap=True)


@dataclass
class RegisterCommand(RegistrationConfig):
    """Register trained nerfstudio runs by re-rendering them: one SfM over all the renders (mode sfm), 3D matches of
    the renders' keypoints (mode known-geometry) or pairwise registrations joined by a pose graph (mode graph)."""

    configs: list[Path] = field(default_factory=list)
    """config.yml of each run (at least 2), as ns-train wrote it."""
    output: Path = Path("registration.json")
    """Registration file to write (JSON, written atomically)."""
    fusion_spec: Path | None = None
    """Also write a fusion spec here (e.g. fusion.json) for ns-train nerfuser and ns-eval: the registration file, and
    the reference run's held-out images as the test images ("test_run"; left out where --data moved a dataset, whose
    held-out images the spec cannot find). A file already there is replaced only where it holds the same."""
    work_dir: Path | None = None
    """Folder for renders and SfM files, reused by later runs with the same inputs (default: <output stem>_work)."""
    data: list[Path] = field(default_factory=list)
    """Dataset folder of each run, in --configs order, for runs whose config.yml points at a dataset that has moved
    (the training poses and the default render camera are read from it)."""
    device: str = field(default_factory=default_device)
    """Torch device the runs render on (default: cuda when torch sees a GPU, else cpu)."""
    eval_num_rays_per_chunk: int | None = None
    """Rays per forward pass when rendering (default: each run's own)."""
    def main(self, renderers: list | None = None) -> dict:  # the record written
        """Register, write the file, print the summary. ``renderers`` replaces the runs of ``configs`` (tests)."""
        if renderers is None:
            check_device(self.device)
            if len(self.configs) < 2:
                raise RegistrationError(f"pass at least 2 runs with --configs (got {len(self.configs)})")
            if self.data and len(self.data) != len(self.configs):
                raise RegistrationError(
                    f"--data names {len(self.data)} dataset folders for {len(self.configs)} runs; name one per run"
                )
            for folder in self.data:
                check_dataset_folder(folder)
            names = run_names(list(self.configs))
            renderers = [
                NerfstudioRenderer(c, device=self.device, eval_num_rays_per_chunk=self.eval_num_rays_per_chunk,
                                   data_override=self.data[i] if self.data else None, name=names[i])
                for i, c in enumerate(self.configs)
            ]  # fmt: skip
        work_dir = self.work_dir or work_dir_for(self.output)
        self._check_outputs(work_dir, renderers)
        spec_text = None
        if self.fusion_spec is not None:  # an index out of range fails in register(), before the spec is written
            spec_text = self._spec_text(renderers[self.reference % len(renderers)].name)
        config = RegistrationConfig(**{f: getattr(self, f) for f in RegistrationConfig.__dataclass_fields__})
        try:
            result = register(renderers, config, work_dir, console=CONSOLE)
        except RegistrationFailed as e:
            # Keep the rejected solution for inspection (threshold calibration), never as the output: marked, so the
            # fusion refuses it unless a user removes the mark on purpose.
            write_registration({**e.record, "refused": str(e)}, Path(work_dir) / "rejected_registration.json")
            raise
        record = result.to_record()
        write_registration(record, self.output)
        print_summary(record)
        odd = [n.name for n in result.nerfs if not 1e-3 <= n.scale_to_reference <= 1e3]
        if odd:
            CONSOLE.print(f"[bold yellow]warning: implausible scale to the reference for {', '.join(odd)} (outside "
                          "1e-3..1e3): check that these runs show the same place[/]")  # fmt: skip
        CONSOLE.print(f"[bold green]wrote[/] {self.output}")
        if spec_text is not None:
            write_text_atomic(self.fusion_spec, spec_text)
            CONSOLE.print(f"[bold green]wrote[/] {self.fusion_spec}")
        tip = camera_optimizer_tip(renderers)
        if tip is not None:
            CONSOLE.print(tip, style="dim", soft_wrap=True, highlight=False, markup=False)
        if self.fusion_spec is not None:
            scored = "ns-eval scores the blend" if not self.data else "add test images to score it with ns-eval"
            CONSOLE.print(f"next: ns-train nerfuser --data {self.fusion_spec} (then ns-viewer; {scored})",
                          soft_wrap=True, highlight=False, markup=False)  # fmt: skip
        else:
            CONSOLE.print(f"next: ns-train nerfuser --data {self.output} (then ns-viewer); to score the blend with "
                          "ns-eval, --fusion-spec fusion.json writes a spec whose test images are the reference run's "
                          "held-out ones", soft_wrap=True, highlight=False, markup=False)  # fmt: skip
        return record

    def _spec_text(self, reference_name: str) -> str:
        """The fusion spec ``--fusion-spec`` writes, checked before any rendering: its path is a file that does not
        exist or already holds the same spec (never a user's own spec replaced); its folder is checked writable with
        the other outputs (:meth:`_check_outputs`)."""
        spec = self.fusion_spec.absolute()
        # no test_run where --data moved a dataset: the held-out images are read where the run's config.yml says
        text = fusion_spec_text(registration=os.path.relpath(self.output.absolute(), spec.parent),
                                test_run=None if self.data else reference_name)  # fmt: skip
        if spec == self.output.absolute():
            raise RegistrationError(f"--fusion-spec {self.fusion_spec} is the registration file; pass another path")
        if spec.is_dir():
            raise RegistrationError(f"--fusion-spec {self.fusion_spec} is a folder; pass a file path (fusion.json)")
        if spec.exists() and spec.read_text() != text:
            raise RegistrationError(f"--fusion-spec {self.fusion_spec} exists and holds another spec; pass another "
                                    "path or remove it")  # fmt: skip
        return text

    def _check_outputs(self, work_dir: Path, renderers) -> None:
        """Before any rendering: the output is a writable file path that is not an input nor inside a run folder; the
        work folder and the fusion spec's folder are writable."""
        output = self.output.absolute()
        for r in renderers:
            config_path = getattr(r, "config_path", None)
            if config_path is None:
                continue
            run_dir = Path(config_path).absolute().parent
            if output == Path(config_path).absolute() or run_dir in output.parents:
                raise RegistrationError(
                    f"--output {self.output} is inside the run folder {run_dir}; write the registration elsewhere"
                )
        if output.is_dir():
            raise RegistrationError(f"--output {self.output} is a folder; pass a file path (e.g. registration.json)")
        paths = [(output, "--output"), (Path(work_dir).absolute() / "x", "--work-dir")]
        if self.fusion_spec is not None:
            paths.append((self.fusion_spec.absolute(), "--fusion-spec"))
        for path, what in paths:
            parent = next((q for q in path.parents if q.exists()), None)
            if parent is None or not parent.is_dir():
                raise RegistrationError(f"{what} {path.parent}: {parent} is not a folder; pass another path")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise RegistrationError(f"{what} {path.parent}: {parent} is not writable; pass another path")


def camera_optimizer_tip(renderers: list) -> str | None:
    """One line for runs trained with a camera optimiser (nerfacto's default), which moves a NeRF's content off its
    dataset's frame: where the capture's own poses are good, training without it registers more accurately. None when
    no run has one on (or a renderer does not say)."""
    names = [r.name for r in renderers if getattr(r, "camera_optimizer_mode", None) not in (None, "off")]
    if not names:
        return None
    return (f"tip: {', '.join(short_names(names).values())} trained with a camera optimiser, which moves each NeRF "
            "off its dataset's poses; where the captures are posed well (a clean COLMAP run), runs trained with "
            "--pipeline.model.camera-optimizer.mode off registered 1.5-5x closer in rotation on our generated captures "
            "(docs/your_own_captures.md, \"Training for fusion\")")  # fmt: skip


def _fmt(x, spec: str = ".3g") -> str:
    return "-" if x is None else format(x, spec)


def short_names(names: list[str]) -> dict[str, str]:
    """Each NeRF name as the tables show it: config paths without the parts every one of them shares (the leading
    folders, a common file name such as ``config.yml``), so that rows stay distinct in a narrow terminal; the names
    as they are when that would not leave them distinct."""
    parts = [PurePath(n).parts for n in names]
    if len(set(names)) < 2:
        return {n: n for n in names}
    end = min(len(q) for q in parts)
    if end > 1 and len({q[-1] for q in parts}) == 1:
        parts = [q[:-1] for q in parts]  # the same file name everywhere (config.yml)
        end -= 1
    start = 0
    while start < end - 1 and len({q[start] for q in parts}) == 1:
        start += 1
    short = ["/".join(q[start:]) for q in parts]
    if len(set(short)) < len(set(names)) or not all(short):
        return {n: n for n in names}
    return dict(zip(names, short, strict=True))


def print_summary(record: dict, console: Console = CONSOLE) -> None:
    """Rich tables: per NeRF (views, scale, residuals) and per pair (overlap, self-check); NeRFs by their
    :func:`short_names`."""
    names = [n["name"] for n in record["nerfs"]]
    short = short_names(names)

    def pair(pair_names: list[str]) -> str:
        return " / ".join(short.get(n, n) for n in pair_names)

    table = Table(title=f"Registration into the frame of {record['reference']['name']}")
    for col in ("NeRF", "rendered", "kept", "registered", "scale", "scale spread", "rot res (deg)", "centre res",
                "estimator"):
        table.add_column(col, justify="left" if col in ("NeRF", "estimator") else "right")
    for i, n in enumerate(record["nerfs"]):
        v, res = n["views"], n["residuals"]
        row = [
            short[n["name"]], str(v["rendered"]), str(v["kept"]), str(v["registered"]),
            _fmt(n["scale_to_reference"], ".4g"),
            _fmt(n["scale_spread"], ".2e"), _fmt(res["rotation_deg_median"], ".3f"), _fmt(res["centre_median"], ".2e"),
            n["estimator"] + (" + BA" if (record.get("refinement") or {}).get("used")
                              and i != record["reference"]["index"] else ""),
        ]
        table.add_row(*row)
    console.print(table)
    checked = [p["self_check"] is not None for p in record["pairs"]]
    caption = None
    if checked and not any(checked):
        caption = "-: no pair cross-render checked (--self-check-views 0)"
    elif not all(checked):  # the check follows the spanning tree of the largest overlaps
        caption = "-: not cross-render checked; its NeRFs are linked, and checked, through the pairs that overlap most"
    pairs = Table(title="NeRF pairs", caption=caption)
    for col in ("pair", "covisible 3D points", "cross-render NCC", "depth", "check"):
        pairs.add_column(col, justify="left" if col == "pair" else "right")
    for p in record["pairs"]:
        sc = p["self_check"]
        # the depth check's log ratio: the direction farther from 0, as the check judges it
        depths = [] if sc is None else [d for d in (sc.get("depth_i_in_j"), sc.get("depth_j_in_i")) if d is not None]
        pairs.add_row(pair(p["names"]), str(p["covisible_points"]), "-" if sc is None else _fmt(sc["ncc"], ".3f"),
                      f"{max(depths, key=abs):+.3f}" if depths else "-",
                      "-" if sc is None else ("[green]passed[/]" if sc["passed"] else "[red]failed[/]"))
    console.print(pairs)
    ref = record.get("refinement")
    if ref is not None:
        if ref["used"]:
            console.print(
                f"rigid-set bundle adjustment: {ref['points']} points seen by two NeRFs, {ref['observations']} "
                f"observations, reprojection RMS {ref['rms_px_before']:.2f} -> {ref['rms_px_after']:.2f} px "
                f"(median {ref['median_px_after']:.2f}); largest change "
                f"{max(c['r_deg'] for c in ref['change']):.3f} deg"
            )
        else:
            console.print(f"[yellow]rigid-set bundle adjustment not used: {ref.get('reason', 'failed')}[/]")
    kg = record.get("known_geometry")
    if kg is not None:
        for p in kg["pairs"]:
            hyps = ", ".join(f"{h['inliers']} inliers" + ("" if h["self_check_ncc"] is None
                                                          else f" (NCC {h['self_check_ncc']:.2f})")
                             for h in p["hypotheses"])  # fmt: skip
            console.print(f"known geometry {pair(p['names'])}: {p['matches']} 3D matches over "
                          f"{p['view_pairs']} view pairs; hypotheses: {hyps or 'none'}")  # fmt: skip
        solve = kg["joint_solve"]
        if solve.get("used"):
            console.print(f"joint solve: {solve['matches']} matches, relative residual RMS "
                          f"{solve['rms_relative_before']:.4f} -> {solve['rms_relative_after']:.4f}")  # fmt: skip
    graph = record.get("graph")
    if graph is not None:
        _print_graph(graph, console, pair)
    t, made = record["timings_s"], record.get("compute_timings_s", {})
    reused = record.get("reused", {})
    sfm_reused = reused.get("sfm", False)
    was_reused = {"render": any(reused.get("renders", [])), "features": sfm_reused, "matching": sfm_reused,
                  "mapping": sfm_reused}  # fmt: skip
    parts = [
        f"{k} {v:.1f} (reused; {made[k]:.1f} when made)" if was_reused.get(k) and made.get(k) is not None
        else f"{k} {v:.1f}"
        for k, v in t.items()
    ]  # fmt: skip
    console.print("time (s): " + ", ".join(parts))
    for name, checks in (record.get("capture_checks") or {}).items():
        found = capture_findings(checks)
        if found:  # said at the start too, but that scrolled away during the renders
            what = escape(f"NeRF {short.get(name, name)}'s capture: {'; '.join(found)}")
            console.print(f"[yellow]warning: {what}. "
                          "These links were made from a run trained on those poses, which no registration mends: "
                          "check its dataset with ns-nerfuser-check-capture and fix it as it advises "
                          "(docs/your_own_captures.md)[/]", soft_wrap=True, highlight=False)  # fmt: skip


def _print_graph(graph: dict, console: Console, pair: Callable[[list[str]], str]) -> None:
    """The pose graph: per candidate pair its retrieval score and verified inliers, its registration's inliers, status
    and residual after the solve; the cycles."""
    cand = graph["candidates"]
    table = Table(title=f"Pose graph: {len(cand['pairs'])} candidate pairs ({cand['source']})")
    for col in ("pair", "score", "verified", "inliers", "status", "r res (deg)", "t res", "|log s| res", "reason"):
        table.add_column(col, justify="left" if col in ("pair", "status", "reason") else "right")
    colour = {"kept": "green", "unverified": "yellow", "dropped": "red", "rejected": "red"}
    for e in graph["edges"]:
        res = e["residual"] or {}
        inliers = None if e["chosen"] is None else e["hypotheses"][e["chosen"]]["inliers"]
        table.add_row(pair(e["names"]), _fmt(e["retrieval_score"], ".2f"), _fmt(e.get("verified_inliers"), "d"),
                      _fmt(inliers, "d"),
                      f"[{colour[e['status']]}]{e['status']}[/]", _fmt(res.get("rotation_deg"), ".3f"),
                      _fmt(res.get("translation"), ".2e"), _fmt(res.get("log_scale"), ".2e"), e["reason"])  # fmt: skip
    console.print(table)
    cycles = graph["cycles"]
    if cycles:
        worst = max(cycles, key=lambda c: c["residual"]["rotation_deg"] or 0.0)
        console.print(f"cycles: {sum(c['passed'] for c in cycles)} of {len(cycles)} within the thresholds; worst "
                      f"{' > '.join(worst['names'])}: {_fmt(worst['residual']['rotation_deg'], '.3f')} deg, "
                      f"translation {_fmt(worst['residual']['translation'], '.2e')}")  # fmt: skip
    else:
        console.print("[yellow]cycles: none; the registered pairs form a tree, no pair is verified by another[/]")


def run(cmd: RegisterCommand, renderers: list | None = None) -> int:
    """Run the command; known bad-input errors become one red line and exit status 1."""
    try:
        cmd.main(renderers)
    except (RegistrationError, RunLoadError) as e:
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        ERR_CONSOLE.print(Text.assemble(("error: ", "bold red"), (message, "red")), highlight=False)
        return 1
    except KeyboardInterrupt:
        # finished renders stay in the work folder (written atomically) and are reused by the next run
        ERR_CONSOLE.print(Text.assemble(("interrupted: ", "bold red"), ("nothing written; renders made so far are "
                                                                         "kept for the next run", "red")))  # fmt: skip
        return 130
    return 0


def entrypoint() -> None:
    """Console script ``ns-nerfuser-register``."""
    tyro.extras.set_accent_color("bright_yellow")
    sys.exit(run(parse(RegisterCommand)))


if __name__ == "__main__":
    entrypoint()
