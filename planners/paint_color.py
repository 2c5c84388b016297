"""Which pixels are paint: the commissioned paint colour (CIELAB) adapted to each piece, and the check
that the paint can be told from its metal at all.

The paper's filter ξ is a fixed colour range and assumes the paint differs from the metal. Scrap is
rusty, primed or painted already, and light changes, so the cell fits, on each piece's initial view,
a Gaussian mixture in CIELAB: one component seeded at the commissioned paint, two at the metal
(darker and lighter half of the piece). The fit follows the paint under dim or coloured light; the
check then refuses a piece whose paint is not a thin band clearly apart from its metal.
"""

from __future__ import annotations

import warnings

import numpy as np
from skimage.color import deltaE_cie76, lab2rgb, rgb2lab
from sklearn.exceptions import ConvergenceWarning
from sklearn.mixture import GaussianMixture

from planners.paint_separation import PaintSeparation

FIT_SAMPLES = 6000  # pixels of the piece the mixture is fitted on (a random subset)
METAL_PARTS = 3  # mixture components for the metal: its colours by lightness (rust, bare, shade)
GAINS = np.array([0.35, 0.45, 0.55, 0.7, 0.85, 1.0, 1.15, 1.3, 1.5])  # light levels the seed tries
MIN_L = 12.0  # L* below which a shaded colour is not told from another
SHADES = np.array([0.55, 0.62, 0.7, 0.8, 0.9, 1.0, 1.12, 1.25, 1.4])  # one view's faces: turned from the lamp or to it
WHITES = np.array([(1.0, 1.0, 1.0), (1.1, 1.0, 0.8), (0.9, 1.0, 1.12)])  # neutral, tungsten, overcast
LUT_BITS = 6  # the mask's colour table: 6 bits a channel, a step of 4 in 255 (at most ~1.5 ΔE76 off)
REG = 4.0  # Lab units squared added to each covariance: a paint stroke seen flat-lit has next to no spread


def to_lab(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 sRGB -> (N, 3) CIELAB (D65), float64."""
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    if len(rgb) == 0:
        return np.zeros((0, 3))
    return rgb2lab(rgb.reshape(1, -1, 3).astype(np.float64) / 255.0).reshape(-1, 3)


class PaintSegmenter:
    """The paint mask of one job. Before ``fit`` it uses the commissioned colour alone (a Mahalanobis
    gate); after, the mixture fitted on the piece."""

    def __init__(self, paint) -> None:  # paint: planners.config.PaintColor
        self.paint = paint
        self.mean0 = np.asarray(paint.lab_mean, dtype=np.float64)
        self.cov0 = np.asarray(paint.lab_cov, dtype=np.float64) + REG * np.eye(3)
        self.gmm: GaussianMixture | None = None
        self.check: PaintSeparation | None = None
        self._lut: np.ndarray | None = None
        self.floor_z: float | None = None  # the table the piece lies on, from ``fit_view``
        self.workspace: tuple[np.ndarray, np.ndarray] | None = None  # the box the piece lies in (the grid's)

    @property
    def fitted(self) -> bool:
        return self.gmm is not None

    def mask(self, rgb: np.ndarray) -> np.ndarray:
        """Which of the (N, 3) uint8 colours are paint. After ``fit`` a table over every colour at
        LUT_BITS per channel: a D435 frame is 400 k pixels, every view."""
        rgb = np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1, 3)
        if self.gmm is None:
            return _d2(to_lab(rgb), self.mean0, self.cov0) < self.paint.gate_d2
        if self._lut is None:  # -1: not asked yet; a view shows a few thousand of the table's 262 k colours
            self._lut = np.full(len(_LUT_COLOURS), -1, dtype=np.int8)
        idx = _lut_index(rgb)
        new = np.unique(idx[self._lut[idx] < 0])
        if len(new):
            self._lut[new] = self._mask_lab(to_lab(_LUT_COLOURS[new]))
        return self._lut[idx] > 0

    def paint_points(self, rgb: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """Which of the points (colours, base-frame positions) are paint: the paint's colour, on the piece.
        The table the piece lies on is never paint, whatever its colour (a white paint and a grey table
        look alike)."""
        paint = self.mask(rgb)
        xyz = np.asarray(xyz).reshape(-1, 3)
        if self.floor_z is not None:
            paint &= xyz[:, 2] > self.floor_z + self.paint.piece_above_m
        if self.workspace is not None:  # the floor far off, lifted by the depth noise there, is no piece either
            paint &= np.all((xyz >= self.workspace[0]) & (xyz <= self.workspace[1]), axis=1)
        return paint

    def _mask_lab(self, lab: np.ndarray) -> np.ndarray:
        # Each component seen under more or less light (a face turned from the lamp): a colour is paint
        # when the paint, lit somehow, explains it better than any metal, and within the paint's gate.
        d2 = np.stack([_d2_shaded(lab, m, c) for m, c in zip(self.gmm.means_, self.gmm.covariances_)])
        paint = d2[self.is_paint_part].min(axis=0)
        if self.is_paint_part.all():
            return paint < self.paint.gate_d2
        return (paint < self.paint.gate_d2) & (paint <= d2[~self.is_paint_part].min(axis=0))

    def fit_view(self, rgb: np.ndarray, xyz: np.ndarray, floor_z: float, seed: int = 0,
                 workspace: tuple | None = None) -> PaintSeparation:
        """``fit`` on one view's points higher than ``paint.piece_above_m`` over the floor and inside
        ``workspace`` ((lo, hi) corners, the grid's box) when given: the piece, not the table it lies on."""
        self.floor_z = float(floor_z)
        if workspace is not None:
            self.workspace = (np.asarray(workspace[0], dtype=np.float64), np.asarray(workspace[1], dtype=np.float64))
        piece = np.asarray(xyz)[:, 2] > floor_z + self.paint.piece_above_m
        if self.workspace is not None:
            piece &= np.all((np.asarray(xyz) >= self.workspace[0]) & (np.asarray(xyz) <= self.workspace[1]), axis=1)
        return self.fit(np.asarray(rgb)[piece], np.asarray(xyz)[piece], seed)

    def fit(self, rgb_piece: np.ndarray, xyz_piece: np.ndarray, seed: int = 0) -> PaintSeparation:
        """Fit on the piece's points of the initial view (colours, base-frame positions) and check the
        paint. Returns (and keeps) the ``PaintSeparation``."""
        lab = to_lab(rgb_piece)
        cfg = self.paint
        if len(lab) < 100:
            self.check = PaintSeparation(ok=False, reason=f"the initial view shows only {len(lab)} points of the piece")
            return self.check
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(lab), FIT_SAMPLES, replace=False) if len(lab) > FIT_SAMPLES else np.arange(len(lab))
        sample, sample_xyz = lab[pick], np.asarray(xyz_piece)[pick]
        light, seeded, metal_passes = self._seed(sample)
        if not seeded.any():
            why = ("under some light the metal itself has the paint's colour, and no light shows a line of it"
                   if metal_passes else "under no light from %g to %g times the sample's" % (GAINS[0], GAINS[-1]))
            self.check = PaintSeparation(ok=False, reason=f"no paint of the commissioned colour ({cfg.name}) in the "
                                                     f"initial view: {why}")
            return self.check
        rest = sample[~seeded] if (~seeded).sum() > 10 else sample
        parts = np.array_split(rest[np.argsort(rest[:, 0])], METAL_PARTS)  # the metal by lightness
        parts = [q if len(q) > 3 else rest for q in parts]
        means = np.stack([sample[seeded].mean(axis=0)] + [q.mean(axis=0) for q in parts])
        covs = np.stack([_cov(sample[seeded])] + [_cov(q) for q in parts])
        share0 = float(seeded.mean())
        gmm = GaussianMixture(1 + METAL_PARTS, covariance_type="full", means_init=means,
                              precisions_init=np.linalg.inv(covs),
                              weights_init=[share0] + [(1 - share0) / METAL_PARTS] * METAL_PARTS, reg_covar=REG,
                              max_iter=40, tol=1e-3, random_state=seed)
        with warnings.catch_warnings():  # 40 EM steps from a seeded start are enough; a few more would not matter
            warnings.simplefilter("ignore", ConvergenceWarning)
            gmm.fit(sample)
        self.gmm, self._lut = gmm, None
        self.light = light
        # a component on the paint's shading line is the paint on a face turned from the light, unless it
        # covers the piece in patches wider than a spray: then it is metal that, less lit, looks like the
        # paint (grey steel beside white paint, brown rust beside orange)
        label = gmm.predict(sample)
        self.is_paint_part = np.array([True] + [
            float(_d2_shaded(gmm.means_[k][None], gmm.means_[0], gmm.covariances_[0])[0]) < cfg.gate_d2
            and not _wider_than(sample_xyz[label == k], sample_xyz[label != k], cfg.max_band_m)
            for k in range(1, 1 + METAL_PARTS)])
        paint_mu, metal_mu = gmm.means_[0], gmm.means_[~self.is_paint_part]
        is_paint = self._mask_lab(lab)
        share = float(is_paint.mean())
        de_metal = np.array([float(deltaE_cie76(paint_mu, m)) for m in metal_mu] or [0.0])
        check = PaintSeparation(ok=True, delta_e=float(de_metal.min()), paint_share=share,
                           paint_lab=np.round(paint_mu, 1).tolist(), metal_lab=np.round(metal_mu, 1).tolist())
        if share * len(lab) < cfg.min_paint_points:
            check.ok = False
            check.reason = (f"no paint of the commissioned colour ({cfg.name}) in the initial view: "
                            f"{int(share * len(lab))} points look like it")
        elif len(metal_mu) == 0:
            check.ok = False
            check.reason = "every colour of the piece is the paint's, lit more or less: the metal looks like the paint"
        elif check.delta_e < cfg.min_delta_e:
            check.ok = False
            check.reason = (f"the paint cannot be told from the metal: ΔE76 {check.delta_e:.1f} between what looks "
                            f"like paint and the metal beside it (at least {cfg.min_delta_e:g} needed)")
        elif share > cfg.max_share:
            check.ok = False
            check.reason = (f"what looks like paint covers {100 * share:.0f} % of the piece in the initial view "
                            f"(a painted line covers at most {100 * cfg.max_share:.0f} %): the metal itself looks "
                            f"like the paint")
        else:
            width = band_width(xyz_piece[is_paint], xyz_piece[~is_paint])
            check.band_width_m = width
            if width is not None and width > cfg.max_band_m:
                check.ok = False
                check.reason = (f"what looks like paint is {1000 * width:.0f} mm wide, not a line (a spray is at "
                                f"most {1000 * cfg.max_band_m:.0f} mm): the metal itself looks like the paint")
        if check.ok and check.delta_e < cfg.warn_delta_e:
            check.warnings.append(f"paint and metal are close in colour (ΔE76 {check.delta_e:.1f}, below "
                                  f"{cfg.warn_delta_e:g}): check the cut follows the paint before lighting the torch")
        self.check = check
        return check

    def _seed(self, lab: np.ndarray) -> tuple[tuple[float, int], np.ndarray, bool]:
        """The light under which the commissioned paint shows on this piece, and the colours that pass its
        gate there: each light (a gain on the sample's sRGB, a white balance) is tried, and the one nearest
        the sample's light that finds a line's worth of paint wins. Also whether some light would make
        the metal itself pass (more than ``max_share`` of the piece)."""
        cfg = self.paint
        rgb0 = lab2rgb(self.mean0.reshape(1, 1, 3)).reshape(3)
        lights = [(g, w) for w in range(len(WHITES)) for g in GAINS]
        rgb = np.clip(np.array([g * rgb0 * WHITES[w] for g, w in lights]), 0, 1)
        means = rgb2lab(rgb.reshape(1, -1, 3)).reshape(-1, 3)
        passed = (_d2_to(lab, means, self.cov0) < cfg.gate_d2).T  # lights x pixels
        counts = passed.sum(axis=1)
        n_min = max(3.0, cfg.min_paint_points * FIT_SAMPLES / max(len(lab), FIT_SAMPLES))
        line = (counts >= n_min) & (counts <= cfg.max_share * len(lab))
        metal_passes = bool((counts > cfg.max_share * len(lab)).any())
        if not line.any():
            return (1.0, 0), np.zeros(len(lab), dtype=bool), metal_passes
        cost = np.array([abs(np.log(g)) + (0.3 if w else 0.0) for g, w in lights])  # the sample's light first
        k = int(np.flatnonzero(line)[np.argmin(cost[line])])
        return lights[k], passed[k], metal_passes


def _lut_index(rgb: np.ndarray) -> np.ndarray:
    q = (rgb >> (8 - LUT_BITS)).astype(np.int32)
    return (q[:, 0] << (2 * LUT_BITS)) | (q[:, 1] << LUT_BITS) | q[:, 2]


_q = (np.arange(1 << LUT_BITS) << (8 - LUT_BITS)) + (1 << (7 - LUT_BITS))  # each bin's centre
_LUT_COLOURS = np.stack(np.meshgrid(_q, _q, _q, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.uint8)


def _cov(x: np.ndarray) -> np.ndarray:
    return (np.cov(x.T) if len(x) > 3 else np.zeros((3, 3))) + REG * np.eye(3)


def band_width(paint_xyz: np.ndarray, metal_xyz: np.ndarray) -> float | None:
    """The paint's width: twice the distance from its points to the nearest metal beside them (the 90th
    percentile, so a few stray pixels do not narrow it). A line gives its spray width, however it
    bends; metal that looks like paint gives the size of the piece. None without metal or paint."""
    from scipy.spatial import cKDTree

    paint_xyz, metal_xyz = np.asarray(paint_xyz).reshape(-1, 3), np.asarray(metal_xyz).reshape(-1, 3)
    if len(paint_xyz) < 20 or len(metal_xyz) < 20:
        return None
    d, _ = cKDTree(metal_xyz).query(paint_xyz, workers=-1)
    return 2.0 * float(np.quantile(d, 0.9))


def _wider_than(part_xyz: np.ndarray, rest_xyz: np.ndarray, width_m: float) -> bool:
    """Whether a colour's points form patches wider than ``width_m`` (``band_width``), not a line."""
    w = band_width(part_xyz, rest_xyz)
    return w is not None and w > width_m


def _d2_shaded(lab: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances of (N, 3) Lab colours to a colour lit anywhere from SHADES times
    as bright (its sRGB scaled: Lambertian shading), the nearest of them."""
    rgb = lab2rgb(np.asarray(mean, dtype=np.float64).reshape(1, 1, 3)).reshape(3)
    means = rgb2lab(np.clip(np.outer(SHADES, rgb), 0, 1).reshape(1, -1, 3)).reshape(-1, 3)
    means = means[(means[:, 0] >= MIN_L) | (SHADES == 1.0)]  # near black every colour looks alike
    return _d2_to(lab, means, cov).min(axis=1)


def _d2(lab: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances of (N, 3) Lab colours."""
    return _d2_to(lab, np.asarray(mean, dtype=np.float64).reshape(1, 3), cov)[:, 0]


def _d2_to(lab: np.ndarray, means: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N, M) squared Mahalanobis distances of (N, 3) Lab colours to (M, 3) means of one covariance:
    whitened (inv(cov) = W W^T), |z - zm|^2 = |z|^2 - 2 z.zm + |zm|^2, every mean in one product."""
    w = np.linalg.cholesky(np.linalg.inv(cov))
    z, zm = np.asarray(lab, dtype=np.float64).reshape(-1, 3) @ w, means @ w
    return np.maximum((z * z).sum(axis=1)[:, None] - 2.0 * (z @ zm.T) + (zm * zm).sum(axis=1)[None, :], 0.0)
