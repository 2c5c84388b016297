"""Planner parameters, validated. Units are in the field names; the paper's values where it has them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np

from pydantic import BaseModel, ConfigDict, Field, model_validator

from configs.loading import load_yaml_model as _load_yaml_model
from configs.poses import pose_from_xyz_rpy_deg


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


Lab3 = tuple[float, float, float]


class PaintColor(_Strict):
    """The yard's marking paint as commissioned (``cellctl calibrate paint``): its colour in CIELAB as a
    sample showed it, and the limits of the check that runs on every piece (planners.paint_color)."""

    name: str = Field("red", min_length=1, max_length=40, description="what the operator calls it")
    lab_mean: Lab3 = Field((45.2, 69.4, 55.6), description="L* a* b* (D65) of the paint, lit as in the sample")
    lab_cov: tuple[Lab3, Lab3, Lab3] = Field(((11.4, 11.3, 9.1), (11.3, 21.4, 14.0), (9.1, 14.0, 15.2)),
                                             description="its covariance: the sample's shading and texture")
    gate_d2: float = Field(16.3, gt=0, le=400, description="a colour farther than this (squared Mahalanobis) from "
                           "the fitted paint is not paint, whatever else it is (chi-square, 3 dof, 0.999)")
    min_delta_e: float = Field(15.0, ge=1, le=100, description="paint and metal closer than this (CIE76) on a piece: "
                               "refused, paint_not_separable")
    warn_delta_e: float = Field(25.0, ge=1, le=100, description="closer than this: done with a warning")
    max_share: float = Field(0.3, gt=0, le=1, description="paint covering more of the piece in the initial view "
                             "is the metal taken for paint: refused")
    max_band_m: float = Field(0.08, gt=0, le=1, description="paint wider than this is no sprayed line: refused")
    min_paint_points: int = Field(50, ge=1, description="fewer paint points in the initial view: no paint there")
    piece_above_m: float = Field(0.005, ge=0, le=0.5, description="points higher than this over the table (the "
                                 "grid's floor) are the piece the colours are fitted on")
    source: str = Field("default", max_length=200, description="where the model came from (a calibration's date)")

    @model_validator(mode="after")
    def _cov(self) -> "PaintColor":
        c = np.asarray(self.lab_cov, dtype=np.float64)
        if not np.allclose(c, c.T, atol=1e-6) or np.linalg.eigvalsh(c).min() <= 0:
            raise ValueError("lab_cov must be a symmetric positive-definite 3x3 matrix")
        if self.warn_delta_e < self.min_delta_e:
            raise ValueError(f"warn_delta_e ({self.warn_delta_e}) must be at least min_delta_e ({self.min_delta_e})")
        return self


class GridConfig(_Strict):
    """The probabilistic occupancy grid (log-odds per cell) over a bounded workspace."""

    lo_m: tuple[float, float, float] = (-0.2, -0.8, 0.0)
    hi_m: tuple[float, float, float] = (1.2, 0.8, 1.0)
    voxel_m: float = Field(0.01, ge=0.002, le=0.1)
    l_hit: float = Field(2.0, gt=0, le=5)
    l_miss: float = Field(-1.5, lt=0, ge=-5)
    l_min: float = Field(-2.0, lt=0, ge=-20)
    l_max: float = Field(3.5, gt=0, le=20)
    shadow_depth_m: float = Field(0.05, ge=0, le=0.5, description="depth behind each hit marked as shadow")
    integrate_stride_px: int = Field(2, ge=1, le=16)
    surface_voxel_m: float = Field(0.002, gt=0, le=0.02)  # de-duplication of C_total / D_total

    @model_validator(mode="after")
    def _bounds(self) -> "GridConfig":
        size = [h - lo for lo, h in zip(self.lo_m, self.hi_m)]
        if min(size) <= 0:
            raise ValueError(f"hi_m must exceed lo_m on every axis, got lo_m={self.lo_m} hi_m={self.hi_m}")
        cells = 1
        for s in size:
            cells *= int(round(s / self.voxel_m))
        if cells > 64_000_000:
            raise ValueError(f"grid would have {cells} cells (> 64M): enlarge voxel_m or shrink the workspace")
        return self


class NBVConfig(_Strict):
    """Parameters of the quality metric Q (eq. 4-8) and stop rule (eq. 9), shared by the NBV planners."""

    lam: float = Field(0.5, ge=0, lt=1, description="λ of eq. 4 (paper: 1/2)")
    alpha_phi: float = Field(5.0, gt=0, description="α_φ of eq. 7 (paper: 5), per phi_length_m squared")
    phi_length_m: float = Field(0.10, gt=0, le=1.0,
                                description="unit in which dist_F of eq. 7 is measured (the paper leaves it unstated)")
    delta_q: float = Field(0.0, description="δ_Q of eq. 9 on the normalized quality")
    min_gain: float = Field(0.82, ge=0, description="a target whose best raw gain (nats) is below this is given up: "
                            "with only unknown cells counting, 0.82 is three unknown cells' h(g) (0.27 nats each), "
                            "the growth a view must show to count (min_view_growth_voxels)")
    min_gain_fraction: float = Field(0.2, ge=0, lt=1,
                                     description="G-NBV: ... or below this share of the first step's best gain")
    joint_min_gain_fraction: float = Field(0.1, ge=0, lt=1, description="the same share with gain_all_frontier: the "
                                           "first view's gain is then the whole frontier's, and at 0.2 the I-beam's last "
                                           "flange was left unseen")
    cnbv_min_gain_fraction: float = Field(0.0, ge=0, lt=1, description="C-NBV: the same share; 0: only min_gain. "
                                          "C-NBV's first gain is the best over the whole frontier, so a share of it "
                                          "ended scans while parts of the drawing were still unseen")
    search_radius_m: float = Field(0.55, gt=0.05, le=1.5, description="outer radius of the candidate sphere")
    min_standoff_m: float = Field(0.25, ge=0.1, le=1.0, description="inner radius: the D435 needs distance")
    candidate_spacing_m: float = Field(0.05, ge=0.005, le=0.3)
    max_view_angle_deg: float = Field(60.0, gt=0, le=90, description="candidates within this angle of the surface normal")
    relaxed_view_angle_deg: float = Field(85.0, gt=0, le=90,
                                          description="the cone tried when no square-on view gains anything")
    min_camera_z_m: float = Field(0.12, description="candidates below this height are not generated")
    clearance_m: float = Field(0.12, ge=0, le=0.5, description="candidates this close to occupied cells are dropped")
    unknown_visibility: float = Field(0.99, gt=0, le=1,
                                      description="P[o=0] in eq. 8 of an unknown cell no ray has ended before: "
                                      "most unknown space round a piece is air, and a view into new ground looks through "
                                      "it (at 0.95 per 1 cm cell 30 cm of it hid all, so views stayed where the map was known)")
    shadow_visibility: float = Field(0.5, gt=0, le=1,
                                     description="P[o=0] in eq. 8 of an unknown cell behind an observed surface (paper: 0.5)")
    rays_w: int = Field(48, ge=4, le=400)
    rays_h: int = Field(28, ge=3, le=300)
    coarse_ray_factor: int = Field(3, ge=1, le=10, description="candidates are first scored with a ray bundle "
                                   "this many times sparser per axis (1: every candidate with the full bundle)")
    refine_top: int = Field(128, ge=1, le=100_000, description="... and the best this many by Q again with the full one")
    max_range_m: float = Field(0.8, gt=0.1, le=5)
    frontier_reach_voxels: int = Field(1, ge=1, le=10, description="how far a drawing cell may be from the unknown")
    min_frontier_cluster: int = Field(3, ge=1, le=1000)
    aim_ahead_m: float = Field(0.08, ge=0, le=0.5,
                               description="look this far past the frontier centroid along the drawing (0: at it, as the paper)")
    cnbv_candidate_spacing_m: float = Field(0.07, ge=0.01, le=0.3, description="C-NBV: lattice of its larger search space")
    cnbv_max_frontier: int = Field(400, ge=1, le=100_000, description="C-NBV: frontier cells seeding search spaces, at most")
    cnbv_angle_steps: int = Field(3, ge=1, le=9, description="C-NBV: orientations per axis (pitch, yaw)")
    cnbv_angle_step_deg: float = Field(15.0, gt=0, le=45, description="C-NBV: spacing of those orientations")
    global_view_directions: int = Field(120, ge=8, le=5000, description="global: candidates on the view sphere")
    global_standoff_m: float = Field(0.35, gt=0.1, le=2, description="global: sphere radius beyond the object")
    global_margin_m: float = Field(0.1, ge=0, le=1, description="global: unknown cells this far around the object count")
    global_unknown_visibility: float = Field(0.95, gt=0, le=1, description="global: unknown_visibility of its "
                                             "gain; it scores every unknown cell round the piece, the solid's inside too, "
                                             "and a more transparent unknown would draw it to look into the inside")
    global_stop_fraction: float = Field(0.03, gt=0, lt=1, description="global: stop when the best gain falls below this share of the first")
    floor_z_m: float = Field(0.02, description="global: occupied cells below this height are the floor")
    revisit_angle_deg: float = Field(25.0, ge=0, le=90,
                                     description="no candidate within this angle (seen from the target) of a past view")
    min_view_growth_voxels: int = Field(3, ge=0, le=10_000,
                                        description="G-NBV: a view adding fewer drawing voxels sends its target to the cone-free "
                                        "tier, a second one gives it up (0: never)")
    end_check_m: float = Field(0.03, ge=0, le=0.2, description="G-NBV: a frontier cluster at a tip of the drawing is "
                               "closed when this much surface past the tip was seen unpainted (0: never)")
    end_width_m: float = Field(0.012, gt=0, le=0.1, description="half-width of that tube past the tip; also the radius "
                               "within which paint must have seen surface all round to be sealed")
    end_radius_m: float = Field(0.05, gt=0.005, le=0.3, description="drawing within this of the cluster gives its direction")
    end_min_points: int = Field(40, ge=1, le=100_000, description="surface points (2 mm apart) that tube must hold")
    line_prior_m: float = Field(0.0, ge=0.0, le=0.5, description="G-NBV: where the surface round the drawing is a "
                                "cylinder, candidates are ranked first by how much of the line's continuation this "
                                "far past its ends they would image (planners.line_prior); 0: off")
    frame_line: bool = Field(False, description="G-NBV: each candidate is rolled about its optical axis so the image's "
                             "wide axis lies along the drawing at its target (the line runs on past its ends)")
    observed_known: bool = Field(True, description="a cell observed occupied or free carries no information "
                                 "about the drawing (its colour was seen with it): only unknown cells count in eq. 5")
    footprint_gain: bool = Field(False, description="G-NBV: each ray counts the cells its share of the image covers "
                                 "where it crosses them (max(1, t² · solid angle per ray / voxel²)), not one: a sparse "
                                 "bundle undercounts what a far view sees by that factor. C-NBV and global keep one per cell crossed: "
                                 "their stop rules were set with it, and C-NBV lost the I-beam with it (92 -> 87 %)")
    gain_all_frontier: bool = Field(False, description="G-NBV: the candidate spheres of the nearest usable "
                                    "clusters compete in one ranking and each candidate's gain counts every usable "
                                    "cluster's frontier, not only its target's (the paper: the nearest cluster's "
                                    "sphere, its frontier alone): a view that resolves two ends is worth both. Off by "
                                    "default: with footprint_gain it saves views but the basket falls to 90.5 % in 5-10 views "
                                    "(docs/BENCHMARKS.md, 2026-12-02 fifth step)")
    joint_clusters: int = Field(4, ge=1, le=64, description="G-NBV with gain_all_frontier: how many of the nearest "
                                "usable clusters put their candidate spheres into one ranking")
    facing_gain: bool = Field(True, description="each cell a ray meets counts by the cosine at which the ray meets "
                              "the surface the map says may be there (it faces observed free space); 0 from behind. "
                              "False: eq. 5 as the paper")
    open_edge_views: tuple[Literal["cnbv", "gnbv"], ...] = Field(
        ("cnbv",), description="planners that, when the grid's frontier has nothing left worth a view, look at the "
        "paint where the measured surface stops (planners.open_edges): C-NBV one view per group of it (its basket "
        "90.5-97.2 -> 96.7-97.2 %); G-NBV one per group (15 views on the basket) or, with joint_edge_views, all at once "
        "(configs/planners.yaml lists both)")
    joint_edge_views: bool = Field(False, description="G-NBV: its open-edge views (open_edge_views) scored on all the "
                                   "open paint at once, from round its centre, instead of one view per group of it")
    edge_cone: bool = Field(False, description="G-NBV: where the paint next to a target lies on the border of the "
                            "measured surface (planners.open_edges), the viewing cone is centred round that border, "
                            "halfway between the surface's normal and the way out past the border, not on the normal of "
                            "the surface within 3 cm: past a rim the unseen face turns away from the views that saw the top")
    open_edge_radius_m: float = Field(0.005, gt=0, le=0.05, description="disc of measured surface that tells whether "
                                      "a paint point lies on its border: a few 2 mm point spacings")
    max_target_visits: int = Field(3, ge=1, le=20, description="give up a frontier cluster after this many views at it")
    reach_prefilter: bool = Field(True, description="drop candidates the arm's capability map calls unreachable "
                                  "before scoring (planners.motion.reach_map), when the runner provides one")
    ik_candidates: int = Field(40, ge=1, le=10_000, description="ranked candidates the runner tries to reach")

    @model_validator(mode="after")
    def _radii(self) -> "NBVConfig":
        if self.min_standoff_m >= self.search_radius_m:
            raise ValueError(f"min_standoff_m ({self.min_standoff_m}) must be below search_radius_m ({self.search_radius_m})")
        return self


class ENVPConfig(_Strict):
    """Extrapolated NVP (§V-A, Alg. 1)."""

    delta_distance_voxels: float = Field(1.0, ge=0, le=50,
                                         description="δ_distance: extrapolate this far past the curve end (paper: 1 voxel)")
    delta_size_voxels: int = Field(3, ge=0, le=10_000,
                                   description="δ_size: an extremity is found when D_total grew by at most this many voxels")
    standoff_m: float = Field(0.35, ge=0.2, le=1.0, description="camera distance from the surface along its normal")
    normal_radius_m: float = Field(0.04, gt=0.005, le=0.3, description="neighbourhood for the surface normal")


class TorchConfig(_Strict):
    """The gas torch on the flange. Its frame: origin at the nozzle tip, z along the flame; the
    body is a cylinder of radius_m from the tip back length_m along -z (for collision checks)."""

    xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.20)  # along the flange z axis, past the fingers
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # fixed-axis roll x, pitch y, yaw z, as the hand-eye
    radius_m: float = Field(0.015, gt=0, le=0.2, description="the torch head")
    length_m: float = Field(0.18, gt=0, le=1.0, description="tip to the back end, nozzle included")
    # an oxy-fuel cutting nozzle tapers from the head to a tip about 12 mm across
    nozzle_radius_m: float = Field(0.006, gt=0, le=0.2, description="the nozzle at its tip")
    nozzle_length_m: float = Field(0.03, ge=0, le=0.5, description="the taper from the head to the tip")
    # within a few centimetres of the metal the occupancy grid's 1 cm cells (plus the margin) close an
    # inside corner the torch fits into: this much of it is checked against the scanned points instead
    fine_length_m: float = Field(0.06, ge=0, le=0.5, description="tip to here: checked against the surface cloud")

    @model_validator(mode="after")
    def _check(self) -> "TorchConfig":
        if self.nozzle_radius_m > self.radius_m:
            raise ValueError(f"torch nozzle_radius_m ({self.nozzle_radius_m}) is wider than its head ({self.radius_m})")
        if self.nozzle_length_m >= self.length_m:
            raise ValueError(f"torch nozzle_length_m ({self.nozzle_length_m}) must be shorter than the torch "
                             f"({self.length_m})")
        if not self.nozzle_length_m <= self.fine_length_m < self.length_m:
            raise ValueError(f"torch fine_length_m ({self.fine_length_m}) must cover the nozzle "
                             f"({self.nozzle_length_m}) and be shorter than the torch ({self.length_m})")
        if any(abs(v) > 360.0 for v in self.rpy_deg):
            raise ValueError(f"torch rpy_deg {self.rpy_deg} outside [-360, 360]")
        if float(np.linalg.norm(self.xyz_m)) > 1.0:
            raise ValueError(f"torch xyz_m {self.xyz_m} is more than 1 m from the flange")
        return self

    def T_flange_torch(self) -> np.ndarray:
        """4x4 torch-tip frame in the flange frame: pass it as Kinematics' T_flange_cam."""
        return pose_from_xyz_rpy_deg(self.xyz_m, self.rpy_deg)

    def T_flange_mount(self) -> np.ndarray:
        """4x4 frame at the torch's back end, same axes as the tip frame: the cylinder spans
        z in [0, length_m] of it (as planners.motion.collision.TorchShape wants its frame)."""
        T = self.T_flange_torch()
        T[:3, 3] -= self.length_m * T[:3, 2]
        return T


class CutPathConfig(_Strict):
    """From the drawing cloud to torch poses and the joint motion that follows them."""

    # drawing -> branches
    line_from: Literal["outline", "skeleton"] = Field(
        "outline", description="the line from the paint's outline moved inward by half the spray width (keeps "
        "sharp tips), or the voxel skeleton of the whole paint (cuts chords across them)")
    voxel_m: float = Field(0.005, ge=0.001, le=0.05, description="skeleton voxel; the 2 mm surface cloud allows 5 mm")
    closing_iterations: int = Field(1, ge=0, le=5, description="close gaps of up to 2x this many voxels")
    min_branch_m: float = Field(0.03, ge=0, le=1.0, description="spurs shorter than this are dropped")
    bridge_max_m: float = Field(0.08, gt=0, le=0.5, description="pieces of a broken line this close belong to one line")
    min_piece_m: float = Field(0.008, gt=0, le=0.2, description="a piece of paint shorter than this along the line is a speck")
    smoothing_voxels: float = Field(0.5, ge=0, le=5, description="B-spline: RMS deviation allowed from the skeleton")
    outline_smoothing_m: float = Field(0.001, ge=0, le=0.02, description="B-spline: RMS deviation allowed from the "
                                       "line the paint's outline gives (line_from: outline)")
    corner_deg: float = Field(45.0, gt=0, le=180, description="a turn sharper than this is a corner: not smoothed away")
    corner_scale_m: float = Field(0.03, ge=0, le=0.2, description="arc over which a corner's turn is measured (0: no corners)")
    spacing_m: float = Field(0.005, ge=0.0005, le=0.1, description="arc length between torch poses")
    pivot_step_deg: float = Field(5.0, gt=0, le=90, description="a larger turn of the normal between poses is taken in "
                                  "steps (the joints between two steps move the flame off its spot: 10 deg moved it 2-4 mm)")
    normal_radius_m: float = Field(0.02, gt=0.002, le=0.2, description="neighbourhood of the surface normal (PCA)")
    # torch poses
    standoff_m: float = Field(0.010, ge=0, le=0.1, description="tip to surface along the normal")
    travel_speed_mps: float = Field(0.005, gt=0, le=0.5, description="cutting speed along the drawing")
    approach_m: float = Field(0.05, ge=0, le=0.5, description="approach/retract pose this far back along the torch axis")
    torch: TorchConfig = TorchConfig()
    # joint motion
    free_roll: bool = Field(True, description="roll about the torch axis left to IK: a round nozzle is symmetric")
    # tolerances (oxy-fuel practice: the tip leans 5-20 deg along the travel, lead or lag; a
    # side tilt bevels the kerf, so less of it is allowed)
    lead_lag_max_deg: float = Field(20.0, ge=0, le=45, description="torch axis tilt along the travel, either way")
    side_tilt_max_deg: float = Field(10.0, ge=0, le=45, description="torch axis tilt across the travel, either way")
    tilt_steps: int = Field(2, ge=0, le=6, description="samples per side of each tilt range (0: the normal only)")
    tilt_cost_weight: float = Field(1.0, ge=0, le=100, description="cost of tilt (rad^2) against joint motion (rad^2)")
    min_cut_m: float = Field(0.02, ge=0, le=0.5, description="a run shorter than this is no cut (a pierce for a stub), "
                             "unless its whole stroke is")
    max_joint_jump_rad: float = Field(0.2, gt=0, le=math.pi, description="larger joint change between poses is infeasible")
    ik_margin_rad: float = Field(0.05, ge=0, le=0.5, description="kept from every joint limit")
    ik_seeds: int = Field(8, ge=1, le=64, description="IK starts per torch pose (tracks of the ladder graph)")
    approach_speed_factor: float = Field(0.3, gt=0, le=1, description="of the arm's limits, for approach and retract")
    dt_s: float = Field(0.01, gt=0, le=0.1, description="sample period of the joint trajectories")
    reverse_branches: bool = Field(True, description="start each branch at the end nearer the torch")
    # collision checks of the cut (the torch must come close to the metal: its nozzle is exempt)
    cut_margin_m: float = Field(0.005, ge=0, le=0.1, description="clearance of arm and torch from the scan")
    max_clearing_views: int = Field(2, ge=0, le=8, description="views after the scan where unseen space blocks the torch")
    nozzle_margin_m: float = Field(0.002, ge=0, le=0.05, description="clearance of the nozzle from the scanned surface")
    # the cut against the paint (planners.cutpath.paint_report)
    line_tolerance_m: float = Field(0.005, gt=0, le=0.05, description="a flame spot this close to the painted line's "
                                    "centre is on it; paint farther than half the spray width plus this from every "
                                    "cut is left uncut")
    flame_deviation_m: float = Field(0.002, gt=0, le=0.05, description="the lit flame may leave the line between "
                                     "two torch poses by this much; a motion that swings it farther is no pivot")
    spray_width_m: float = Field(0.02, gt=0, le=0.1, description="the spray's width where no line can measure it")
    share_disagreement: float = Field(0.03, gt=0, le=1, description="the cut's own share and the paint's differing "
                                      "by more than this is a warning")

    @model_validator(mode="after")
    def _sizes(self) -> "CutPathConfig":
        if self.normal_radius_m < self.voxel_m:
            raise ValueError(f"normal_radius_m ({self.normal_radius_m}) must be at least voxel_m ({self.voxel_m})")
        return self


class PlannersConfig(_Strict):
    grid: GridConfig = GridConfig()
    paint: PaintColor = PaintColor()
    nbv: NBVConfig = NBVConfig()
    enpv: ENVPConfig = ENVPConfig()
    max_steps: int = Field(16, ge=1, le=200, description="views per scan at most, initial one included")
    coverage_voxel_m: float = Field(0.01, gt=0.001, le=0.1)
    cutpath: CutPathConfig = CutPathConfig()

    @model_validator(mode="before")
    @classmethod
    def _no_hsv(cls, data):
        if isinstance(data, dict) and "color" in data:
            raise ValueError("`color:` (the fixed HSV paint filter) is gone: the paint is a colour model in CIELAB "
                             "under `paint:` (planners.config.PaintColor), commissioned with `cellctl calibrate "
                             "paint`; delete the `color:` block")
        return data


class ConfigError(ValueError):
    """A config file is unreadable or invalid; the message names the file and the field."""


def load_yaml_model(path: str | Path, model: type[BaseModel]) -> BaseModel:
    """Load and validate a YAML file; every failure is a ConfigError naming the file and field."""
    return _load_yaml_model(path, model, ConfigError, "config")


def load_planners_config(path: str | Path | None = None) -> PlannersConfig:
    if path is None:
        from configs import CONFIG_DIR  # configs/ is data only; no device code behind it

        path = CONFIG_DIR / "planners.yaml"
    return load_yaml_model(path, PlannersConfig)  # type: ignore[return-value]
