"""Region growing: the compact representation of ERASE-Net (docs/design.md section 6).

From each seed (a predicted centre, in bins) a region grows through 6-connected voxels of the RAD
cube. A voxel joins when its intensity is at least ``intensity_ratio`` times the seed's (the paper's
``I_thresh``: half the seed's intensity) and its (range, angle) cell lies within ``distance_m``
metres of the seed's cell in Cartesian x-y (``D_thresh``). Doppler is bounded only by connectivity
and intensity (the Doppler axis is not treated as circular).

Intensity is log power in dB above the frame's noise level (by default the median log power of the
cube, estimated on a subsample; objects fill far less than half of it). Half of the raw dB value
would sit tens of dB below the noise, admit every voxel of the disc and make ``I_thresh`` void; the
paper grows regions on its normalised input, where noise sits near zero, which is what this is.
A voxel must also be at least ``min_snr_db`` above the noise level (labels never go below noise + 6
dB), so a weak seed's region cannot leak through the noise.

Vectorised: per seed, one threshold over the box around the seed's disc and one flood fill
(scikit-image's compiled fill) from the seed, never a Python loop over voxels. "Visited points" are the
voxels a breadth-first search would examine, accepted or not: the region and its 6-neighbours in
the cube (a binary dilation), counted once over all seeds. ``bridge`` lets a region cross small
gaps (candidates dilated ``bridge`` times for connectivity, so gaps of up to ``2 * bridge`` voxels close;
only real candidates become members).

Cost: members leave the padded box as flat cube indices (no argwhere / ravel), the first seed
keeps a voxel through a whole-cube claim mask (no np.unique), visited voxels are OR-ed into a whole-cube
mask on each region's bounding box and counted there (whole-cube masks are zeroed by the OS page by page, so
only the pages near the regions are touched), and the noise median is selected within a bracket. Same
voxels, owners and visited counts as the plain algorithm (tests/radar/test_region_growing.py keeps it as the
reference); 1.5x (``small``, bridging: the fill over the dilated candidates is most of what remains) to 2.2x
(``carrada``) faster.

Settings per radar are part of its profile (the ``[region_growing]`` table of its file; read by
:meth:`RegionGrowingConfig.for_profile`); a radar whose file states none gets the paper's 0.5 / 6 m with a
logged warning, and ``radarseg radar tune-growing PROFILE`` (:mod:`radar.growing_sweep`) derives them for a
new radar from a short sweep on its simulated frames. The built-in presets' settings come from sweeps over
ratio x floor x D_thresh x bridge on simulated frames seeded at the true centres (12 frames per preset; recall /
mean ROI voxels): the ``I_thresh`` ratio is 0 everywhere, so the noise floor binds (simulated labels
reach down to noise + 6 dB and to their object's peak - 20 dB; a ratio of 0.5 cut recall to 0.6-0.8).

- ``small``: 5 dB floor, 12 m, bridging 2 (80 validation frames of a 1000-sequence store, recall / ROI voxels /
  visited: 6 dB, 12 m, bridge 1: 0.885 / 12.1 k / 29 k; bridge 2: 0.915 / 17.6 k; 16 m: 0.935 / 24.2 k;
  5 dB, 12 m: 0.943 / 26.7 k / 74 k (chosen); 5 dB, 16 m: 0.961 / 37.0 k; 20 m: 0.967 / 45.9 k). The misses
  are bright voxels of the same object in blobs the disc or the gaps cut off: an 8-element array spreads
  a strong object over +-20 angle bins (about +-10 m laterally at 30 m), and near +-60 degrees the
  angle FFT wraps part of it to the other edge;
- ``carrada``: 4.5 dB floor, 12 m, no bridging: 0.912 / 21 k. Its 8-element array spreads objects
  wide in angle and its 0.2 m x 32x-padded bins make noise clusters large: 0.95 needed a 3 dB floor
  with bridging and 400 k ROI voxels (1.4 s), so we trade recall for a compact ROI;
- ``nxp``: the paper's 6 m, 6 dB floor, bridging (its 192-element array resolves an object's
  scatterers into separate blobs);
- other radars: the paper's 0.5 / 6 m unless their file says otherwise.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.morphology._flood_fill_cy import _flood_fill_equal  # flood's compiled fill (scikit-image pinned)
from skimage.segmentation import flood

from radar.centres import Centres
from radar.profiles import RadarProfile, get_profile

logger = logging.getLogger(__name__)
_warned_default: set[str] = set()

SIX_CONNECTED = ndimage.generate_binary_structure(3, 1)


@dataclass(frozen=True)
class RegionGrowingConfig:
    intensity_ratio: float = 0.5  # I_thresh = ratio * the seed's dB above the noise level
    distance_m: float = 6.0  # D_thresh: radius of the x-y disc around the seed's cell
    min_snr_db: float = 6.0  # and never below this many dB above the noise level
    seed_search: tuple[int, int, int] = (2, 2, 2)  # the seed moves to the brightest voxel within +- these bins
    bridge: int = 0  # dilations linking candidates: gaps of up to 2 * bridge voxels close (True = 1)

    @classmethod
    def for_profile(cls, profile: RadarProfile | str, **overrides) -> RegionGrowingConfig:
        """The settings a radar's profile states (its ``[region_growing]`` table), with keyword overrides; the
        paper's for a profile that states none (logged once per radar)."""
        profile = get_profile(profile)
        stated = dict(profile.region_growing)
        if not stated and not overrides and profile.name not in _warned_default:
            _warned_default.add(profile.name)
            logger.warning("radar %r states no [region_growing] settings: assuming the paper's (intensity ratio "
                           "0.5, 6 m, 6 dB floor); derive this radar's with `radarseg radar tune-growing PROFILE`",
                           profile.name)
        return cls(**{**stated, **overrides})

    def __post_init__(self) -> None:
        if not 0.0 <= self.intensity_ratio <= 1.0:
            raise ValueError(f"intensity_ratio must be in [0, 1], got {self.intensity_ratio}")
        if self.distance_m <= 0:
            raise ValueError(f"distance_m must be > 0, got {self.distance_m}")
        if int(self.bridge) != self.bridge or self.bridge < 0:
            raise ValueError(f"bridge must be a gap size in voxels >= 0 (True = 1), got {self.bridge}")
        object.__setattr__(self, "bridge", int(self.bridge))


@dataclass(frozen=True)
class Regions:
    """ROI voxels of one frame.

    ``voxels``: (N, 3) int64 (range, angle, Doppler) bins, sorted by flat index; ``seed_index``: (N,)
    the seed each voxel grew from (the first seed that reached it); ``seeds``: (S, 3) int64 seed
    voxels; ``visited``: voxels examined, accepted or not, counted once.
    """

    voxels: np.ndarray
    seed_index: np.ndarray
    seeds: np.ndarray
    visited: int
    shape: tuple[int, int, int]

    def __len__(self) -> int:
        return len(self.voxels)

    def mask(self) -> np.ndarray:
        """(R, A, D) bool cube of the ROI."""
        mask = np.zeros(self.shape, bool)
        mask[tuple(self.voxels.T)] = True
        return mask

    def recall(self, instances: np.ndarray) -> float:
        """Fraction of ground-truth object voxels (instances > 0) inside the ROI (1.0 if none)."""
        n_truth = int(np.count_nonzero(instances))
        if n_truth == 0:
            return 1.0
        return int(np.count_nonzero(instances[tuple(self.voxels.T)])) / n_truth


def dilate6(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """Binary dilation of a 3-D mask by the 6-connected cross, ``iterations`` times, zero outside the array:
    the same as ``ndimage.binary_dilation(mask, SIX_CONNECTED, iterations)`` in 6 shifted ORs per iteration,
    3-5x faster than scipy's general structuring-element loop on ROI boxes."""
    out = mask.copy()
    for iteration in range(iterations):
        previous = mask if iteration == 0 else out.copy()  # the input is left as it is: no copy the first time
        for axis in range(3):
            lead = [slice(None)] * 3
            lag = [slice(None)] * 3
            lead[axis], lag[axis] = slice(1, None), slice(None, -1)
            out[tuple(lead)] |= previous[tuple(lag)]
            out[tuple(lag)] |= previous[tuple(lead)]
    return out


def flood6(mask: np.ndarray, seed: tuple[int, int, int]) -> np.ndarray:
    """The 6-connected component of a 3-D bool ``mask`` holding ``seed`` (a voxel inside the mask).

    The same as ``skimage.segmentation.flood(mask, seed, connectivity=1)``, whose compiled fill it runs on an
    array padded here by one zero voxel, skipping the public wrapper's generic padding and border flags
    (3-4x its cost on ROI boxes). Returns a bool view of shape ``mask.shape``.
    """
    if not mask[seed]:
        raise ValueError(f"seed {seed} must lie inside the mask")
    padded = np.zeros(tuple(n + 2 for n in mask.shape), np.uint8)
    padded[1:-1, 1:-1, 1:-1] = mask
    return _flood_padded(padded, tuple(int(s) + 1 for s in seed))[1:-1, 1:-1, 1:-1].view(bool)


def _flood_padded(padded: np.ndarray, seed: tuple[int, int, int]) -> np.ndarray:
    """Fill flags (uint8, 1 = member, else 0) of the 6-connected ones of ``padded`` (C-contiguous uint8 0/1
    whose outermost voxels are all 0, so the fill never steps outside) holding ``seed`` (padded coordinates)."""
    _, n_angle, n_doppler = padded.shape
    offsets = np.array([-n_angle * n_doppler, -n_doppler, -1, 1, n_doppler, n_angle * n_doppler], np.intp)
    flags = np.zeros(padded.shape, np.uint8)
    start = (seed[0] * n_angle + seed[1]) * n_doppler + seed[2]
    _flood_fill_equal(padded.reshape(-1), flags.reshape(-1), offsets, start, np.uint8(1))
    return flags


def _seed_voxels(seeds: Centres | np.ndarray, log_power: np.ndarray, search: tuple[int, int, int]) -> np.ndarray:
    """Integer seed voxels (S, 3): each seed rounded, then moved to the brightest voxel near it (a
    predicted centre is the mean of an object's voxels and may fall between its scatterers)."""
    shape = np.array(log_power.shape)
    bins = seeds.bins if isinstance(seeds, Centres) else np.asarray(seeds, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(bins).all():
        raise ValueError("seeds must be finite (range, angle, Doppler) bins")
    voxels = np.rint(bins).astype(np.int64)
    voxels[:, 2] %= shape[2]  # Doppler wraps
    voxels = np.clip(voxels, 0, shape - 1)
    for i, centre in enumerate(voxels):
        lo = np.maximum(centre - search, 0)
        hi = np.minimum(centre + np.array(search) + 1, shape)
        window = log_power[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        voxels[i] = lo + np.unravel_index(np.argmax(window), window.shape)
    return voxels


def noise_level_db(log_power: np.ndarray, step: int = 31) -> float:
    """Median log power (dB) of a cube from every ``step``-th voxel: the frame's noise level."""
    return float(exact_median(log_power.reshape(-1)[::step]))


def exact_median(values: np.ndarray) -> np.floating:
    """``np.median`` of a 1-D float array, bit for bit, selected within a bracket instead of partitioning it all.

    A sorted probe of every 13th value brackets the median with 8 standard deviations of rank on either side;
    counting below the bracket and partitioning the ~8 % inside replaces the full partition (3-4x faster on
    the 135 k samples of a ``carrada`` cube). When the bracket misses (or NaNs are present) ``np.median`` decides.
    """
    n = len(values)
    if n < 32768:  # np.median is as fast below
        return np.median(values)
    values = np.ascontiguousarray(values)
    probe = np.sort(values[::13])  # a prime stride: no aliasing with power-of-two Doppler axes
    margin = 4 * int(np.sqrt(len(probe))) + 1  # the probe's median rank has a std of sqrt(len) / 2
    lo = probe[max(len(probe) // 2 - margin, 0)]
    hi = probe[min(len(probe) // 2 + margin, len(probe) - 1)]
    below = int(np.count_nonzero(values < lo))
    inside = values[(values >= lo) & (values <= hi)]
    above = int(np.count_nonzero(values > hi))
    first, last = (n - 1) // 2 - below, n // 2 - below  # np.median averages ranks (n-1)//2 and n//2
    if below + len(inside) + above != n or first < 0 or last >= len(inside):
        return np.median(values)
    chosen = np.partition(inside, [first, last])[first:last + 1]
    return np.mean(chosen)  # as np.median: the mean in the array's dtype


def grow_regions(log_power: np.ndarray, seeds: Centres | np.ndarray, profile: RadarProfile,
                 config: RegionGrowingConfig | None = None, *, noise_db: float | None = None) -> Regions:
    """ROI voxels grown from ``seeds`` ((S, 3) bins or :class:`Centres`) in a log-power cube (R, A, D).

    ``noise_db``: the level intensities are measured from (default :func:`noise_level_db`).
    """
    config = config or RegionGrowingConfig.for_profile(profile)
    if log_power.shape != profile.shape:
        raise ValueError(f"log-power cube must have shape {profile.shape}, got {log_power.shape}")
    if noise_db is None:
        noise_db = noise_level_db(log_power)
    shape = profile.shape
    n_angle, n_doppler = shape[1], shape[2]
    seed_voxels = _seed_voxels(seeds, log_power, config.seed_search)
    cart_x, cart_y = profile.ra_cartesian
    reach = int(np.ceil(config.distance_m / profile.range_res)) + 1
    # Whole-cube masks are allocated zeroed by the OS page by page: only the pages near the regions are touched.
    claimed = np.zeros(int(np.prod(shape)), bool)  # voxels owned by an earlier seed (the first to reach one keeps it)
    examined = np.zeros(shape, bool)  # visited voxels, counted once over all seeds
    n_visited = 0
    members, owners = [], []
    for i, (r0, a0, d0) in enumerate(seed_voxels):
        r_lo, r_hi = max(0, r0 - reach), min(shape[0], r0 + reach + 1)
        disc = ((cart_x[r_lo:r_hi] - cart_x[r0, a0]) ** 2 + (cart_y[r_lo:r_hi] - cart_y[r0, a0]) ** 2
                <= config.distance_m**2)  # (rows, A)
        cols = np.flatnonzero(disc.any(axis=0))
        a_lo, a_hi = max(0, cols.min() - 1), min(shape[1], cols.max() + 2)  # +1 margin for the dilation
        rows_any = np.flatnonzero(disc.any(axis=1))
        r_lo, r_hi = max(0, r_lo + rows_any.min() - 1), min(shape[0], r_lo + rows_any.max() + 2)
        disc = ((cart_x[r_lo:r_hi, a_lo:a_hi] - cart_x[r0, a0]) ** 2
                + (cart_y[r_lo:r_hi, a_lo:a_hi] - cart_y[r0, a0]) ** 2 <= config.distance_m**2)
        seed_db = log_power[r0, a0, d0] - noise_db
        if seed_db < config.min_snr_db:  # a seed in the noise grows nothing; only the seed is examined
            n_visited += not examined[r0, a0, d0]
            examined[r0, a0, d0] = True
            members.append((np.zeros(0, np.int64),) * 4)
            owners.append(np.zeros(0, np.int64))
            continue
        box = log_power[r_lo:r_hi, a_lo:a_hi]  # (rows, cols, D)
        threshold = noise_db + max(config.intensity_ratio * seed_db, config.min_snr_db)
        # Candidates in a box padded by one zero voxel: the compiled fill runs on it without bounds checks.
        candidates = np.zeros((r_hi - r_lo + 2, a_hi - a_lo + 2, n_doppler + 2), bool)
        inner = candidates[1:-1, 1:-1, 1:-1]
        np.greater_equal(box, threshold, out=inner)
        inner &= disc[:, :, None]
        seed_padded = (r0 - r_lo + 1, a0 - a_lo + 1, d0 + 1)
        if not candidates[seed_padded]:  # rounding put the seed just under its own threshold: skimage's flood
            region = _reference_flood(inner, config.bridge, disc, seed_padded)
        elif config.bridge:  # connect across gaps, then keep only real candidates
            linked = np.zeros_like(candidates)
            np.logical_and(dilate6(inner, config.bridge), disc[:, :, None], out=linked[1:-1, 1:-1, 1:-1])
            region = _flood_padded(linked.view(np.uint8), seed_padded).view(bool) & candidates
        else:
            region = _flood_padded(candidates.view(np.uint8), seed_padded).view(bool)
        # Members as flat indices of the cube, straight from the padded box's flat indices (sorted).
        padded_flat = np.flatnonzero(region)
        rows_cols, doppler = np.divmod(padded_flat, n_doppler + 2)
        rows, cols = np.divmod(rows_cols, a_hi - a_lo + 2)
        rows += r_lo - 1
        cols += a_lo - 1
        doppler -= 1
        flat = (rows * n_angle + cols) * n_doppler + doppler
        fresh = ~claimed[flat]
        claimed[flat] = True
        members.append((flat[fresh], rows[fresh], cols[fresh], doppler[fresh]))
        owners.append(np.full(int(np.count_nonzero(fresh)), i, np.int64))
        if len(flat) == 0:
            continue
        # Examined voxels = members and their 6-neighbours in the cube: a dilation on the members' bounding box.
        lo = np.maximum([rows[0] - 1, cols.min() - 1, doppler.min() - 1], [0, 0, 0])
        hi = np.minimum([rows[-1] + 2, cols.max() + 2, doppler.max() + 2], shape)
        near = dilate6(region[lo[0] - r_lo + 1:hi[0] - r_lo + 1, lo[1] - a_lo + 1:hi[1] - a_lo + 1,
                              lo[2] + 1:hi[2] + 1])
        seen = examined[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        n_visited += int(np.count_nonzero(near)) - int(np.count_nonzero(near & seen))
        seen |= near
    return _regions_in_cube_order(members, owners, seed_voxels, n_visited, shape)


def _regions_in_cube_order(members: list, owners: list, seed_voxels: np.ndarray, n_visited: int,
                           shape: tuple[int, int, int]) -> Regions:
    """The seeds' member runs ((flat, range, angle, Doppler) per seed) merged into one voxel list in flat cube
    order, each voxel with the index of the seed that claimed it."""
    if not members:
        return Regions(np.zeros((0, 3), np.int64), np.zeros(0, np.int64), seed_voxels, 0, shape)
    flat, *coordinates = (np.concatenate(parts) for parts in zip(*members, strict=True))
    seed_index = np.concatenate(owners)
    voxels = np.empty((len(flat), 3), np.int64)
    if np.all(flat[1:] > flat[:-1]):  # the seeds' runs already follow each other
        for axis, values in enumerate(coordinates):
            voxels[:, axis] = values
        return Regions(voxels, seed_index, seed_voxels, n_visited, shape)
    order = np.argsort(flat, kind="stable")  # each seed's indices are one sorted run: a merge of S runs
    for axis, values in enumerate(coordinates):
        np.take(values, order, out=voxels[:, axis])
    return Regions(voxels, seed_index[order], seed_voxels, n_visited, shape)


def _reference_flood(inner: np.ndarray, bridge: int, disc: np.ndarray, seed_padded: tuple[int, int, int]) -> np.ndarray:
    """The original per-seed step for a seed that is not a candidate (skimage floods the seed's value, False):
    the region in padded coordinates."""
    seed = tuple(s - 1 for s in seed_padded)
    if bridge:
        local = flood(dilate6(inner, bridge) & disc[:, :, None], seed, connectivity=1) & inner
    else:
        local = flood(inner, seed, connectivity=1)
    region = np.zeros(tuple(n + 2 for n in inner.shape), bool)
    region[1:-1, 1:-1, 1:-1] = local
    return region
