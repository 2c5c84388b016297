"""Commissioning the yard's paint from one picture of a sample: paint sprayed on a piece of the yard's
scrap, held so the paint is in the middle of the picture and bare metal all round it.

The picture's colours are clustered (scikit-learn GaussianMixture in CIELAB, the number of colours by
BIC); the paint is the colour found in the middle and nowhere on the sample's rim, the metal every colour
of the rim. The paint model (mean, covariance) is written to the cell's config only if it is apart from
every metal colour by ``min_delta_e`` and the metal all round does not pass its gate: a sample with no
paint, or paint the cell could not tell from this metal, is refused with the reason.
"""

from __future__ import annotations

import warnings

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from skimage.color import deltaE_cie76
from sklearn.exceptions import ConvergenceWarning
from sklearn.mixture import GaussianMixture

from planners.config import PaintColor
from planners.paint_color import REG, to_lab

FIT_SAMPLES = 8000  # pixels the mixture is fitted on
MAX_COLOURS = 6  # at most this many colours in one sample (paint, rust patches, bare steel, glints, ...)
CENTRE = 1.0 / 3.0  # the middle third of the picture (each way) is where the paint is held
RIM = 1.0 / 6.0  # the outer sixth on every side is the metal round it
MIN_CENTRE_SHARE = 0.05  # the paint covers at least this much of the middle
MAX_RIM_SHARE = 0.01  # ... and no more than this of the rim (a colour on the rim is the metal's)
MAX_METAL_PASS = 0.02  # the rim's pixels the new paint gate may take: paint taken from the metal
MIN_VAR = 4.0  # Lab units squared: the least spread kept per axis (a D435's colour noise and a scan's shading)
SAMPLE_DEPTH_M = 0.05  # the sample: pixels within this of the depth at the picture's middle


class PaintCalibration(BaseModel):
    """What `cellctl calibrate paint` found. ``paint`` is set only when ``ok``."""

    model_config = ConfigDict(extra="forbid")

    ok: bool
    reason: str | None = None
    paint: PaintColor | None = None
    delta_e: float | None = Field(None, description="ΔE76 from the paint to the nearest metal colour of the sample")
    colours: int = Field(0, description="colours the sample was clustered into")
    paint_pixels: int = 0
    centre_share: float | None = Field(None, description="share of the middle that is paint")
    metal_lab: list[list[float]] = Field(default_factory=list, description="the rim's colours, L* a* b*")
    metal_pass_share: float | None = Field(None, description="share of the rim the paint's gate takes as paint")
    sample_pixels: int = 0


def sample_mask(depth: np.ndarray, band_m: float = SAMPLE_DEPTH_M) -> np.ndarray:
    """Pixels of the sample: the surface at the distance the picture's middle shows (the floor or the
    wall behind is farther). (H, W) bool; all False when the middle has no depth."""
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    mid = depth[int(H * (0.5 - CENTRE / 2)):int(H * (0.5 + CENTRE / 2)), int(W * (0.5 - CENTRE / 2)):int(W * (0.5 + CENTRE / 2))]
    mid = mid[np.isfinite(mid) & (mid > 0)]
    if len(mid) < 100:
        return np.zeros((H, W), dtype=bool)
    z = float(np.median(mid))
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (np.abs(depth - z) < band_m)


def regions(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(centre, rim) pixel masks of a picture of ``shape``."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W]
    fu, fv = (u + 0.5) / W, (v + 0.5) / H
    centre = (np.abs(fu - 0.5) < CENTRE / 2) & (np.abs(fv - 0.5) < CENTRE / 2)
    rim = (fu < RIM) | (fu > 1 - RIM) | (fv < RIM) | (fv > 1 - RIM)
    return centre, rim


def calibrate_paint(rgb: np.ndarray, sample: np.ndarray, base: PaintColor, *, name: str, source: str,
                    seed: int = 0) -> PaintCalibration:
    """The paint model from a picture (``rgb`` (H, W, 3) uint8) of a sample whose pixels ``sample`` (H, W)
    marks. ``base`` gives the check's limits (``min_delta_e``, ``gate_d2``), kept in the result."""
    rgb = np.asarray(rgb, dtype=np.uint8)
    sample = np.asarray(sample, dtype=bool)
    centre, rim = regions(sample.shape)
    centre, rim = centre & sample, rim & sample
    n = int(sample.sum())
    if centre.sum() < 200 or rim.sum() < 200:
        where = "the middle of the picture" if centre.sum() < 200 else "the rim of the picture"
        return PaintCalibration(ok=False, sample_pixels=n, reason=(
            f"the sample does not fill {where} (no depth there, or nothing at the middle's distance): hold it "
            f"0.25-0.5 m in front of the camera, filling the picture"))
    lab = to_lab(rgb[sample])
    at_centre, at_rim = centre[sample], rim[sample]
    rng = np.random.default_rng(seed)
    fit_on = lab[rng.choice(len(lab), FIT_SAMPLES, replace=False)] if len(lab) > FIT_SAMPLES else lab
    gmm = _mixture(fit_on, seed)
    label = gmm.predict(lab)
    k = gmm.n_components
    c_share = np.bincount(label[at_centre], minlength=k) / max(1, at_centre.sum())
    r_share = np.bincount(label[at_rim], minlength=k) / max(1, at_rim.sum())
    metal = r_share > MAX_RIM_SHARE
    metal_lab = [np.round(gmm.means_[j], 1).tolist() for j in np.flatnonzero(metal)]
    candidates = np.flatnonzero(~metal & (c_share >= MIN_CENTRE_SHARE))
    out = PaintCalibration(ok=False, colours=int(k), metal_lab=metal_lab, sample_pixels=n)
    if len(candidates) == 0:
        out.reason = ("no paint in the sample: every colour in the middle of the picture is also on the metal round "
                      "it (spray a patch of the paint, hold it in the middle, bare metal all round)")
        return out
    j = int(candidates[np.argmax(c_share[candidates])])
    px = lab[(label == j) & at_centre]
    mean = px.mean(axis=0)
    cov = np.cov(px.T) if len(px) > 3 else np.zeros((3, 3))
    w, V = np.linalg.eigh(cov)
    cov = (V * np.maximum(w, MIN_VAR)) @ V.T  # a flat-lit sample has next to no spread; scans do
    cov = 0.5 * (cov + cov.T)
    out.paint_pixels, out.centre_share = int(len(px)), round(float(c_share[j]), 4)
    de = np.array([float(deltaE_cie76(mean, gmm.means_[m])) for m in np.flatnonzero(metal)] or [np.inf])
    out.delta_e = round(float(de.min()), 2) if np.isfinite(de.min()) else None
    d = lab[at_rim] - mean
    d2 = np.einsum("ij,jk,ik->i", d, np.linalg.inv(cov + REG * np.eye(3)), d)
    out.metal_pass_share = round(float((d2 < base.gate_d2).mean()), 4)
    if out.delta_e is not None and out.delta_e < base.min_delta_e:
        out.reason = (f"the paint cannot be told from this metal: ΔE76 {out.delta_e:.1f} between the paint and the "
                      f"metal round it (at least {base.min_delta_e:g} needed): use a paint of another colour")
        return out
    if out.metal_pass_share > MAX_METAL_PASS:
        out.reason = (f"{100 * out.metal_pass_share:.1f} % of the metal round the paint has the paint's colour (at "
                      f"most {100 * MAX_METAL_PASS:g} %): the cell would take this metal for paint; use a paint of "
                      f"another colour")
        return out
    out.ok = True
    out.paint = PaintColor(**{**base.model_dump(), "name": name, "source": source[:200],
                              "lab_mean": tuple(round(float(x), 2) for x in mean),
                              "lab_cov": tuple(tuple(round(float(x), 3) for x in row) for row in cov)})
    return out


def _mixture(lab: np.ndarray, seed: int) -> GaussianMixture:
    """The sample's colours: the mixture of 2..MAX_COLOURS components with the lowest BIC."""
    best, best_bic = None, np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        for k in range(2, MAX_COLOURS + 1):
            g = GaussianMixture(k, covariance_type="full", reg_covar=1.0, max_iter=100, n_init=1,
                                init_params="k-means++", random_state=seed).fit(lab)
            bic = g.bic(lab)
            if bic < best_bic:
                best, best_bic = g, bic
    return best
