"""Registration step 2: one SfM over the union of every NeRF's renders (pycolmap, CPU).

SIFT features, exhaustive matching up to :attr:`SfMConfig.exhaustive_max_images` images (pose-guided pairs above),
incremental mapping with one shared PINHOLE camera whose exactly known intrinsics stay fixed. Cached in
``<work_dir>/sfm/<key>`` (database, ``sparse/`` models, ``observations.npz``, ``result.json``).
"""

from __future__ import annotations

import json
import shutil
import time
import zipfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from jaxtyping import Float
from rich.console import Console

from nerfuser_ns import sim3
from nerfuser_ns.cameras import Intrinsics
from nerfuser_ns.files import atomic_path, write_text_atomic
from nerfuser_ns.registration.config import (
    CONSOLE,
    RegistrationError,
    SfMConfig,
    content_hash,
    json_matrix,
    suggestion,
)
from nerfuser_ns.registration.render_cache import ViewSet

OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z; its own inverse


@dataclass
class SfMResult:
    """What registration needs from the SfM run (JSON-cached beside its database)."""

    c2w: dict[str, list]
    """Per registered image of the largest model: camera-to-world in the SfM frame C, OpenGL axes."""
    model_counts: list[list[int]]
    """Per model (largest first): registered views per NeRF."""
    covisible: dict[str, list[int]]
    """Per registered image: number of its 3D points also observed by each NeRF's images."""
    num_points3D: int
    mean_reprojection_error: float
    num_images: int
    matching: str
    timings: dict[str, float] = field(default_factory=dict)
    reused: bool = False
    folder: str = ""
    """The SfM's work folder (database, ``sparse/`` models, ``observations.npz``)."""


def _cheap_pairs(views: Sequence[ViewSet], names: list[list[str]], cfg: SfMConfig) -> list[tuple[str, str]]:
    """Image pairs linear in the number of images: own-NeRF nearest views (by known pose) + a spread cross subset."""
    pairs = set()
    for i, vs in enumerate(views):
        idx = np.flatnonzero(vs.kept)
        c = vs.c2w[idx, :3, 3]
        d = vs.c2w[idx, :3, 2]  # viewing axis (back): close in position and direction = likely overlap
        dist = np.linalg.norm(c[:, None] - c[None], axis=-1) / max(np.linalg.norm(c - c.mean(0), axis=-1).mean(), 1e-9)
        dist = dist + (1 - d @ d.T)
        for a in range(len(idx)):
            for b in np.argsort(dist[a])[1 : cfg.own_neighbors + 1]:
                pairs.add(tuple(sorted((names[i][idx[a]], names[i][idx[b]]))))
        for j, vj in enumerate(views):
            if j == i:
                continue
            jdx = np.flatnonzero(vj.kept)
            sub = jdx[np.unique(np.round(np.linspace(0, len(jdx) - 1, min(cfg.cross_views, len(jdx)))).astype(int))]
            for a in idx:
                for b in sub:
                    pairs.add(tuple(sorted((names[i][a], names[j][b]))))
    return sorted(pairs)


def run_sfm(
    views: Sequence[ViewSet], intrinsics: Intrinsics, cfg: SfMConfig, work_dir: Path, console: Console = CONSOLE
) -> SfMResult:
    """SIFT + matching + incremental mapping over the kept views of all NeRFs, intrinsics known and fixed.

    Cached: a second call with the same renders and settings reads ``result.json`` back.
    """
    import pycolmap  # lazy: heavy

    renders_root = views[0].folder.parent
    names = [vs.image_names for vs in views]
    used = [n for vs, ns in zip(views, names, strict=True) for n, k in zip(ns, vs.kept, strict=True) if k]
    nerf_of = {n: i for i, ns in enumerate(names) for n in ns}
    key = content_hash({"images": used, "sfm": asdict(cfg), "intrinsics": asdict(intrinsics),
                        "colmap": pycolmap.__version__})  # fmt: skip
    folder = work_dir / "sfm" / key[:16]
    result_path = folder / "result.json"
    if result_path.is_file():
        try:
            return SfMResult(**{**json.loads(result_path.read_text()), "reused": True, "folder": str(folder)})
        except (TypeError, ValueError):
            pass
    if folder.exists():
        shutil.rmtree(folder)
    (folder / "sparse").mkdir(parents=True)
    db = folder / "database.db"
    timings = {}
    device = pycolmap.Device.cpu
    pycolmap.logging.minloglevel = 0 if cfg.verbose else 2  # glog: 0 INFO, 1 WARNING, 2 ERROR

    with console.status(f"SfM: extracting SIFT features from {len(used)} renders"):
        t0 = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        k = intrinsics
        reader.camera_params = f"{k.fx!r},{k.fy!r},{k.cx!r},{k.cy!r}"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = cfg.num_threads
        extraction.use_gpu = False
        extraction.sift.max_num_features = cfg.max_num_features
        pycolmap.extract_features(
            db, renders_root, image_names=used, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
            extraction_options=extraction, device=device,
        )
        timings["features"] = time.perf_counter() - t0

    matching_opts = pycolmap.FeatureMatchingOptions()
    matching_opts.num_threads = cfg.num_threads
    matching_opts.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed
    verification.min_num_inliers = cfg.min_num_inliers
    exhaustive = len(used) <= cfg.exhaustive_max_images
    with console.status(f"SfM: matching {len(used)} renders ({'exhaustive' if exhaustive else 'pose-guided pairs'})"):
        t0 = time.perf_counter()
        if exhaustive:
            pycolmap.match_exhaustive(db, matching_options=matching_opts, verification_options=verification,
                                      device=device)
        else:
            pair_file = folder / "pairs.txt"
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in _cheap_pairs(views, names, cfg)))
            pairing = pycolmap.ImportedPairingOptions()
            pairing.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(db, matching_options=matching_opts, pairing_options=pairing,
                                       verification_options=verification, device=device)
        timings["matching"] = time.perf_counter() - t0

    with console.status("SfM: incremental mapping (intrinsics fixed)"):
        t0 = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        # The renders' intrinsics are exact: never refine them.
        options.ba_refine_focal_length = False
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = False
        options.mapper.abs_pose_refine_extra_params = False
        options.min_model_size = cfg.min_model_size
        options.min_num_matches = cfg.min_num_matches
        options.mapper.abs_pose_min_num_inliers = cfg.abs_pose_min_num_inliers
        options.mapper.abs_pose_min_inlier_ratio = cfg.abs_pose_min_inlier_ratio
        options.num_threads = cfg.num_threads
        options.random_seed = cfg.seed
        models = pycolmap.incremental_mapping(db, renders_root, folder / "sparse", options)
        timings["mapping"] = time.perf_counter() - t0

    recons = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    model_counts = []
    for rec in recons:
        counts = [0] * len(views)
        for image_id in rec.reg_image_ids():
            counts[nerf_of[rec.image(image_id).name]] += 1
        model_counts.append(counts)
    c2w, covisible, num_points, reproj = {}, {}, 0, float("nan")
    if recons:
        rec = recons[0]
        id_to_nerf = {}
        for image_id in rec.reg_image_ids():
            image = rec.image(image_id)
            c2w[image.name] = json_matrix(_camera_to_world(image))
            id_to_nerf[image_id] = nerf_of[image.name]
            covisible[image.name] = [0] * len(views)
        # Per image, how many of its 3D points the other NeRFs' images see too (overlap, for the self-check).
        for point in rec.points3D.values():
            ids = [el.image_id for el in point.track.elements]
            nerfs = {id_to_nerf[i] for i in ids if i in id_to_nerf}
            if len(nerfs) < 2:
                continue
            for i in set(ids):
                if i in id_to_nerf:
                    row = covisible[rec.image(i).name]
                    for j in nerfs:
                        row[j] += 1
        num_points = rec.num_points3D()
        reproj = float(rec.compute_mean_reprojection_error())
    result = SfMResult(c2w, model_counts, covisible, num_points, reproj, len(used),
                       "exhaustive" if exhaustive else "pose-guided pairs", timings, folder=str(folder))
    if recons:
        _save_observations(recons[0], folder / "observations.npz")
    write_text_atomic(result_path, json.dumps(asdict(result)) + "\n")
    return result


def check_registered_views(
    sfm: SfMResult, views: Sequence[ViewSet], min_views: int, source: str = "hemisphere"
) -> None:
    """Every NeRF needs ``min_views`` views in the largest SfM model; the error says whether its views formed a
    separate model (no overlap found) or too few registered, and what to try after poses from ``source``."""
    names = [vs.name for vs in views]
    advice = suggestion(source)
    if not sfm.model_counts:
        raise RegistrationError(
            f"SfM reconstructed nothing from the renders of {', '.join(names)} (too few matches); {advice}"
        )
    largest = sfm.model_counts[0]
    for i in range(len(views)):
        if largest[i] >= min_views:
            continue
        elsewhere = [m for m in sfm.model_counts[1:] if m[i] >= min_views]
        if elsewhere:
            together = [names[j] for j in range(len(views)) if largest[j] >= min_views]
            raise RegistrationError(
                f"{names[i]}: its views form a separate SfM model from {', '.join(together) or 'the others'} "
                f"(no overlap found between the NeRFs); {advice}"
            )
        raise RegistrationError(
            f"{names[i]}: only {largest[i]} of {int(views[i].kept.sum())} views registered in the SfM model "
            f"(need {min_views}); {advice}"
        )


def _save_observations(rec, path: Path) -> None:
    """The feature tracks of an SfM model as flat arrays (what the rigid-set bundle adjustment needs)."""
    reg = list(rec.reg_image_ids())
    row = {image_id: n for n, image_id in enumerate(reg)}
    names = [rec.image(i).name for i in reg]
    xyz, cam, point, xy = [], [], [], []
    for p_idx, p in enumerate(rec.points3D.values()):
        xyz.append(p.xyz)
        for el in p.track.elements:
            cam.append(row[el.image_id])
            point.append(p_idx)
            xy.append(rec.image(el.image_id).points2D[el.point2D_idx].xy)
    with atomic_path(path) as tmp:
        np.savez_compressed(
            tmp, names=np.array(names), points=np.asarray(xyz, np.float64).reshape(-1, 3),
            obs_cam=np.asarray(cam, np.int32), obs_point=np.asarray(point, np.int32),
            obs_xy=np.asarray(xy, np.float64).reshape(-1, 2),
        )


def _camera_to_world(image) -> Float[np.ndarray, "4 4"]:
    """A registered pycolmap image's camera-to-world in its model's frame, OpenGL axes."""
    cam_from_world = sim3.to_homogeneous(np.asarray(image.cam_from_world().matrix(), dtype=np.float64))
    # COLMAP cameras use OpenCV axes (looking +z, y down); nerfstudio's are OpenGL: flip y and z.
    return sim3.invert_sim3(cam_from_world) @ OPENGL_FROM_OPENCV


def other_models(sfm: SfMResult) -> list[dict[str, np.ndarray]]:
    """Camera-to-world per registered image (each in its own model's frame, OpenGL axes) of every SfM model but the
    one the registration uses, largest first; read from the ``sparse/`` folder (empty when it holds no other)."""
    import pycolmap  # lazy: heavy

    sparse = Path(sfm.folder) / "sparse"
    folders = sorted((d for d in sparse.glob("*") if d.is_dir()), key=lambda d: (len(d.name), d.name))
    used, out = set(sfm.c2w), []
    for rec in sorted((pycolmap.Reconstruction(str(d)) for d in folders), key=lambda r: -r.num_reg_images()):
        poses = {rec.image(i).name: _camera_to_world(rec.image(i)) for i in rec.reg_image_ids()}
        if set(poses) != used:
            out.append(poses)
    return out


def load_observations(sfm: SfMResult) -> dict[str, np.ndarray]:
    """Feature tracks of the largest SfM model (SfM frame): ``names``, ``points``, ``obs_cam``, ``obs_point``,
    ``obs_xy``. Work folders written before these were stored get them from their ``sparse/`` models."""
    folder = Path(sfm.folder)
    path = folder / "observations.npz"
    if not path.is_file():
        import pycolmap  # lazy: heavy

        models = [pycolmap.Reconstruction(str(d)) for d in sorted((folder / "sparse").glob("*")) if d.is_dir()]
        if not models:
            raise RegistrationError(f"{folder}: no SfM model to refine on; delete the folder to rerun the SfM")
        _save_observations(max(models, key=lambda r: r.num_reg_images()), path)
    try:
        with np.load(path) as z:
            return {key: z[key] for key in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise RegistrationError(
            f"{path}: damaged SfM cache ({type(e).__name__}); delete {folder} and run again (the SfM is redone)"
        ) from None
