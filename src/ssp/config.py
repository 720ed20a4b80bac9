"""Configuration: one nested pydantic model, every constant of the method named and documented.

Units are SI (metres, kilograms, seconds, radians) unless a field name says otherwise.
Defaults come from ``../shared/DESIGN.md`` section 4 and the reference code's constants
(``notes/reference-impl.md``); fields marked *calibrate* are engine specific and are measured
for MuJoCo by the calibration script (docs/calibration.md, issue 3).

YAML round trip: :func:`load_config` / :func:`dump_config`; ``ssp dump-config`` prints the defaults.
"""

from __future__ import annotations

import difflib
import math
import reprlib
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ssp.errors import ConfigError, SSPError

#: The most simulation steps (``window / physics.timestep``) of one window of the search: 50
#: with the defaults, 150 with the reference code's windows.
MAX_WINDOW_STEPS = 2000
#: The most nodes a YAML file may expand to through its aliases (a config file has a few
#: hundred): more is refused, so that an alias bomb costs nothing.
MAX_YAML_NODES = 100_000
#: Values echoed in a configuration error are cut to this many characters.
MAX_ECHO = 80


class _Section(BaseModel):
    # allow_inf_nan=False: a non-finite number (YAML .inf, .nan) is rejected with its field path
    model_config = ConfigDict(
        extra="forbid", validate_assignment=True, frozen=False, allow_inf_nan=False
    )


class PhysicsConfig(_Section):
    """MuJoCo world settings (notes/engines.md section 8: stiff contacts are mandatory)."""

    timestep: float = Field(0.005, gt=0, le=0.05, description="Simulation step dt, s.")
    gravity: float = Field(9.81, gt=0, description="Gravity magnitude along -z, m/s^2.")
    integrator: Literal["implicitfast", "implicit", "euler", "rk4"] = Field(
        "implicitfast", description="MuJoCo integrator."
    )
    cone: Literal["elliptic", "pyramidal"] = Field(
        "elliptic", description="Friction cone; elliptic makes efc_force[0] the normal force."
    )
    solref_timeconst_steps: float = Field(
        2.0, gt=0, description="Contact solref time constant, in multiples of timestep (2 dt)."
    )
    solref_dampratio: float = Field(1.0, gt=0, description="Contact solref damping ratio.")
    solimp: tuple[float, float, float, float, float] = Field(
        (0.99, 0.999, 0.001, 0.5, 2.0),
        description="Contact solimp (dmin, dmax, width m, midpoint, power): stiff contacts.",
    )
    torsional_friction: float = Field(0.005, ge=0, description="Torsional friction coefficient.")
    rolling_friction: float = Field(0.0001, ge=0, description="Rolling friction coefficient.")
    table_friction: float = Field(1.0, ge=0, description="Sliding friction of the table plane.")
    solver_iterations: int = Field(
        100, ge=1, le=10_000, description="Constraint solver iterations."
    )
    solver_tolerance: float = Field(1e-8, gt=0, description="Constraint solver tolerance.")
    noslip_iterations: int = Field(
        0, ge=0, le=10_000, description="Noslip solver iterations (0 = off)."
    )
    sleep_disabled: bool = Field(
        True,
        description=(
            "Put disabled objects to sleep (MuJoCo's sleeping trees), so that a step skips "
            "their dynamics; False only restores their poses after every step. Both leave a "
            "disabled object where it is."
        ),
    )
    contact_margin: float | None = Field(
        None,
        ge=0,
        le=0.001,
        description=(
            "Contact margin, m: contacts engage this far before the surfaces touch, which "
            "cancels the rest penetration of stiff contacts and lets touching stacks engage at "
            "once. None = 0.08 g dt^2 (0.02 mm at dt = 5 ms, the order of the rest penetration "
            "in a stack with the default solref/solimp; it scales with dt^2)."
        ),
    )

    @property
    def solref(self) -> tuple[float, float]:
        """MuJoCo (timeconst s, dampratio) for contacts."""
        return (self.solref_timeconst_steps * self.timestep, self.solref_dampratio)


class DecompositionConfig(_Section):
    """Convex decomposition (CoACD out of process, cached; notes/engines.md section 3)."""

    threshold: float = Field(0.05, gt=0, le=1, description="CoACD concavity threshold.")
    max_convex_hull: int = Field(-1, description="CoACD hull cap (-1: no cap).")
    preprocess_mode: Literal["auto", "on", "off"] = Field(
        "off", description="CoACD manifold preprocessing; 'off' for watertight meshes."
    )
    resolution: int = Field(2000, ge=20, description="CoACD sampling resolution.")
    seed: int = Field(0, description="CoACD random seed (determinism).")
    timeout_s: float = Field(900.0, gt=0, description="Wall-clock cap per CoACD run, s.")
    memory_limit_gb: float = Field(8.0, gt=0, description="Address-space cap per CoACD run, GiB.")
    fallback_threshold: float = Field(
        0.1, gt=0, le=1, description="Coarser CoACD threshold tried when the first run fails."
    )
    fallback_max_convex_hull: int = Field(16, description="Hull cap of the coarser retry.")
    iou_samples: int = Field(
        100_000, ge=1000, description="Monte Carlo points for the hull-vs-mesh volume IoU."
    )
    mode: Literal["auto", "coacd", "convex-hull"] = Field(
        "auto",
        description=(
            "auto: one hull for a mesh convex within convex_tolerance, its shells for a mesh "
            "of convex shells, else CoACD; coacd: always CoACD; convex-hull: always the single "
            "convex hull."
        ),
    )
    convex_tolerance: float = Field(
        0.04,
        ge=0,
        lt=1,
        description=(
            "A mesh, shell or merged pair of parts counts as convex when its convex hull "
            "holds at most this fraction of empty volume; nearly convex neighbouring parts "
            "are merged up to it."
        ),
    )
    max_parts: int = Field(
        32, ge=1, description="Most convex parts of a model (cheapest merges beyond it)."
    )
    max_faces: int = Field(
        50_000, ge=100, description="Meshes with more faces are decimated before CoACD."
    )
    min_iou: float = Field(
        0.8,
        ge=0,
        le=1,
        description="Warn (log and DecompositionInfo.warnings) when the parts' IoU is lower.",
    )


class LibraryConfig(_Section):
    """Object models: units checks, defaults for missing properties, samples."""

    min_extent: float = Field(0.005, gt=0, description="Smallest plausible model extent, m.")
    max_extent: float = Field(5.0, gt=0, description="Largest plausible model extent, m.")
    default_density: float = Field(
        700.0, gt=0, description="Density when a model gives neither mass nor density, kg/m^3."
    )
    default_friction: float = Field(1.0, ge=0, description="Sliding friction when not given.")
    surface_spacing: float = Field(
        0.003, gt=0, description="Target spacing of surface samples, m (reference: 3 mm voxels)."
    )
    max_surface_points: int = Field(20_000, ge=10, description="Cap on surface samples.")
    interior_spacing: float = Field(
        0.004, gt=0, description="Grid spacing of interior samples (overlap volume), m."
    )
    max_interior_points: int = Field(4000, ge=10, description="Cap on interior samples.")
    sample_seed: int = Field(0, description="Seed of surface sampling (determinism).")
    max_mesh_faces: int = Field(
        300_000,
        ge=100,
        description=(
            "Meshes with more faces are decimated to this many when loaded (quadric "
            "decimation; bounds the memory of validation, samples and decomposition)."
        ),
    )
    max_hand_extent: float = Field(
        1.0,
        gt=0,
        description=(
            "A model larger than this (m) is loaded but logged as implausible for a "
            "hand-held object (check units/scale)."
        ),
    )
    max_hand_mass: float = Field(
        25.0, gt=0, description="A heavier model (kg) is loaded but logged as implausible."
    )
    cache_dir: Path | None = Field(
        None, description="Hull cache folder; default $SSP_CACHE_DIR or ~/.cache/ssp."
    )
    decomposition: DecompositionConfig = Field(default_factory=DecompositionConfig)

    @model_validator(mode="after")
    def _extents_ordered(self) -> LibraryConfig:
        if self.min_extent >= self.max_extent:
            raise ValueError("min_extent must be smaller than max_extent")
        return self


class ForcesConfig(_Section):
    """Data-guiding forces (paper Eq. 13 for f_pi, Eq. 14 for F and tau; DESIGN section 4)."""

    max_distance: float = Field(
        0.02, gt=0, description="d_t: correspondence cut-off of the point-pair kernel, m."
    )
    gravity_fraction: float = Field(
        2.0,
        ge=0,
        description=(
            "f: peak data force F_max = f m g (proportional to mass). DESIGN's default is "
            "0.5; the reference's block-scene launch used 2.0, which is also what converges "
            "within the search windows here (docs/parser.md)."
        ),
    )
    visible_samples_only: bool = Field(
        True,
        description=(
            "With a camera pose, only model samples facing the camera and not hidden behind "
            "another object pull (and count in the data fit); False: every sample, as in the "
            "paper."
        ),
    )
    final_icp: bool = Field(
        True,
        description=(
            "Before the output, pull each detected object toward its point-to-plane ICP pose "
            "on its segment (the reference code's cached-ICP force mode) and let physics "
            "settle it, then a window without forces."
        ),
    )
    icp_max_distance: float = Field(
        0.01, gt=0, description="Correspondence cut-off of that ICP, m."
    )
    friction_scale: float = Field(
        0.0,
        ge=0,
        le=1,
        description=(
            "Sliding friction is multiplied by this while the data forces act (a pull of "
            "f m g could not slide a resting object against friction mu m g >= f m g); full "
            "friction returns for the window without forces, where stability is judged."
        ),
    )


class StabilityConfig(_Section):
    """Stability term P_B = L(-s_B (a_t beta_t - a_B)) L(-s_B (a_R beta_R - a_B)) (Eq. 9)."""

    steepness: float = Field(
        73.0,
        gt=0,
        description="sigma_B (calibrated for MuJoCo, docs/calibration.md; reference 40).",
    )
    midpoint: float = Field(
        0.056, ge=0, description="alpha_B (calibrated, docs/calibration.md; reference 0.1)."
    )
    translation_weight: float = Field(1.0, ge=0, description="alpha_t.")
    rotation_weight: float = Field(1.0, ge=0, description="alpha_R.")


class CollisionConfig(_Section):
    """Collision term P_C = L(-s_c (e_C - a_c)), e_C = d/eps_d * v_c/v_t (Eq. 10)."""

    steepness: float = Field(
        19000.0, gt=0, description="sigma_c (calibrated for MuJoCo, docs/calibration.md)."
    )
    midpoint: float = Field(0.00016, ge=0, description="alpha_c (calibrated, docs/calibration.md).")
    min_depth: float = Field(
        0.0004,
        ge=0,
        description=(
            "Penetrations shallower than this (m) are taken as solver residue: no overlap "
            "volume is computed for them (the interior grid could not resolve them anyway)."
        ),
    )


class SupportConfig(_Section):
    """Support term P_S = L(s_s sum_i F_S,i + a_s) (Eq. 11)."""

    steepness: float = Field(0.5, ge=0, description="sigma_s.")
    offset: float = Field(0.5, description="alpha_s.")


class DataConfig(_Section):
    """Data fitness P_D = L(s_d (min(c / C_max, 1) - a_d)) (Eq. 12).

    The reference code's constants (s_d 10, a_d 0.36, C_max 0.5; the paper gives none)
    saturate: any pose that explains half of the model's samples scores P_D > 0.99, so the
    term cannot tell a pose 6 mm off from the right one, and the transition term then holds a
    moved object back (docs/parser.md).
    Ours put every c on the log-linear side of the logistic (a_d = C_max = 1): ``log P_D`` is
    then about ``s_d (c - 1)``, each explained sample adding ``s_d / M``.
    """

    steepness: float = Field(20.0, gt=0, description="sigma_d (reference 10).")
    midpoint: float = Field(1.0, description="alpha_d (reference 0.36).")
    c_max: float = Field(
        1.0, gt=0, le=1, description="C_max: fit fraction counted as full (reference 0.5)."
    )
    inlier_radius: float = Field(
        0.0037, gt=0, description="r_c: a surface sample is explained within this distance, m."
    )


class TransitionConfig(_Section):
    """Transition term P_T = exp(-|dt|^2/2 s_t^2) exp(-dtheta^2/2 s_r^2) (Eq. 6), with a floor."""

    sigma_translation: float = Field(0.01, gt=0, description="sigma_t, m.")
    sigma_rotation: float = Field(math.radians(18.0), gt=0, description="sigma_r, rad (18 deg).")
    floor: float = Field(
        -8.0,
        le=0,
        description=(
            "log P_T never falls below this: the transition is a mixture of the Gaussian and "
            "a small uniform part (e^floor), so an orientation the data keeps contradicting "
            "can be given up (a half turn costs -50 without it); -1e9: DESIGN's plain Gaussian."
        ),
    )


class TemporalConfig(_Section):
    """Transition modes (paper section IV-C)."""

    static_translation: float = Field(0.0075, gt=0, description="Static below this motion, m.")
    static_rotation: float = Field(
        math.radians(5.0), gt=0, description="Static below this rotation, rad (5 deg)."
    )
    moved_fit_drop: float = Field(
        0.5,
        ge=0,
        le=1,
        description=(
            "A known object whose estimate changed beyond the static thresholds moved in the "
            "world only if the data where it was changed: its previous pose is now seen "
            "empty, explains this much less of its visible surface than in the frame that "
            "set it, or its data lie temporal.moved_residual_rise farther from it; otherwise "
            "the estimate was corrected and the object is static (ssp.motion.moved_in_world)."
        ),
    )
    moved_fit_gain: float = Field(
        0.1,
        ge=0,
        le=1,
        description=(
            "A changed estimate of an object whose data at its previous pose changed is motion "
            "only when this frame's data prefer it: it explains this much more of the object's "
            "visible surface than the previous pose does, or the segment lies closer to it "
            "(ssp.motion.prefers_estimate)."
        ),
    )
    moved_residual_rise: float = Field(
        0.0005,
        ge=0,
        description=(
            "A changed estimate is motion when the object's segment lies this much farther "
            "from its previous pose than in the frame that set it (mean point-to-plane "
            "distance, the evidence's residual, m; ssp.motion.moved_in_world)."
        ),
    )
    static_fusion_frames: int = Field(
        4,
        ge=1,
        description=(
            "A static object whose data where it was are as they were is output at the "
            "running mean of its estimates since it came to rest, over at most this many "
            "frames (ssp.motion.fuse_static); 1: each frame's estimate as it is."
        ),
    )
    association_distance: float = Field(
        0.05, gt=0, description="Largest centre distance of a hypothesis to its object, m."
    )
    association_size_fraction: float = Field(
        0.8,
        gt=0,
        description=(
            "The association gate of a class is at most this fraction of its median extent "
            "(the centre distance of two such objects side by side), so they never merge."
        ),
    )
    visible_fit: float = Field(
        0.5,
        ge=0,
        le=1,
        description=(
            "An undetected object whose previous pose explains at least this fraction of its "
            "visible surface (ssp.verification) is still there (missed detection): it stays."
        ),
    )
    occluded_fraction: float = Field(
        0.4,
        ge=0,
        le=1,
        description=(
            "An undetected object is hidden (ephemeral) when at least this fraction of its "
            "camera-facing surface lies behind observed depth (reference: 40 %)."
        ),
    )
    seen_through_fraction: float = Field(
        0.3,
        ge=0,
        le=1,
        description=(
            "An object whose camera-facing surface is seen through (observed depth behind it) "
            "at least this much lies in space the camera sees empty: an undetected known one "
            "is removed unless it carries load, a new one is rejected (ssp.verification)."
        ),
    )
    retain_acceleration: float = Field(
        0.1,
        gt=0,
        description=(
            "An undetected object is support-retained when, without it, an object it carries "
            "would accelerate from rest by more than this fraction of g (or of its largest "
            "angular acceleration under gravity): it would fall."
        ),
    )
    replaced_overlap: float = Field(
        0.3,
        ge=0,
        le=1,
        description="An ephemeral object is removed when another object fills this fraction "
        "of its volume.",
    )
    merge_overlap: float = Field(
        0.3,
        ge=0,
        le=1,
        description=(
            "Hypothesis groups of one class whose best poses share this fraction of the "
            "volume are one object (two objects cannot share a volume); 1 disables merging."
        ),
    )
    claim_overlap: float = Field(
        0.1,
        ge=0,
        le=1,
        description=(
            "A new object's hypothesis without an instance segment that shares this fraction "
            "of its own or a known object's volume is about that object's data: a pose of it "
            "(same class), or a competitor for its volume (ssp.shared_volume); 1 disables."
        ),
    )
    depth_tolerance: float = Field(
        0.005, gt=0, description="Depth agreement for the visibility tests, m."
    )
    explained_fraction: float = Field(
        0.9,
        ge=0,
        le=1,
        description=(
            "A new object's hypotheses are a duplicate of an undetected object when that "
            "object's previous pose explains this fraction of the segment they came from "
            "(points within the inlier radius plus the sample spacing of its surface "
            "samples); the undetected object takes the segment. 1 disables the test."
        ),
    )


class VerificationConfig(_Section):
    """Hypothesis verification (``ssp.verification``; DESIGN section 6): an object the parser
    has not seen before is kept only if the data supports it."""

    min_fit: float = Field(
        0.3,
        ge=0,
        le=1,
        description=(
            "A new object must explain at least this fraction of its visible surface (the "
            "camera-facing samples the camera could see, with a segment point within the "
            "inlier radius)."
        ),
    )
    min_explained: float = Field(
        0.85,
        ge=0,
        le=1,
        description=(
            "... and account for at least this fraction of the points of its instance segment "
            "(with instance labels; a real object accounts for nearly all of its segment, "
            "stray mask pixels included, a cube proposed on a ball for much less)."
        ),
    )
    min_visible_samples: int = Field(
        10,
        ge=1,
        description="Fewer visible surface samples than this: nothing to verify an object by.",
    )
    fall_stability: float = Field(
        -5.0,
        le=0,
        description=(
            "An object whose stability term (log P_B) is below this would fall where it is: "
            "the scene says so in its warnings."
        ),
    )
    fallback_fit_drop: float = Field(
        0.25,
        gt=0,
        le=1,
        description=(
            "A detected object whose searched pose explains this much less of its visible "
            "surface than its best hypothesis is put back at that hypothesis, with a warning "
            "(the search moved it off its data)."
        ),
    )
    fallback_collision: float = Field(
        -1.0,
        le=0,
        description=(
            "... unless its collision term (log P_C) there is below this: data wins over "
            "physics only where it does not put one object into another."
        ),
    )
    fallback_below: float = Field(
        0.05,
        ge=0,
        le=1,
        description=(
            "... nor when more than this fraction of its own instance segment lies over 1 cm "
            "below it: the segment is one object reaching lower than the hypothesis' shape (a "
            "cube fitted to a can's top, seen from above), so nothing undetected holds it up "
            "(ssp.holders.reaches_below)."
        ),
    )
    stand_explained: float = Field(
        0.8,
        ge=0,
        le=1,
        description=(
            "A new object that would fall where the data puts it is kept only if it explains "
            "at least this fraction of its visible surface and accounts for as much of its "
            "instance segment (when it has one): then it is there, held by something "
            "undetected (a known object: its fit alone, ssp.verification.falls_unheld)."
        ),
    )
    stand_seen_through: float = Field(
        0.15,
        ge=0,
        le=1,
        description=(
            "... and, with its own instance segment, the camera sees through less than this "
            "fraction of its camera-facing "
            "surface there (half the seen-empty bar, temporal.seen_through_fraction): strong "
            "data confirms the object at both ends, its segment explained and its surface "
            "seen, not a shape that sticks out of what the camera saw (a cube fitted to a "
            "can's top, its corners over the table)."
        ),
    )


class SearchConfig(_Section):
    """Simulation windows and budgets of the search (Alg. 1, 3; DESIGN section 4).

    Stepping is quasi-static, so an object moves at most about ``a dt^2`` per step (0.25 mm
    under gravity at dt = 5 ms): a window of ``w`` seconds corrects errors up to about
    ``w / dt * 0.25 mm`` (docs/parser.md, "Quasi-static windows").
    """

    settle_with_forces: float = Field(
        0.15, ge=0, description="Per-hypothesis window with data forces, s (reference 0.45)."
    )
    settle_without_forces: float = Field(
        0.1, ge=0, description="Per-hypothesis window without forces, s (reference 0.3)."
    )
    initial_settle: float = Field(
        0.15, ge=0, description="Settle of the first guess before the support graph, s."
    )
    final_settle: float = Field(
        0.2, ge=0, description="Settle of the whole chosen scene, with forces, s."
    )
    rest_check_every: int = Field(
        0,
        ge=0,
        description=(
            "Steps between rest checks in a window without forces: the window ends early once "
            "no object moved more than rest_translation / rest_rotation per step (0: never; "
            "4 was not validated on all of Table I: on the realistic structures, seed 1001, "
            "it gave 16 gross object-frames instead of 15)."
        ),
    )
    rest_translation: float = Field(
        2e-6, gt=0, description="At rest below this motion per step, m (0.4 mm/s at 5 ms)."
    )
    rest_rotation: float = Field(
        2e-4, gt=0, description="At rest below this rotation per step, rad (0.04 rad/s)."
    )
    hypotheses_per_object: int = Field(5, ge=1, description="k: hypotheses kept per object.")
    same_start_translation: float = Field(
        1e-3,
        ge=0,
        description=(
            "A candidate within this (m) and same_start_rotation of one tested before it for "
            "the same object starts the same window and is not tested again (0: test all)."
        ),
    )
    same_start_rotation: float = Field(
        math.radians(1.0), ge=0, description="... and within this rotation, rad (1 deg)."
    )
    reach: float = Field(
        0.02,
        ge=0,
        description=(
            "Objects whose bounding box stays farther than this (m) from every candidate of "
            "the tested object are left out of its tests (cost independent of scene size)."
        ),
    )
    previous_candidates: bool = Field(
        True, description="Add the previous frame's pose of an object as a candidate (IV-C)."
    )
    unchanged_shortcut: bool = Field(
        True,
        description=(
            "Skip the search when nothing changed: no object appeared or vanished, every "
            "object's hypotheses (per-axis median) lie within the static translation of its "
            "previous pose, and that pose still fits the data (see unchanged_fit_ratio)."
        ),
    )
    skip_settled: bool = Field(
        True,
        description=(
            "An unchanged object (as for unchanged_shortcut) that no changed object comes "
            "within reach of keeps its previous pose without tests (ssp.static)."
        ),
    )
    processes: int = Field(
        1,
        ge=1,
        le=64,
        description=(
            "Processes testing an object's candidates at once (forked from the parser's "
            "process when a frame's search starts, Linux only; ssp.lanes); the results are "
            "identical for any number. 2 on a 2-core machine."
        ),
    )
    retest_static: bool = Field(
        True,
        description=(
            "Test every hypothesis of an unchanged object near a change (False: only its "
            "first-guess and previous poses: faster changed frames, but on the paper's "
            "structures 12 gross object-frames instead of 4: a block a new one lands on may "
            "need another of its hypotheses; ssp.static)."
        ),
    )
    unchanged_fit_ratio: float = Field(
        0.7,
        gt=0,
        le=1,
        description=(
            "An object is unchanged when the data fit c at its previous pose is at least this "
            "fraction of the fit it had in the frame that set that pose (minus the tolerance)."
        ),
    )
    unchanged_fit_tolerance: float = Field(
        0.02, ge=0, le=1, description="Absolute slack of that test (barely visible objects)."
    )
    force_refresh_every: int = Field(
        4, ge=1, description="Steps between updates of the data-force wrenches."
    )
    correspondence_every: int = Field(
        2,
        ge=1,
        description="Wrench updates between nearest-neighbour queries of the data forces.",
    )
    force_samples: int = Field(
        300, ge=10, description="Model surface samples used for the data forces per object."
    )
    fit_samples: int = Field(
        1000, ge=10, description="Model surface samples used for the data fit per object."
    )


class PerceptionConfig(_Section):
    """The perception front end (``ssp.perception``): table, segments, pose hypotheses.

    The hypothesis generator plays ObjRecRANSAC's role (paper section IV-D): oriented point pairs
    of a segment are matched to model pairs with the same point-pair feature (Drost et al.
    2010), each match gives a pose, the poses are scored on a voxel occupancy grid of the
    segment, and the best distinct ones are refined by ICP. Lengths relative to a model are
    fractions of its diameter.
    """

    table_distance: float = Field(
        0.006, gt=0, description="RANSAC inlier distance of the table plane, m."
    )
    table_height: float = Field(
        0.004, ge=0, description="Points lower than this above the table are table, m."
    )
    cluster_tolerance: float = Field(
        0.006, gt=0, description="Euclidean clustering distance of segments, m."
    )
    min_segment_points: int = Field(30, ge=3, description="Smaller segments are ignored.")
    normal_neighbours: int = Field(16, ge=3, description="k of the PCA normals.")
    hypotheses_per_object: int = Field(5, ge=1, description="k: hypotheses per object found.")
    sampling: float = Field(
        0.05, gt=0, le=0.5, description="Voxel of the model and segment samples (x diameter)."
    )
    max_model_points: int = Field(
        450, ge=50, description="Cap of model samples in the pair table (coarser voxel)."
    )
    pair_samples: int = Field(600, ge=10, description="Scene point pairs drawn per model.")
    matches_per_pair: int = Field(6, ge=1, description="Model pairs tried per scene pair.")
    angle_step_deg: float = Field(12.0, gt=0, le=90, description="Feature angle bin, deg.")
    score_voxel: float = Field(
        0.004, gt=0, description="Occupancy grid voxel of the coarse pose scoring, m."
    )
    inlier_distance: float = Field(
        0.005, gt=0, description="A model sample within this of the segment is explained, m."
    )
    class_screen: float = Field(
        0.85,
        gt=0,
        le=1,
        description=(
            "Classes whose coarse score is below this fraction of the best class's are not "
            "refined (class screening)."
        ),
    )
    max_classes: int = Field(2, ge=1, description="Classes refined per object at most.")
    refine: int = Field(5, ge=1, description="Distinct candidates refined by ICP per object.")
    alternatives: int = Field(
        4,
        ge=0,
        description=(
            "Other orientations refined per object: the best candidate of each orientation "
            "turned by over alternative_deg from those refined. The ones that explain the "
            "segment nearly as well are kept among the k (a mostly hidden object's seen part "
            "often fits several orientations; the scene parser chooses)."
        ),
    )
    alternative_deg: float = Field(
        30.0, gt=0, le=180, description="Orientation difference of an alternative, deg."
    )
    alternative_coarse: float = Field(
        0.5,
        ge=0,
        le=1,
        description="An alternative's coarse score is at least this fraction of the best's.",
    )
    alternative_coverage: float = Field(
        0.03,
        ge=0,
        le=1,
        description=(
            "An alternative explains at least the best's fraction of the segment points minus this."
        ),
    )
    min_score: float = Field(
        0.3, ge=0, le=1, description="Objects whose best score is lower are not reported."
    )
    max_objects_per_segment: int = Field(
        12, ge=1, description="Objects explained one after another in a single segment."
    )
    processes: int = Field(
        1,
        ge=1,
        le=64,
        description=(
            "Processes estimating the hypotheses of a frame's segments at once (forked per "
            "frame, Linux only; ssp.lanes); the hypotheses are identical for any number."
        ),
    )
    reuse_unchanged: bool = Field(
        True,
        description=(
            "An instance segment unchanged since the frame its hypotheses were estimated on "
            "(the same camera; its points' count, centroid and spread alike) keeps them "
            "instead of being estimated again (ssp.perception.reuse)."
        ),
    )
    reuse_min_score: float = Field(
        0.7,
        ge=0,
        le=1,
        description=(
            "Only hypotheses this confident are kept for an unchanged segment (the best score "
            "of every object found in it); a less confident estimate is made again each frame, "
            "where another frame's noise may find the object."
        ),
    )
    reuse_min_coverage: float = Field(
        0.85,
        ge=0,
        le=1,
        description=(
            "... and only when each object's best hypothesis explains this fraction of the "
            "segment's points (verification's bar for a new object, min_explained)."
        ),
    )
    reuse_min_margin: float = Field(
        0.05,
        ge=0,
        le=1,
        description=(
            "... and only when no other orientation (alternative_deg apart) scored within this "
            "of the best: a view that allows another orientation nearly as well is estimated "
            "again each frame (the parser's tie margin)."
        ),
    )


class CorrectionConfig(_Section):
    """Depth correction before judging (``ssp.correction``): a hypothesis whose silhouette
    covers observed surface that lies at another depth is slid along its viewing ray to that
    depth, then aligned to it, before verification judges it. An RGB pose estimator's error is
    mostly there: on LM-O, MegaPose's is 14 mm along the ray (median; 75th percentile 35 mm)
    against 5 mm across it (``shared/data/lmo-megapose``)."""

    enabled: bool = Field(True, description="Correct hypotheses along their viewing ray.")
    max_shift: float = Field(
        0.12,
        gt=0,
        description=(
            "Largest correction along the ray, m (MegaPose on LM-O: 95 % of its along-ray "
            "errors of targets it got right in rotation are below about 10 cm)."
        ),
    )
    min_shift: float = Field(
        0.008,
        ge=0,
        description=(
            "Smaller corrections are left to the data forces (which reach "
            "``forces.max_distance``), m."
        ),
    )
    min_support: float = Field(
        0.3,
        gt=0,
        le=1,
        description=(
            "At the corrected depth at least this fraction of the hypothesis' silhouette "
            "samples (its facing samples whose ray meets the object's observed surface) must "
            "lie on the observed surface..."
        ),
    )
    gain: float = Field(
        2.0,
        ge=1,
        description="... and at least this many times as many as at the estimator's depth.",
    )
    min_samples: int = Field(
        10, ge=1, description="Fewer silhouette samples than this: nothing to correct by."
    )
    min_silhouette: float = Field(
        0.5,
        gt=0,
        le=1,
        description=(
            "With instance labels, at least this fraction of the facing samples' rays with data "
            "must meet one label (its own segment's): the silhouette fits one object; one that "
            "straddles a nearer object and its own is occluded, not misplaced in depth."
        ),
    )
    min_coverage: float = Field(
        0.7,
        gt=0,
        le=1,
        description=(
            "With instance labels, the corrected hypothesis' silhouette must cover at least "
            "this fraction of its segment's points: the silhouettes agree, only the depth was "
            "wrong (a hypothesis centimetres off across the ray, or of another shape, is not "
            "made to fit by sliding it)."
        ),
    )
    claim_support: float = Field(
        0.5,
        gt=0,
        le=1,
        description=(
            "A label that a hypothesis explains where it is (this fraction of its facing "
            "samples on the label's surface) is explained: no other hypothesis is slid onto "
            "it (ssp.correction.claimed_labels)."
        ),
    )
    min_fit: float = Field(
        0.6,
        ge=0,
        le=1,
        description=(
            "At the corrected pose at least this fraction of the facing samples that nothing "
            "in front hides must lie on the object's observed surface: the pose explains what "
            "the camera sees of it (a gross hypothesis slid onto a surface it does not match, "
            "across the ray or in orientation, leaves most of its visible samples off it)."
        ),
    )
    max_seen_through: float = Field(
        0.3,
        ge=0,
        le=1,
        description=(
            "At the corrected pose at most this fraction of the facing samples may be seen "
            "through (a wrong shape slid onto a surface sticks out into seen empty space; "
            "``temporal.seen_through_fraction`` would call it seen empty)."
        ),
    )
    align: bool = Field(
        True,
        description=(
            "Then align the slid model to the observed surface (point-to-plane ICP within "
            "``align_distance``), kept only when it explains more of the silhouette."
        ),
    )
    align_distance: float = Field(
        0.015, gt=0, description="The alignment's largest correspondence distance, m."
    )


class SSPConfig(_Section):
    """Every setting of ssp. Construct with defaults, from a dict, or from YAML."""

    physics: PhysicsConfig = Field(default_factory=PhysicsConfig)
    library: LibraryConfig = Field(default_factory=LibraryConfig)
    forces: ForcesConfig = Field(default_factory=ForcesConfig)
    stability: StabilityConfig = Field(default_factory=StabilityConfig)
    collision: CollisionConfig = Field(default_factory=CollisionConfig)
    support: SupportConfig = Field(default_factory=SupportConfig)
    data: DataConfig = Field(default_factory=DataConfig)
    transition: TransitionConfig = Field(default_factory=TransitionConfig)
    temporal: TemporalConfig = Field(default_factory=TemporalConfig)
    search: SearchConfig = Field(default_factory=SearchConfig)
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    correction: CorrectionConfig = Field(default_factory=CorrectionConfig)
    perception: PerceptionConfig = Field(default_factory=PerceptionConfig)
    seed: int = Field(0, description="Seed for everything random in ssp.")

    @model_validator(mode="after")
    def _reach_covers_the_window(self) -> SSPConfig:
        """``search.reach`` must cover what a candidate's window can move an object.

        Quasi-static steps move an object by at most about ``g dt^2`` each (0.25 mm at
        dt = 5 ms), so the window of a test (``search.settle_with_forces`` +
        ``search.settle_without_forces``: ``w`` seconds, ``w / dt`` steps) moves it up to about
        ``w / dt * g dt^2 = w g dt`` (:class:`SearchConfig`; docs/parser.md, "Quasi-static
        windows"): 12.3 mm with the defaults. The search sets aside the objects farther than
        ``reach`` from a tested object's candidates (and an unchanged object with no change
        within ``reach`` keeps its pose untested), so a smaller reach could leave out an object
        that the test moves into. Checked when a configuration is built or loaded
        (``SSPConfig(...)``, :meth:`from_dict`, :func:`load_config`); a field set in place
        afterwards is not checked again.
        """
        s, p = self.search, self.physics
        window = s.settle_with_forces + s.settle_without_forces
        bound = window * p.gravity * p.timestep
        if s.reach < bound:
            raise ValueError(
                f"search.reach = {s.reach:g} m is less than what a search window can move an "
                f"object: (search.settle_with_forces + search.settle_without_forces) * "
                f"physics.gravity * physics.timestep = ({s.settle_with_forces:g} + "
                f"{s.settle_without_forces:g}) s * {p.gravity:g} m/s^2 * {p.timestep:g} s = "
                f"{bound:.4g} m (docs/parser.md, 'Quasi-static windows'): set search.reach to "
                f"at least {bound:.4g} or shorten the windows"
            )
        return self

    @model_validator(mode="after")
    def _windows_have_bounded_steps(self) -> SSPConfig:
        """Every simulation window of the search is at most :data:`MAX_WINDOW_STEPS` steps of
        ``physics.timestep`` (50 with the defaults): a tiny timestep or a huge window would
        make a frame take unbounded time (``physics.timestep: 1e-7`` is 2.5 million steps per
        tested candidate)."""
        s, dt = self.search, self.physics.timestep
        windows = (
            ("search.settle_with_forces + search.settle_without_forces",
             s.settle_with_forces + s.settle_without_forces),
            ("search.initial_settle", s.initial_settle),
            ("search.final_settle", s.final_settle),
        )  # fmt: skip
        for name, seconds in windows:
            steps = seconds / dt
            if steps > MAX_WINDOW_STEPS:
                raise ValueError(
                    f"physics.timestep = {dt:g} s makes the window {name} = {seconds:g} s "
                    f"{steps:,.0f} simulation steps, more than {MAX_WINDOW_STEPS:,} (a frame "
                    f"would take unbounded time): set physics.timestep to at least "
                    f"{seconds / MAX_WINDOW_STEPS:.3g} s or shorten the window"
                )
        return self

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None, where: str = "configuration") -> SSPConfig:
        """Validate a (possibly partial) nested dict; missing fields keep their defaults.

        Raises:
            ConfigError: one line per problem, ``where: section.field: problem``, with the
                closest valid key for an unknown one (:func:`config_problems`).
        """
        try:
            return cls.model_validate(data or {})
        except ValidationError as exc:
            lines = config_problems(exc)
            head = f"{where}: " if len(lines) == 1 else f"{where}: {len(lines)} problems:\n  "
            raise ConfigError(head + "\n  ".join(lines)) from None

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON/YAML types only)."""
        return self.model_dump(mode="json")


# ------------------------------------------------------------------------------ messages
def _field_paths(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every dotted key of ``model`` (sections and their fields), e.g. ``physics.timestep``."""
    out = []
    for name, info in model.model_fields.items():
        key = prefix + name
        out.append(key)
        sub = info.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            out.extend(_field_paths(sub, key + "."))
    return out


def _section_at(loc: tuple) -> type[BaseModel] | None:
    """The config section class at ``loc`` (a tuple of field names), or None."""
    model: Any = SSPConfig
    for part in loc:
        info = model.model_fields.get(part) if isinstance(part, str) else None
        sub = info.annotation if info is not None else None
        if not (isinstance(sub, type) and issubclass(sub, BaseModel)):
            return None
        model = sub
    return model


def _suggest(loc: tuple) -> str:
    """`` (did you mean 'x'?)`` for an unknown key at ``loc``, or ``""``."""
    key = str(loc[-1])
    section = _section_at(loc[:-1])
    if section is not None:
        close = difflib.get_close_matches(key, list(section.model_fields), n=1, cutoff=0.6)
        if close:
            return f" (did you mean {'.'.join([*map(str, loc[:-1]), close[0]])!r}?)"
    paths = _field_paths(SSPConfig)
    by_leaf = {p: p.rsplit(".", 1)[-1] for p in paths}
    close = difflib.get_close_matches(key, list(set(by_leaf.values())), n=1, cutoff=0.75)
    if close:
        where = sorted(p for p, leaf in by_leaf.items() if leaf == close[0])
        return f" (did you mean {where[0]!r}?)"
    if section is not None:
        return f"; valid keys here: {', '.join(section.model_fields)}"
    return ""


def _loc(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def config_problems(exc: ValidationError) -> list[str]:
    """One readable line per problem of a configuration :class:`ValidationError`:
    ``section.field: what is wrong (got value)``; unknown keys get the closest valid key
    (difflib). Repeated lines (one per missing tuple item) are merged."""
    lines: list[str] = []
    for err in exc.errors():
        loc = tuple(err["loc"])
        kind = err["type"]
        got = err.get("input")
        if kind == "extra_forbidden":
            line = f"{_loc(loc)}: unknown setting{_suggest(loc)}"
        elif kind == "missing" and loc and isinstance(loc[-1], int):
            line = f"{_loc(loc[:-1])}: too few values, got {got!r}"
        else:
            msg = str(err["msg"]).removeprefix("Value error, ")
            shown = got if not isinstance(got, dict) else None
            line = f"{_loc(loc)}: {msg[:1].lower()}{msg[1:]}" + (
                f" (got {_echo(shown)})" if shown is not None else ""
            )
        if line not in lines:
            lines.append(line)
    return lines


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict = 3, 8, 8, 8
_REPR.maxstring = _REPR.maxother = MAX_ECHO


def _echo(value: Any) -> str:
    """``repr(value)``, cut to about :data:`MAX_ECHO` characters without building the whole
    repr (a value shared many times over by YAML aliases would take minutes)."""
    text = _REPR.repr(value)
    return text if len(text) <= MAX_ECHO else text[: MAX_ECHO - 3] + "..."


def _expanded_nodes(root: yaml.Node, limit: int) -> int:
    """The number of nodes of the YAML tree ``root`` once its aliases are expanded (a node
    shared ``n`` times counts ``n`` times), or ``limit + 1`` when it exceeds ``limit`` or an
    alias refers to a node that contains it (an infinite tree). Linear in the distinct nodes."""

    def children(node: yaml.Node) -> list[yaml.Node]:
        if isinstance(node, yaml.MappingNode):
            return [n for pair in node.value for n in pair]
        if isinstance(node, yaml.SequenceNode):
            return list(node.value)
        return []

    size: dict[int, int] = {}
    path: set[int] = set()  # the nodes being counted: an ancestor seen again is a cycle
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            size[key] = min(limit + 1, 1 + sum(size[id(c)] for c in children(node)))
            path.discard(key)
            continue
        if key in size:
            continue
        path.add(key)
        stack.append((node, True))
        for c in children(node):
            if id(c) in path:
                return limit + 1
            if id(c) not in size:
                stack.append((c, False))
    return size[id(root)]


def _safe_load(text: str, where: str, error: type[SSPError]) -> Any:
    """:func:`yaml.safe_load` of ``text``, refusing a document whose aliases expand it beyond
    :data:`MAX_YAML_NODES` nodes (before anything is built from it)."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        if _expanded_nodes(node, MAX_YAML_NODES) > MAX_YAML_NODES:
            raise error(
                f"{where}: YAML aliases (*name) expand it to more than {MAX_YAML_NODES:,} "
                "values, or refer to themselves: refused (an alias bomb?); write the values out"
            )
        return loader.construct_document(node)
    finally:
        loader.dispose()


def read_yaml(path: Path, error: type[SSPError], what: str = "file") -> Any:
    """Parsed YAML of ``path`` (None if empty); raises ``error`` if unreadable, not UTF-8 text,
    or invalid YAML."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise error(
            f"{path}: the {what} is not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
            f"offset {exc.start}): save it as UTF-8"
        ) from None
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc}") from exc
    try:
        return _safe_load(text, str(path), error)
    except RecursionError:
        raise error(f"{path}: not valid YAML: nested too deeply to read") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        what = " ".join(str(getattr(exc, "problem", None) or exc).split())
        raise error(f"{where}: not valid YAML: {what}") from exc


def load_config(path: str | Path) -> SSPConfig:
    """Read a YAML file (partial files allowed) into an :class:`SSPConfig`."""
    path = Path(path)
    data = read_yaml(path, ConfigError, "config file")
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    return SSPConfig.from_dict(data, str(path))


def dump_config(config: SSPConfig) -> str:
    """YAML text of ``config`` with a units header (:func:`load_config` reads it back; the
    command ``ssp dump-config --out FILE`` writes it)."""
    return "# ssp configuration. Units: metres, kilograms, seconds, radians.\n" + yaml.safe_dump(
        config.to_dict(), sort_keys=False
    )
