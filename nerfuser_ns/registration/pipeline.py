"""The registration pipeline: the automatic pose-source cascade, one attempt composed of the steps, and the
nerfstudio-run entry point.

One attempt (:func:`register_once`), mode ``sfm`` (the paper's): render
(:mod:`~nerfuser_ns.registration.render_cache`) -> SfM (:mod:`~nerfuser_ns.registration.sfm`) -> per-NeRF SIM(3)
(:mod:`~nerfuser_ns.registration.estimate`) -> rigid-set bundle adjustment (:mod:`~nerfuser_ns.registration.refine`)
-> cross-render self-check (:mod:`~nerfuser_ns.registration.self_check`) -> the record
(:mod:`~nerfuser_ns.registration.record`). Mode ``known-geometry`` (ours, :func:`register_known_geometry`): render
with depth -> keypoints lifted to 3D, candidate view pairs, 3D-3D matches, SIM(3) hypotheses scored by the self-check
(:mod:`~nerfuser_ns.registration.known_geometry`, :mod:`~nerfuser_ns.registration.retrieval`) -> joint solve ->
rigid-set bundle adjustment on the matches -> re-render refinement at co-located views
(:mod:`~nerfuser_ns.registration.colocated`) -> self-check -> the record. Mode ``graph`` (ours, for many NeRFs,
:func:`register_graph`): render with depth -> keypoints lifted to 3D -> candidate NeRF pairs (retrieval, or the
neighbours given) -> each pair registered on known geometry and cross-render checked (an edge, or a rejected pair) ->
cycle check and robust pose-graph solve (:mod:`~nerfuser_ns.registration.pose_graph`) -> self-check -> the record.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.capture_check import SQUARE_PIXEL_ADVICE, FoldCheck, check_dataset, fold_check, intrinsics_check
from nerfuser_ns.match_check import MatchCheck, check_dataset_matches
from nerfuser_ns.registration.assemble import build_known_geometry_result, build_result
from nerfuser_ns.registration.colocated import refine_colocated
from nerfuser_ns.registration.config import (
    CONSOLE,
    DEFAULT_RENDER_SIZE,
    SUGGESTION,
    RegistrationConfig,
    RegistrationError,
    RegistrationFailed,
    TwinLinked,
    json_float,
    validate_settings,
)
from nerfuser_ns.registration.direct import align_direct
from nerfuser_ns.registration.estimate import NerfEstimate, estimate_transforms
from nerfuser_ns.registration.graph import register_graph
from nerfuser_ns.registration.known_geometry import (
    joint_solve,
)
from nerfuser_ns.registration.pairwise import (
    chain_from_reference,
    check_depth,
    check_views,
    choose_hypothesis,
    matches_per_pair,
    pair_hypotheses,
    pair_summary,
    render_and_lift,
    views_matched,
)
from nerfuser_ns.registration.record import RegistrationResult, capture_folded, work_dir_for, write_registration
from nerfuser_ns.registration.reference_colour import compose_with_reference, reference_colour
from nerfuser_ns.registration.refine import refine_on_matches, refine_transforms
from nerfuser_ns.registration.render_cache import (
    ViewSet,
    check_inputs,
    check_kept_views,
    render_views_cached,
)
from nerfuser_ns.registration.self_check import (
    CrossRenderCheck,
    best_views,
    camera_failure,
    camera_residuals,
    covisibility,
    cross_render_check,
    failure_message,
    model_contest,
    model_disagreements,
    model_failure_line,
    pair_failure,
    spanning_pairs,
)
from nerfuser_ns.registration.sfm import SfMResult, check_registered_views, run_sfm
from nerfuser_ns.registration.twin_check import twin_check
from nerfuser_ns.renderers import NerfstudioRenderer, Renderer, gives_depth
from nerfuser_ns.runs import default_device, run_names


@dataclass
class SamplingChoice:
    """One pose-sampling setting to try, and why it was chosen."""

    config: RegistrationConfig
    """The registration settings with a concrete pose source and render camera."""
    reason: str
    """Why this source and camera (printed and recorded)."""


def _training_cameras_available(renderer: Renderer) -> str | None:
    """None when the renderer's training poses can be read, else the reason why not (one line)."""
    try:
        poses = renderer.training_poses()
    except (RegistrationError, ValueError, OSError) as e:  # runs.RunLoadError is a ValueError
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    return None if poses is not None and len(poses) > 0 else "it has no training poses"


def resolve_sampling(renderers: Sequence[Renderer], config: RegistrationConfig) -> list[SamplingChoice]:
    """The pose-sampling settings to try, in order: the user's choice, or for ``source="auto"`` the training poses
    (then training + hemisphere, then the hemisphere) when every run's dataset is readable, else the hemisphere; in
    mode ``sfm`` the automatic choice ends with known geometry on the most views (training + hemisphere, else the
    hemisphere) when every renderer gives depth.

    The render camera defaults to the reference run's training cameras' horizontal field of view and aspect, with
    ``size`` pixels along the longer side; :data:`DEFAULT_RENDER_SIZE` when they are unknown.
    """
    sc = config.sampling
    k = len(renderers)
    missing = {}
    if sc.source == "auto" or sc.width is None or sc.height is None or sc.fov_deg is None:
        for i, r in enumerate(renderers):
            why = _training_cameras_available(r)
            if why is not None:
                missing[i] = why
    width, height, fov = sc.width, sc.height, sc.fov_deg
    camera_note = "render size and field of view as given"
    if width is None or height is None or fov is None:
        ref = config.reference % k if -k <= config.reference < k else 0
        intr = None if ref in missing else getattr(renderers[ref], "training_intrinsics", lambda: None)()
        if intr is not None:
            factor = sc.size / max(intr.width, intr.height)
            auto_w, auto_h = max(8, round(intr.width * factor)), max(8, round(intr.height * factor))
            auto_fov = math.degrees(2 * math.atan2(intr.width / 2, intr.fx))
            camera_note = f"render camera from {renderers[ref].name}'s training cameras"
        else:
            auto_w, auto_h, auto_fov = DEFAULT_RENDER_SIZE
            camera_note = "render camera {}x{} at {:g} deg (the reference run's training cameras are unknown)".format(
                *DEFAULT_RENDER_SIZE)
        width = auto_w if width is None else width
        height = auto_h if height is None else height
        fov = auto_fov if fov is None else fov
    if sc.source != "auto":
        sources = [(sc.source, "as given")]
    elif missing:
        i, why = next(iter(missing.items()))
        sources = [("hemisphere", f"training poses unavailable ({renderers[i].name}: {why})")]
    else:
        sources = [("training", "every run's dataset is readable"),
                   ("both", "the training poses alone did not register"),
                   ("hemisphere", "neither the training poses nor training + hemisphere registered")]  # fmt: skip
    modes = [config.mode] * len(sources)
    if sc.source == "auto" and config.mode == "sfm" and all(gives_depth(r) for r in renderers):
        # SfM links views by their features alone; known geometry also knows where each view looks, and registers
        # pairs that SfM splits into separate models or merges wrongly (docs/known_geometry.md)
        widest = "hemisphere" if missing else "both"  # the most views
        sources.append((widest, "SfM registered with no pose source: known geometry (ours, --mode known-geometry) "
                                "on the most views"))  # fmt: skip
        modes.append("known-geometry")
    out = []
    for (source, why), mode in zip(sources, modes, strict=True):
        sampling = replace(sc, source=source, width=int(width), height=int(height), fov_deg=float(fov))
        out.append(SamplingChoice(replace(config, mode=mode, sampling=sampling), f"{why}; {camera_note}"))
    return out


def check_captures(renderers: Sequence[Renderer], console: Console = CONSOLE) -> dict | None:
    """The fold check (of the run's dataset file in file order where the renderer names it, else of its training
    cameras) and the camera check (:mod:`nerfuser_ns.capture_check`), and the match check
    (:mod:`nerfuser_ns.match_check`) of its dataset's COLMAP files, per NeRF name (the fold check's record with the
    camera's under ``camera`` and the match check's under ``matches``; None when no renderer knows its training
    images); a folded or drifted capture is warned about: its run was trained on those poses, which no registration
    mends."""
    out = {}
    for r in renderers:
        files = getattr(r, "training_image_files", None)
        if files is None:
            continue
        try:
            poses, names = r.training_poses(), [str(f) for f in files()]
            camera = getattr(r, "training_intrinsics", lambda: None)()  # optional (Renderer.training_poses)
        except (RegistrationError, ValueError, OSError):  # no dataset: resolve_sampling says so
            continue
        if poses is None or len(poses) != len(names):
            continue
        dataset = getattr(r, "dataset_path", lambda: None)()  # optional: a renderer without a dataset file has none
        check = _dataset_fold_check(dataset) or fold_check(poses, names)
        out[r.name] = check.to_record()
        warning = check.warning(f"NeRF {r.name}")
        if warning is not None:
            console.print(f"[yellow]warning: {warning}. The run was trained on those poses and no registration mends "
                          "that: check its dataset with ns-nerfuser-check-capture, pose it again or train on its "
                          "larger side (docs/your_own_captures.md)[/]")  # fmt: skip
        matches = _match_check(dataset)
        if matches is not None:
            out[r.name]["matches"] = matches.to_record()
            warning = matches.warning(f"NeRF {r.name}'s dataset")
            if warning is not None:
                mend = ("train on its larger side (ns-nerfuser-check-capture --write-larger-side: its views form two "
                        "sides)" if matches.smaller_side is not None else "pose it again")  # fmt: skip
                console.print(f"[yellow]warning: {warning}. The run was trained on those poses and no registration "
                              f"mends that: check its dataset with ns-nerfuser-check-capture and {mend} "
                              "(docs/your_own_captures.md)[/]")  # fmt: skip
        if camera is not None:
            camera_check = intrinsics_check(camera)
            out[r.name]["camera"] = camera_check.to_record()
            warning = camera_check.warning(f"NeRF {r.name}")
            if warning is not None:
                console.print(f"[yellow]warning: {warning}. The run was trained on that camera: {SQUARE_PIXEL_ADVICE} "
                              "before training (docs/your_own_captures.md)[/]")  # fmt: skip
    return out or None


def _dataset_fold_check(dataset: Path | None) -> FoldCheck | None:
    """The file-order fold check of every frame of the transforms file the run was given (``dataset``), as
    ``ns-nerfuser-check-capture`` checks it; None where the renderer names no such file. Not the training cameras
    alone: nerfstudio holds out every tenth frame or so for evaluation, and the gaps can make an unordered capture's
    file order look like a rig's sequences (measured on street-8's larger side: a fold reported at lag 10)."""
    if dataset is None:
        return None
    try:
        return check_dataset(dataset)
    except (ValueError, OSError):
        return None


def _match_check(dataset: Path | None) -> MatchCheck | None:
    """The match check (:mod:`nerfuser_ns.match_check`) of the views the run trained on, where the renderer names its
    dataset (``dataset``) and the dataset keeps COLMAP's files; None otherwise (the check is a warning, never a reason
    to stop)."""
    if dataset is None:
        return None
    try:
        check = check_dataset_matches(dataset)
    except (ValueError, OSError):
        return None
    return check if check.checked else None


def twin_fallback(choice: SamplingChoice) -> SamplingChoice:
    """The choice after the twin check refused an SfM link: known geometry on the same pose source (its renders, with
    depth, are already made)."""
    return SamplingChoice(replace(choice.config, mode="known-geometry"),
                          f"the twin check refused the SfM's link: known geometry (ours) on the same renders; "
                          f"{choice.reason.split('; ', 1)[-1]}")  # fmt: skip


def _gist(reason: str) -> str:
    """A failure's finding without its advice: the text before the first ``; `` outside parentheses."""
    depth = 0
    for i, ch in enumerate(reason):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and reason.startswith("; ", i):
            return reason[:i]
    return reason


def every_choice_failed(
    attempts: Sequence[dict], work_dir: Path | str, capture_checks: dict | None = None, num_runs: int | None = None
) -> str:
    """The one-line error when every pose source of the automatic choice failed: what each found, then the causes
    left (runs of different places, or a capture whose COLMAP poses are inconsistent, which no registration mends),
    naming the runs whose capture checks (:func:`check_captures`) found a fold; where the checks vouch for all
    ``num_runs`` runs' poses, the causes without a fold."""
    found = "; ".join(f"{a['source']} ({a['mode']}): {_gist(a['error'])}" for a in attempts)
    checks = capture_checks or {}
    folded = [name for name, c in checks.items() if capture_folded(c)]
    if folded:
        cause = (f"The capture check found {', '.join(folded)} trained on folded COLMAP poses (warned above), which no "
                 "registration mends: pose that capture again, check it with ns-nerfuser-check-capture and train again")
    elif num_runs is not None and len(checks) == num_runs and all(_vouched(c) for c in checks.values()):
        cause = ("The capture checks found every run's COLMAP poses consistent (each explains all its matches), so a "
                 "fold is not the cause: either the runs show too little of the same place, or a check refused a right "
                 "link (each reason above says how to loosen its check; judge a link kept that way by its blend)")
    else:
        cause = ("Either the runs do not show the same place, or a capture's COLMAP poses are inconsistent (repeated "
                 "structure can fold a reconstruction, and a run trained on it cannot be registered): check each "
                 "dataset with ns-nerfuser-check-capture")
    return (f"no pose source registered the runs, {len(attempts)} tried: {found}. {cause}; see "
            f"docs/your_own_captures.md; the renders stay in {work_dir} for the next try")  # fmt: skip


def _vouched(checks: dict) -> bool:
    """Whether one run's capture checks vouch for its poses: matched exhaustively, every match explained by them, no
    fold in file order."""
    matches = checks.get("matches") or {}
    compared, possible = matches.get("compared_pairs"), matches.get("possible_pairs")
    return bool(matches.get("checked")) and not capture_folded(checks) and compared is not None and compared == possible


def _choice_list(choices: Sequence[SamplingChoice]) -> str:
    """``training (sfm), both (sfm), ...``: each choice's pose source and mode."""
    return ", ".join(f"{c.config.sampling.source} ({c.config.mode})" for c in choices)


def register(
    renderers: Sequence[Renderer],
    config: RegistrationConfig | None,
    work_dir: Path | str,
    console: Console = CONSOLE,
) -> RegistrationResult:
    """Register N >= 2 renderers; returns the typed result (``.to_record()`` is what :func:`write_registration`
    stores). ``config`` None: the defaults. ``work_dir`` holds the renders and SfM files (reused by later calls with the
    same inputs).

    With ``sampling.source="auto"`` (the default) the pose sources of :func:`resolve_sampling` are tried in order until
    one registers; each choice and each fallback is printed. Raises :class:`RegistrationError` (one line, naming the
    NeRF) when the result cannot be trusted.
    """
    config = config or RegistrationConfig()
    if len(renderers) < 2:
        raise RegistrationError(f"registration needs at least 2 NeRFs, got {len(renderers)}")
    choices = resolve_sampling(renderers, config)  # a list: a twin refusal changes what comes next
    capture_checks = check_captures(renderers, console)
    for choice in choices:
        validate_settings(choice.config)
    if len(choices) > 1:  # a refusal then is not the end: say so before the first one can be read that way
        console.print(f"automatic pose sampling: tries {_choice_list(choices)} in turn and keeps the first that "
                      "registers")  # fmt: skip
    tried = []
    n = -1
    while n + 1 < len(choices):
        n += 1
        choice = choices[n]
        sc = choice.config.sampling
        mode = "" if choice.config.mode == config.mode else f", mode [bold]{choice.config.mode}[/]"
        console.print(f"pose sampling: [bold]{sc.source}[/]{mode} ({choice.reason}), renders {sc.width}x{sc.height} "
                      f"at {sc.fov_deg:.1f} deg")  # fmt: skip
        start = time.perf_counter()
        record_choice = {"requested": config.sampling.source, "source": sc.source, "mode": choice.config.mode,
                         "reason": choice.reason, "tried_before": tried}  # fmt: skip
        try:
            result = register_once(renderers, choice.config, work_dir, console)
        except RegistrationError as e:
            reason = str(e).splitlines()[0]
            if n + 1 == len(choices):
                if isinstance(e, RegistrationFailed):  # the rejected record says what was tried before it
                    e.result.sampling_choice = record_choice
                if not tried:
                    raise
                summary = every_choice_failed([*tried, {"source": sc.source, "mode": choice.config.mode,
                                                        "error": reason}], work_dir, capture_checks,
                                              len(renderers))  # fmt: skip
                if isinstance(e, RegistrationFailed):
                    raise type(e)(summary, e.result) from e
                raise RegistrationError(summary) from e
            seconds = round(time.perf_counter() - start, 1)  # its renders and SfM, which the record keeps no other way
            attempt = {"source": sc.source, "mode": choice.config.mode, "error": reason, "seconds": seconds}
            if isinstance(e, RegistrationFailed):  # a check refused a solution: keep it, to judge the check later
                attempt["refused_transforms"] = [np.asarray(nr.T_to_reference).tolist() for nr in e.result.nerfs]
            tried.append(attempt)
            console.print(f"[yellow]{sc.source} poses did not register ({choice.config.mode}, {seconds:.0f} s): "
                          f"{reason}[/]")  # fmt: skip
            if isinstance(e, TwinLinked):
                # every SfM over these NeRFs sees the same repeated structure: known geometry, on these renders first
                choices[n + 1 :] = [twin_fallback(choice), *(c for c in choices[n + 1 :] if c.config.mode != "sfm"
                                                             and c.config.sampling.source != sc.source)]  # fmt: skip
            console.print(f"trying next ({n + 2} of {len(choices)}): {_choice_list(choices[n + 1 : n + 2])}")
            continue
        result.sampling_choice = record_choice
        result.capture_checks = capture_checks
        if config.reference_colour and config.colour_views > 0:
            match_reference_colours(result, renderers[result.reference], config.colour_views, console)
        return result
    raise AssertionError("unreachable")  # pragma: no cover


def match_reference_colours(
    result: RegistrationResult, reference: Renderer, num_views: int, console: Console
) -> None:
    """Compose every NeRF's colour map with the reference NeRF's map to its own training images
    (:mod:`~nerfuser_ns.registration.reference_colour`), in place, and record it (or why there is none)."""
    with console.status(f"appearance: rendering the reference NeRF at {num_views} of its training cameras"):
        rc = reference_colour(reference, num_views)
    if rc.colour_map is None:
        console.print(f"appearance: the colour maps stay relative to the reference NeRF ({rc.skipped})")
    else:
        gains = np.round(np.diag(rc.colour_map[:, :3]), 3).tolist()
        console.print(f"appearance: the reference NeRF's colours mapped to its training images (linear gains {gains}, "
                      f"{rc.views} views)")  # fmt: skip
        maps = compose_with_reference([n.colour_to_reference for n in result.nerfs], rc.colour_map)
        for n, m in zip(result.nerfs, maps, strict=True):
            n.colour_to_reference = m
    result.reference_colour = rc.to_record()


def register_once(
    renderers: Sequence[Renderer],
    config: RegistrationConfig,
    work_dir: Path | str,
    console: Console,
) -> RegistrationResult:
    """One registration with concrete pose-sampling settings (see :func:`register`); returns the result.

    Raises :class:`RegistrationFailed` (with the result) when the self-check rejects the solution.
    """
    if config.mode == "known-geometry":
        return register_known_geometry(renderers, config, work_dir, console)
    if config.mode == "graph":
        return register_graph(renderers, config, work_dir, console)
    work_dir = Path(work_dir)
    ref, min_views, intr = check_inputs(renderers, config)
    timings: dict[str, float] = {}

    # 1. Render (or reuse the renders of a previous run). With depth where every renderer gives it (a by-product of
    # the render): known geometry, the automatic choice's last step, then lifts these views instead of rendering them
    # again (measured on a drive pair: 1131 s of its 1320 s were those renders).
    t0 = time.perf_counter()
    depth = all(gives_depth(r) for r in renderers)
    views = [render_views_cached(r, config.sampling, work_dir / "renders", console, depth=depth) for r in renderers]
    timings["render"] = time.perf_counter() - t0
    check_kept_views(views, min_views, config.sampling)

    # 2. One SfM over the union (reused SfM steps take no time in this run).
    sfm = run_sfm(views, intr, config.sfm, work_dir, console)
    for step in ("features", "matching", "mapping"):
        timings[step] = 0.0 if sfm.reused else sfm.timings.get(step, 0.0)
    check_registered_views(sfm, views, min_views, config.sampling.source)

    # 3. Per NeRF: its SIM(3) into the SfM frame C, then into the reference frame; 4. refined.
    t0 = time.perf_counter()
    estimates = estimate_transforms(views, sfm, config)
    T_to_C = np.stack([e.estimate.T for e in estimates])
    T_to_ref = sim3.to_reference_frame(T_to_C, ref)
    refinement = None
    if config.refine:
        with console.status("refining the transforms (rigid-set bundle adjustment)"):
            T_to_ref, refinement = refine_transforms(views, sfm, T_to_C, ref, intr, config.refine_loss_scale_px)
        T_to_C = T_to_C[ref] @ T_to_ref
    timings["solve"] = time.perf_counter() - t0
    overlap = covisibility(views, sfm)  # between NeRFs: 3D points seen by both
    tree = spanning_pairs(overlap)  # the pairs the direct alignment aligns and the self-check checks
    order = best_views(views, sfm, tree)
    # 5a. The checks that need no renders: each NeRF's SfM cameras, then the other SfM models, against the solution.
    # Before the direct alignment and the self-check, whose renders a link they refuse would waste (the alignment's
    # changes stay far inside their 5-degree rule; the cameras are checked again against the final transform).
    early = camera_failure_of(views, estimates, T_to_C, T_to_ref, [r.name for r in renderers], config)
    models, contests = None, None
    if config.model_check and early is None:
        t0 = time.perf_counter()
        models, contests = contest_models(renderers, views, sfm, T_to_ref, intr, config, order, console)
        timings["model_check"] = time.perf_counter() - t0
    twin = None
    if config.twin_check and depth and early is None and models is None:  # 5a'. a wrong copy of repeated structure?
        t0 = time.perf_counter()
        twin = twin_check(renderers, views, T_to_ref, tree, intr, config, console)
        timings["twin_check"] = time.perf_counter() - t0
        if twin.warning is not None:
            console.print(f"[yellow]{twin.warning}[/]")
    refused = early or models or (twin.refusal if twin is not None else None)
    colocated = None
    if config.colocated.enabled and config.colocated.sfm and refused is None and depth:  # 4c. re-render refinement
        t0 = time.perf_counter()
        T_to_ref, colocated = refine_colocated(renderers, views, T_to_ref, tree, ref, intr, config.colocated, console)
        T_to_C = T_to_C[ref] @ T_to_ref
        timings["colocated"] = time.perf_counter() - t0
    direct = None
    if config.direct.enabled and refused is None:  # 4b. direct alignment of the tree's pairs
        t0 = time.perf_counter()
        T_to_ref, direct = align_direct(renderers, views, T_to_ref, tree, ref, intr, config.direct, order, console)
        T_to_C = T_to_C[ref] @ T_to_ref
        timings["direct"] = time.perf_counter() - t0

    # 5b. The cross-render self-check (not rendered when the cameras or the models already refuse the solution).
    checked_pairs = tree if config.self_check_views > 0 and refused is None else []
    t0 = time.perf_counter()
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config, order)
    timings["self_check"] = time.perf_counter() - t0

    # 6. The record; fail clearly when the self-check says the SfM merged the wrong things.
    result = build_result(
        renderers=renderers, views=views, sfm=sfm, estimates=estimates, T_to_ref=T_to_ref, T_to_C=T_to_C,
        refinement=refinement, overlap=overlap, checks=checks, config=config, intrinsics=intr, timings=timings,
    )
    result.direct = direct
    result.colocated = colocated
    result.twin_check = None if twin is None else twin.summary
    result.model_check = None if not contests else {"contests": contests}
    failure = check_failure(result, checks, config, models or (twin.refusal if twin is not None else None))
    if failure is not None:
        raise (TwinLinked if twin is not None and failure == twin.refusal else RegistrationFailed)(failure, result)
    return result


def contest_models(
    renderers: Sequence[Renderer], views: Sequence[ViewSet], sfm: SfMResult, T_to_ref: np.ndarray, intr: Intrinsics,
    config: RegistrationConfig, order: dict[tuple[int, int], Sequence[int]], console: Console,
) -> tuple[str | None, list[dict]]:
    """The model check: each link of another SfM model that disagrees with the registration's
    (:func:`~nerfuser_ns.registration.self_check.model_disagreements`) cross-rendered beside it on the same views and
    judged by :func:`~nerfuser_ns.registration.self_check.model_contest`. Returns the refusal line of the first that
    refuses (or None) and what the record keeps of each contest. With the self-check off (no views to render) a
    disagreement refuses unscored, as the check did before it rendered."""
    names = [r.name for r in renderers]
    contests: list[dict] = []
    scoring = replace(config, colour_views=0)  # the scores alone
    registration_checks: dict[tuple[int, int], CrossRenderCheck] = {}  # per pair: models disagreeing alike share it
    for d in model_disagreements(views, sfm, T_to_ref, config):
        contest = {"model_views": d.num_views, "nerfs": [names[d.a], names[d.j]], "r_err_deg": json_float(d.r_err_deg),
                   "t_err_reference": json_float(d.t_ref), "s_err": json_float(d.s_err)}  # fmt: skip
        contests.append(contest)
        if config.self_check_views <= 0:
            contest["verdict"] = "refused (unscored: the self-check is off)"
            return model_failure_line(d, names, config), contests
        with console.status(f"model check: another SfM model links {names[d.j]} to {names[d.a]} otherwise; "
                            "cross-rendering its link beside the registration's"):  # fmt: skip
            if (d.a, d.j) not in registration_checks:
                (registration_checks[(d.a, d.j)],) = cross_render_check(renderers, views, T_to_ref, [(d.a, d.j)],
                                                                        intr, scoring, order)  # fmt: skip
            mine = registration_checks[(d.a, d.j)]
            (theirs,) = cross_render_check(renderers, views, d.T_to_ref, [(d.a, d.j)], intr, scoring, order)
        refuses = model_contest(mine, theirs, config)
        contest.update(registration_ncc=json_float(mine.score), model_ncc=json_float(theirs.score),
                       registration_depth=json_float(mine.depth_disagreement),
                       model_depth=json_float(theirs.depth_disagreement),
                       verdict="refused" if refuses else "kept the registration's link")  # fmt: skip
        if refuses:
            return model_failure_line(d, names, config, (mine.score, theirs.score)), contests
        why = pair_failure(theirs, config)
        why = (f"under its link the {_gist(why)}" if why is not None else
               f"its link cross-renders at NCC {theirs.score:.2f} against the registration's {mine.score:.2f}, more "
               f"than {config.known_geometry.ambiguity_margin} below")  # fmt: skip
        console.print(f"model check: another SfM model ({d.num_views} views) links {names[d.j]} to {names[d.a]} "
                      f"{d.r_err_deg:.1f} deg away, but {why}: the registration's link kept")
    return None, contests


def check_failure(
    result: RegistrationResult, checks: Sequence[CrossRenderCheck], config: RegistrationConfig,
    models: str | None = None,
) -> str | None:
    """Why the solution cannot be trusted, in one line (cameras that contradict their transform, other SfM models
    that link the NeRFs otherwise (``models``, :func:`contest_models`'s line), then a failed cross-render self-check),
    or None."""
    cameras = None
    if config.camera_check:
        cameras = camera_failure([n.name for n in result.nerfs], [n.scale_to_reference for n in result.nerfs],
                                 [n.residuals.rotation_deg_median for n in result.nerfs],
                                 [n.residuals.centre_median for n in result.nerfs], config)  # fmt: skip
    return cameras or models or failure_message(checks, [n.name for n in result.nerfs], config)


def camera_failure_of(
    views: Sequence[ViewSet], estimates: Sequence[NerfEstimate], T_to_C: np.ndarray, T_to_ref: np.ndarray,
    names: Sequence[str], config: RegistrationConfig,
) -> str | None:
    """:func:`camera_failure` of the SfM cameras against transforms not yet in a result (None when the check is off)."""
    if not config.camera_check:
        return None
    residuals = camera_residuals(views, estimates, T_to_C)
    # the same cameras against the estimator's own transforms: whether they fit any one SIM(3) at all
    own = camera_residuals(views, estimates, np.stack([e.estimate.T for e in estimates]))
    fitted = [(json_float(np.median(rot)), json_float(np.median(cen))) for rot, cen in own]
    fitted = [None if None in f else f for f in fitted]
    scales = [float(sim3.decompose_sim3(T)[2]) for T in T_to_ref]
    return camera_failure(names, scales, [json_float(np.median(rot)) for rot, _ in residuals],
                          [json_float(np.median(cen)) for _, cen in residuals], config, fitted)  # fmt: skip


MIN_DEPTH_SIGMA = 1e-4
"""Floor of the relative depth noise the known-geometry refinement assumes (exact depth would weigh infinitely)."""


def register_known_geometry(
    renderers: Sequence[Renderer], config: RegistrationConfig, work_dir: Path | str, console: Console
) -> RegistrationResult:
    """One registration on known geometry (mode ``known-geometry``, ours); returns the result.

    Raises :class:`RegistrationError` (one line) when a NeRF has too few reliable keypoints, a NeRF matches no other,
    or two hypotheses are equally good; :class:`RegistrationFailed` (with the result) when the self-check rejects the
    solution.
    """
    work_dir = Path(work_dir)
    ref, min_views, intr = check_inputs(renderers, config)
    check_depth(renderers)
    kg = config.known_geometry
    names = [r.name for r in renderers]
    k = len(renderers)
    timings: dict[str, float] = {}
    views, feats = render_and_lift(renderers, config, work_dir, console, intr, min_views, timings)

    t0 = time.perf_counter()
    with console.status("known geometry: matching keypoints across NeRFs"):
        matches = matches_per_pair(feats, views, config)
    timings["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    hypotheses = {pair: pair_hypotheses(renderers, views, feats, m, intr, config, console)
                  for pair, m in matches.items()}  # fmt: skip
    timings["hypotheses"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    choice = {pair: choose_hypothesis(hyps, (names[pair[0]], names[pair[1]]), config)
              for pair, hyps in hypotheses.items() if hyps}  # fmt: skip
    chosen = {pair: hypotheses[pair][n] for pair, n in choice.items()}
    overlap = np.zeros((k, k), dtype=int)
    for (a, b), h in chosen.items():
        overlap[a, b] = overlap[b, a] = len(h.inliers)
    tree = spanning_pairs(overlap)
    for a, b in tree:
        if overlap[a, b] == 0:
            best = max((len(h.inliers) for p, hs in hypotheses.items() if b in p for h in hs), default=0)
            raise RegistrationError(
                f"{names[b]}: no SIM(3) to the other NeRFs has {kg.min_inliers} inlier 3D matches (best {best}); "
                f"the NeRFs may not overlap: {SUGGESTION}"
            )
    T_initial = chain_from_reference(chosen, tree, ref, k)
    # pairs off the tree join the solve only when they agree with the tree (a wrong link would pull it apart)
    links, linked, dropped = [], [], []
    for (a, b), h in chosen.items():
        implied = sim3.relative_sim3(T_initial[a], T_initial[b])  # b -> a
        err = sim3.sim3_errors(h.T, implied)
        if (a, b) not in tree and (err.r_err_deg > 5.0 or err.s_err > 0.1):
            dropped.append([names[a], names[b]])
            continue
        ia, ib = matches[(a, b)].ia[h.inliers], matches[(a, b)].ib[h.inliers]
        s_a, s_b = (float(sim3.decompose_sim3(T_initial[n])[2]) for n in (a, b))
        sigma = 0.5 * (s_a * feats[a].distance[ia] + s_b * feats[b].distance[ib])
        links.append((a, b, feats[a].points[ia], feats[b].points[ib], sigma))
        linked.append((a, b, ia, ib))
    T_to_ref, solve = joint_solve(T_initial, ref, links, kg.loss_scale)
    refinement = None
    if config.refine and solve["used"]:
        # the depth's noise, as the joint solve's residuals measure it, weighs it against the reprojections
        depth_sigma = max(solve["median_relative_after"], MIN_DEPTH_SIGMA)
        with console.status("refining the transforms (rigid-set bundle adjustment on the matches)"):
            T_to_ref, refinement = refine_on_matches(views, feats, linked, T_to_ref, ref, intr,
                                                     config.refine_loss_scale_px, depth_sigma)  # fmt: skip
    timings["solve"] = time.perf_counter() - t0
    colocated = None
    if config.colocated.enabled:  # re-render refinement of the tree's pairs
        t0 = time.perf_counter()
        T_to_ref, colocated = refine_colocated(renderers, views, T_to_ref, tree, ref, intr, config.colocated, console)
        timings["colocated"] = time.perf_counter() - t0

    checked_pairs = tree if config.self_check_views > 0 else []
    t0 = time.perf_counter()
    with console.status("self-check: cross-rendering NeRF pairs"):
        checks = cross_render_check(renderers, views, T_to_ref, checked_pairs, intr, config,
                                    check_views(feats, views, matches, chosen, checked_pairs))  # fmt: skip
    timings["self_check"] = time.perf_counter() - t0
    matched = views_matched(feats, matches, chosen, k)
    summary = {
        "keypoints": {names[i]: f.counts for i, f in enumerate(feats)},
        "pairs": [{"names": [names[a], names[b]], **pair_summary(feats, m, hypotheses[(a, b)], choice.get((a, b)),
                                                                  config)}
                  for (a, b), m in matches.items()],
        "tree": [[names[a], names[b]] for a, b in tree],
        "dropped_pairs": dropped,
        "joint_solve": solve,
    }  # fmt: skip
    result = build_known_geometry_result(
        renderers=renderers, views=views, T_to_ref=T_to_ref, T_initial=T_initial, views_matched=matched,
        overlap=overlap, checks=checks, config=config, timings=timings, known_geometry=summary,
        refinement=refinement,
    )
    result.colocated = colocated
    failure = check_failure(result, checks, config)
    if failure is not None:
        raise RegistrationFailed(failure, result)
    return result


def register_runs(
    config_paths: Sequence[Path | str],
    output: Path | str,
    config: RegistrationConfig | None = None,
    work_dir: Path | str | None = None,
    names: Sequence[str] | None = None,
    device: str | None = None,
    console: Console = CONSOLE,
    data_overrides: Sequence[Path | None] | None = None,
) -> RegistrationResult:
    """Register trained nerfstudio runs from their config.yml files and write the registration file at ``output``.

    ``work_dir`` defaults to ``<output>_work`` (renders and SfM files, reused by later calls). ``data_overrides[i]``
    is run i's dataset folder where its config's path no longer holds it (training poses are read from it). Raises
    :class:`RegistrationError` or ``runs.RunLoadError`` (one line) on bad input; nothing is written then. ``device``
    defaults to cuda when torch sees a GPU, else cpu.
    """
    output = Path(output)
    device = device or default_device()
    if names is not None and len(names) != len(config_paths):
        raise RegistrationError(f"{len(names)} names for {len(config_paths)} runs")
    if data_overrides is not None and len(data_overrides) != len(config_paths):
        raise RegistrationError(f"{len(data_overrides)} dataset folders for {len(config_paths)} runs")
    labels = list(names) if names is not None else run_names(list(config_paths))
    renderers = [
        NerfstudioRenderer(
            c, device=device, name=labels[i],
            data_override=None if data_overrides is None else data_overrides[i],
        )
        for i, c in enumerate(config_paths)
    ]  # fmt: skip
    work_dir = Path(work_dir) if work_dir is not None else work_dir_for(output)
    result = register(renderers, config, work_dir, console=console)
    write_registration(result, output)
    return result
