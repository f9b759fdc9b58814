"""NeRF registration from re-rendering (NeRFuser, ICCV 2023, Sec. 3.2), for N >= 2 NeRFs.

Pipeline, one module per step: sample camera poses in each NeRF's own frame (the paper's hemisphere, the run's
training poses, or both) and render them, cached in a work folder keyed by the inputs (:mod:`.render_cache`) -> one
SfM over the union of the renders with pycolmap (SIFT, one shared PINHOLE camera with the exactly known intrinsics,
kept fixed; :mod:`.sfm`) -> per NeRF, the SIM(3) NeRF -> SfM frame from the same cameras known in both frames
(:mod:`.estimate`, maths in :mod:`nerfuser_ns.sim3`) -> express everything in a reference NeRF's frame -> refine the
SIM(3)s by bundle adjustment over each NeRF's rigid camera set (:mod:`.refine`, maths in :mod:`nerfuser_ns.bundle`)
-> self-check by cross-rendering (SfM can merge unrelated content into one confident, wrong model; :mod:`.self_check`)
-> one JSON registration file, assembled (:mod:`.assemble`) and written atomically (:mod:`.record`). :mod:`.pipeline`
composes them; :mod:`.config` holds the settings and errors. Ours beside the paper's SfM: the known-geometry mode
(:mod:`.known_geometry`, :mod:`.retrieval`, steps shared in :mod:`.pairwise`, then :mod:`.colocated`) and, for
many NeRFs, the graph mode (:mod:`.graph`, :mod:`.pose_graph`, :mod:`.distributed`).

Anything a renderer of the :class:`nerfuser_ns.renderers.Renderer` protocol can render registers: trained nerfstudio
runs (:class:`~nerfuser_ns.renderers.NerfstudioRenderer`) or ground-truth scenes for tests.

Conventions: SIM(3) ``T_AB`` maps points of A into B (``p_B = T_AB p_A``); poses are camera-to-world, OpenGL camera
axes (nerfstudio). Bad inputs raise :class:`RegistrationError` with a one-line message naming the NeRF.
"""

from nerfuser_ns.registration.config import (
    CONSOLE,
    DEFAULT_RENDER_SIZE,
    FORMAT_VERSION,
    SUGGESTION,
    PoseSamplingConfig,
    RegistrationConfig,
    RegistrationError,
    RegistrationFailed,
    SfMConfig,
    TwinLinked,
    validate_settings,
)
from nerfuser_ns.registration.estimate import NerfEstimate, estimate_transform, estimate_transforms
from nerfuser_ns.registration.pipeline import (
    SamplingChoice,
    register,
    register_once,
    register_runs,
    resolve_sampling,
)
from nerfuser_ns.registration.record import (
    NerfEntry,
    RegisteredNerf,
    RegistrationFileError,
    RegistrationResult,
    capture_findings,
    iter_registered_nerfs,
    read_registration,
    read_render_poses,
    render_folders,
    work_dir_for,
    write_minimal_registration,
    write_registration,
)
from nerfuser_ns.registration.refine import refine_transforms
from nerfuser_ns.registration.render_cache import ViewSet, render_key, render_views_cached, sample_poses
from nerfuser_ns.registration.self_check import CrossRenderCheck, cross_render_check, ncc, spanning_pairs
from nerfuser_ns.registration.sfm import OPENGL_FROM_OPENCV, SfMResult, load_observations, run_sfm

__all__ = [
    "CONSOLE",
    "DEFAULT_RENDER_SIZE",
    "FORMAT_VERSION",
    "OPENGL_FROM_OPENCV",
    "SUGGESTION",
    "CrossRenderCheck",
    "NerfEntry",
    "NerfEstimate",
    "PoseSamplingConfig",
    "RegisteredNerf",
    "RegistrationConfig",
    "RegistrationError",
    "RegistrationFailed",
    "TwinLinked",
    "RegistrationFileError",
    "RegistrationResult",
    "SamplingChoice",
    "SfMConfig",
    "SfMResult",
    "ViewSet",
    "capture_findings",
    "cross_render_check",
    "estimate_transform",
    "estimate_transforms",
    "iter_registered_nerfs",
    "load_observations",
    "ncc",
    "read_registration",
    "read_render_poses",
    "refine_transforms",
    "register",
    "register_once",
    "register_runs",
    "render_folders",
    "render_key",
    "render_views_cached",
    "resolve_sampling",
    "run_sfm",
    "sample_poses",
    "spanning_pairs",
    "validate_settings",
    "work_dir_for",
    "write_minimal_registration",
    "write_registration",
]
