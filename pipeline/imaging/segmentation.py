"""Foreground masks of the specimen: from a background plate or by GrabCut.

The automatic segmenters differ in what they take for the set:

- ``segment_neutral_backdrop``: anything grey, white or black; for a handheld capture
  (its borders show the room from every side, so no colour along them need be the
  set's) and a capture on the printed board (whose black and white turn with the
  specimen);
- ``FixedSet.segment``: the colours along the borders of most photos of one fixed
  set (``SetColours``), whatever they are: a turntable's blue backdrop, a ring's black
  cloth, and, for a camera that does not move, pixels that stay as they are while the
  specimen turns (``still_pixels``): the room behind a turntable;
- ``segment_centre_prior``: whatever GrabCut separates from the image border.

Used by the masks stage and by ``pipeline check`` (which looks at mask coverage
before the expensive stages run).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from pipeline import logger
from pipeline.imaging.photo_io import read_photo, srgb_encode

SHADOW_CHROMA_CHANGE = 0.03
"""A shadow darkens the set without changing its colour by more than this (chroma units)."""


def _working_copy(image: np.ndarray, working_size: int) -> np.ndarray:
    """``image`` resized so that its longer side is ``working_size``.

    Small photos are enlarged too: GrabCut's boundary is pixel-exact at the working
    size, so segmenting a 128-pixel photo at 400 pixels places its edges to a third
    of a photo pixel.
    """
    factor = working_size / max(image.shape[:2])
    if abs(factor - 1) < 1e-3:
        return image
    size = (max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)


def _photo_size(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if mask.shape == shape:
        return mask
    shrinking = mask.shape[0] > shape[0]
    soft = cv2.resize(
        mask.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    )
    return soft >= 0.5


def grabcut(image: np.ndarray, seeds: np.ndarray, iterations: int) -> np.ndarray:
    """GrabCut on an 8-bit RGB image from a seed map of cv2.GC_* labels; True = foreground."""
    labels = seeds.astype(np.uint8).copy()
    foreground = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if foreground.all() or not foreground.any():  # GrabCut needs samples of both
        return foreground
    background_model, foreground_model = np.zeros((1, 65)), np.zeros((1, 65))
    # GrabCut seeds its colour models by k-means from OpenCV's global random state:
    # without a fixed seed a mask depends on what the process did before.
    cv2.setRNGSeed(0)
    cv2.grabCut(image, labels, None, background_model, foreground_model, iterations, cv2.GC_INIT_WITH_MASK)
    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def centre_prior_seeds(shape: tuple[int, int], centre_fraction: float) -> np.ndarray:
    """Probably foreground inside a centred box covering ``centre_fraction`` of each side,
    surely background along a thin frame at the border, probably background between."""
    height, width = shape
    seeds = np.full(shape, cv2.GC_PR_BGD, np.uint8)
    border = max(1, round(0.02 * max(shape)))
    seeds[:border], seeds[-border:], seeds[:, :border], seeds[:, -border:] = (cv2.GC_BGD,) * 4
    margin_y, margin_x = round(height * (1 - centre_fraction) / 2), round(width * (1 - centre_fraction) / 2)
    seeds[margin_y : height - margin_y, margin_x : width - margin_x] = cv2.GC_PR_FGD
    return seeds


def segment_centre_prior(srgb: np.ndarray, centre_fraction: float, iterations: int, working_size: int) -> np.ndarray:
    """The object near the image centre, separated from the rest by GrabCut's colour models."""
    small = _working_copy(srgb, working_size)
    mask = grabcut(small, centre_prior_seeds(small.shape[:2], centre_fraction), iterations)
    return _photo_size(mask, srgb.shape[:2])


def chroma(srgb: np.ndarray) -> np.ndarray:
    """Colourfulness in [0, 1]: spread of the (slightly blurred) 8-bit sRGB channels.

    Measured on encoded values, where sensor noise in dark pixels stays small,
    unlike ratios of linear values.
    """
    blurred = cv2.GaussianBlur(srgb.astype(np.float32), (0, 0), 1.0)
    return (blurred.max(axis=-1) - blurred.min(axis=-1)) / 255.0


def segment_neutral_backdrop(
    srgb: np.ndarray, backdrop_chroma: float, centre_fraction: float, iterations: int, working_size: int
) -> np.ndarray:
    """The specimen on a grey, white or black set (table, sweep, printed board).

    Pixels greyer than ``backdrop_chroma`` are backdrop for sure, up to twice that
    probably; pixels three times as colourful are specimen for sure. The centre
    prior and GrabCut's colour models decide the rest, which is what lets a grey
    highlight on the specimen stay foreground.
    """
    small = _working_copy(srgb, working_size)
    colourfulness = chroma(small)
    seeds = centre_prior_seeds(small.shape[:2], centre_fraction)
    inside = seeds == cv2.GC_PR_FGD
    seeds[inside & (colourfulness < 2 * backdrop_chroma)] = cv2.GC_PR_BGD
    seeds[colourfulness < backdrop_chroma] = cv2.GC_BGD
    seeds[inside & (colourfulness > 3 * backdrop_chroma)] = cv2.GC_FGD
    return _photo_size(grabcut(small, seeds, iterations), srgb.shape[:2])


LIGHTNESS_WEIGHT = 0.4
"""Weight of CIELAB lightness against the two colour axes in distances between colours:
the set's own shading (a shadow, a lit patch of the table) changes its lightness much more
than its hue."""

SET_COLOUR_CLUSTERS = 8
"""Colours (k-means clusters) the border pixels of a capture are sorted into."""

MIN_BORDER_PRESENCE = 0.5
"""A border colour is the set's only when at least this fraction of the photos show it
along their border (at least 1 % of that photo's border pixels): the set frames every
photo, a specimen cut off by the frame only some."""

COLOUR_NOISE_FLOOR = 2.0
"""Smallest colour distance (weighted CIELAB units) taken as noise: about the least
difference the eye sees."""


def _weighted_lab(srgb: np.ndarray) -> np.ndarray:
    lab = cv2.cvtColor(srgb.astype(np.float32) / 255.0, cv2.COLOR_RGB2Lab)
    lab[..., 0] *= LIGHTNESS_WEIGHT
    return lab


def _srgb_of(weighted_lab: np.ndarray) -> np.ndarray:
    """The 8-bit-scale sRGB colour (floats) of a weighted CIELAB colour."""
    lab = np.array(weighted_lab, np.float32).reshape(1, 1, 3)
    lab[..., 0] /= LIGHTNESS_WEIGHT
    return np.clip(cv2.cvtColor(lab, cv2.COLOR_Lab2RGB)[0, 0] * 255.0, 0.0, 255.0)


def _border(shape: tuple[int, int]) -> np.ndarray:
    """A frame 3 % of the longer side wide (at least 2 px) along the image border."""
    width = max(2, round(0.03 * max(shape)))
    frame = np.zeros(shape, bool)
    frame[:width], frame[-width:], frame[:, :width], frame[:, -width:] = (True,) * 4
    return frame


@dataclass(frozen=True)
class SetColours:
    """The colours of a fixed set (backdrop, table, stand), learned from the borders of
    its photos; ``distance`` says how far a pixel is from all of them, in units of
    ``noise`` (the spread of the set's own border pixels about their colours)."""

    colours: np.ndarray
    """Weighted CIELAB colours of the set (n x 3)."""
    noise: float
    """95th percentile of the set's border pixels' distance to their colour, at least
    ``COLOUR_NOISE_FLOOR``."""

    @classmethod
    def learn(cls, photos: list[np.ndarray], samples_per_photo: int = 2000) -> SetColours:
        """From 8-bit RGB ``photos`` of one set (working copies): their border pixels
        sorted into ``SET_COLOUR_CLUSTERS`` colours, of which those along the borders of
        most photos are kept."""
        rng = np.random.default_rng(0)
        pixels, owner = [], []
        for index, photo in enumerate(photos):
            border = _weighted_lab(photo)[_border(photo.shape[:2])]
            chosen = rng.choice(len(border), min(samples_per_photo, len(border)), replace=False)
            pixels.append(border[chosen])
            owner.append(np.full(len(chosen), index))
        pixels_all, owner_all = np.concatenate(pixels).astype(np.float32), np.concatenate(owner)
        clusters = min(SET_COLOUR_CLUSTERS, len(pixels_all))
        cv2.setRNGSeed(0)  # k-means++ draws from OpenCV's global random state
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.1)
        _, labels, centres = cv2.kmeans(pixels_all, clusters, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
        labels = labels.ravel()
        shares = np.array([np.bincount(labels[owner_all == i], minlength=clusters) for i in range(len(photos))])
        shares = shares / np.maximum(shares.sum(axis=1, keepdims=True), 1)
        presence = (shares >= 0.01).mean(axis=0)
        kept = np.flatnonzero(presence >= MIN_BORDER_PRESENCE)
        if len(kept) == 0:  # no colour frames most photos: the commonest one
            kept = np.array([int(np.argmax(presence))])
        members = pixels_all[np.isin(labels, kept)]
        spread = np.min(np.linalg.norm(members[:, None] - centres[kept][None], axis=-1), axis=1)
        return cls(centres[kept], max(float(np.quantile(spread, 0.95)), COLOUR_NOISE_FLOOR))

    def distance(self, srgb: np.ndarray, hue_only: bool = False) -> np.ndarray:
        """Each pixel's distance to the nearest set colour, in units of ``noise``;
        ``hue_only``: lightness left out (a shadow on the set is near its colour)."""
        first = 1 if hue_only else 0
        lab = _weighted_lab(srgb).reshape(-1, 1, 3)[..., first:]
        nearest = np.full(lab.shape[0], np.inf, np.float32)
        for colour in self.colours[:, first:]:  # one colour at a time: memory stays one image
            nearest = np.minimum(nearest, np.linalg.norm(lab[:, 0] - colour, axis=-1))
        return (nearest / self.noise).reshape(srgb.shape[:2])

    def in_shade(self, srgb: np.ndarray) -> np.ndarray:
        """Pixels that are one of these colours in shade: within three noise units of the
        colour dimmed to the pixel's brightness (every sRGB channel scaled alike, as less
        light scales them), and farther than three from the colour itself."""
        pixels = srgb.astype(np.float32)
        lab = _weighted_lab(srgb)
        shaded = np.zeros(srgb.shape[:2], bool)
        for colour in self.colours:
            lit = _srgb_of(colour)
            scale = np.clip(pixels.sum(axis=-1) / max(float(lit.sum()), 1.0), 0.0, 1.0)
            dimmed = _weighted_lab(scale[..., None] * lit)
            near_dimmed = np.linalg.norm(lab - dimmed, axis=-1) <= 3 * self.noise
            shaded |= near_dimmed & (np.linalg.norm(dimmed - colour, axis=-1) > 3 * self.noise)
        return shaded


def still_pixels(grey: np.ndarray) -> np.ndarray:
    """For a stack of 8-bit grey photos from a camera that did not move (n x h x w): the
    pixels of each that differ from the stack's median by less than 4 noise sigmas (noise
    from the median absolute difference, most of which is the still set), blurred over
    2 px so that sensor noise does not speckle the result."""
    stack = grey.astype(np.float32)
    difference = np.abs(stack - np.median(stack, axis=0))
    noise = max(1.4826 * float(np.median(difference)), 1.0)
    return np.stack([cv2.GaussianBlur(d, (0, 0), 2.0) < 4 * noise for d in difference])


ALWAYS_STILL = 0.9
"""A pixel still in at least this fraction of a fixed camera's photos is the set for
sure (the room); one still less often may be a plain specimen's middle, which looks
alike from every side, and is left to GrabCut."""


def _solid(pixels: np.ndarray) -> np.ndarray:
    """``pixels`` without lines a pixel or two thin: a set's edge that shifts by a pixel
    between photos (a table wobbling as it turns) is not still, yet it is no specimen but
    a blend of two set colours."""
    return cv2.morphologyEx(pixels.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0


def _colours_of(lab: np.ndarray, noise: float, min_share: float = 0.0) -> SetColours | None:
    """Weighted CIELAB pixels (m x 3) sorted into ``SET_COLOUR_CLUSTERS`` colours with
    the given noise, those of fewer than ``min_share`` of the pixels left out; None for
    too few pixels."""
    if len(lab) < SET_COLOUR_CLUSTERS:
        return None
    cv2.setRNGSeed(0)  # k-means++ draws from OpenCV's global random state
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.1)
    _, labels, colours = cv2.kmeans(
        lab.astype(np.float32), SET_COLOUR_CLUSTERS, None, criteria, 1, cv2.KMEANS_PP_CENTERS
    )
    shares = np.bincount(labels.ravel(), minlength=SET_COLOUR_CLUSTERS) / len(lab)
    return SetColours(colours[shares >= min_share], noise)


SPECIMEN_PLATE_MIN_SHARE = 0.05
"""Least share of the specimen's changed pixels a colour must have to be the colour of
where it stands most of the time (a large plain part); rarer colours are mostly the set's
edges caught moving."""


def specimen_plate(small: list[np.ndarray], still: np.ndarray, colours: SetColours) -> np.ndarray:
    """Pixels where a fixed camera's photos (8-bit RGB working copies; ``still``: each
    one's still pixels) show the specimen most of the time.

    There (the specimen's foot on the turntable's axis, a plain body that looks alike
    from every side) the photos' median is the specimen, so the specimen's pixels stay
    as they are and the set's, when it shows, change: stillness and change say the
    opposite of what they say elsewhere. Such a median is unlike every set colour's hue
    (a shadow the specimen casts in every photo darkens the set and keeps its hue) and
    like the specimen's colours, learned where change does mean the specimen: pixels
    that changed where the median is the set, and are unlike the set themselves. Pixels
    still in nearly every photo (``ALWAYS_STILL``) are the room for sure and left out.
    """
    stack = np.stack(small)  # one channel at a time: np.median works in float64
    median = np.dstack([np.median(stack[..., c], axis=0) for c in range(3)]).astype(np.uint8)
    set_median = colours.distance(median, hue_only=True) <= 3
    rng = np.random.default_rng(0)
    passing = []
    for photo, photo_still in zip(small, still, strict=True):
        known = _weighted_lab(photo)[_solid(~photo_still & set_median & (colours.distance(photo) > 3))]
        passing.append(known[rng.choice(len(known), min(2000, len(known)), replace=False)])
    specimen = _colours_of(np.concatenate(passing), colours.noise, SPECIMEN_PLATE_MIN_SHARE)
    if specimen is None:
        return np.zeros(median.shape[:2], bool)
    return (still.mean(axis=0) < ALWAYS_STILL) & ~set_median & (specimen.distance(median) <= 3)


@dataclass(frozen=True)
class FixedSet:
    """What the photos of one fixed set (a turntable's or a ring's) show of the set: its
    colours, and for a camera that did not move, each photo's still pixels and where the
    specimen shows most of the time."""

    colours: SetColours
    still: np.ndarray | None
    """Each photo's still pixels at the working size (n x h x w; ``still_pixels``), or
    None for a camera that moved."""
    always_still: np.ndarray | None
    """Pixels still in at least ``ALWAYS_STILL`` of the photos."""
    specimen_plate: np.ndarray | None
    """Pixels the photos show the specimen in most of the time (``specimen_plate``)."""

    @classmethod
    def learn(cls, photos: Iterable[np.ndarray], working_size: int, camera_fixed: bool) -> FixedSet:
        """From the 8-bit RGB photos of one camera setting, in the order ``segment``'s
        ``index`` counts them (an iterable: each is cut to the working size as it comes,
        so that a generator never holds more than one full photo); ``camera_fixed``: a
        turntable's (the specimen turns, the set and the camera stay), not a ring's."""
        small = [_working_copy(photo, working_size) for photo in photos]
        colours = SetColours.learn(small)
        if not camera_fixed or len({s.shape for s in small}) > 1:
            return cls(colours, None, None, None)
        still = still_pixels(np.stack([cv2.cvtColor(s, cv2.COLOR_RGB2GRAY) for s in small]))
        return cls(colours, still, still.mean(axis=0) >= ALWAYS_STILL, specimen_plate(small, still, colours))

    def segment(self, srgb: np.ndarray, index: int, centre_fraction: float, iterations: int, working_size: int):
        """The specimen in photo ``index`` (8-bit RGB).

        Within the noise of a set colour is backdrop for sure, up to twice that probably;
        three times as far (inside the centre prior) is specimen for sure, unless the
        pixel is still, which makes it probably backdrop, or backdrop for sure where it
        is still in nearly every photo or unlike the specimen. Where the photos show the
        specimen most of the time (``specimen_plate``) the roles swap: a still pixel as
        far from the set is specimen for sure, a changed one is left to GrabCut, which
        decides the rest.
        """
        small = _working_copy(srgb, working_size)
        distance = self.colours.distance(small)
        seeds = centre_prior_seeds(small.shape[:2], centre_fraction)
        inside = seeds == cv2.GC_PR_FGD
        seeds[inside & (distance < 2)] = cv2.GC_PR_BGD
        if self.still is not None:
            still, plate = self.still[index], self.specimen_plate
            says_specimen = np.where(plate, still, ~still)
            seeds[inside & (distance > 3) & says_specimen] = cv2.GC_FGD
            set_still = still & ~plate
            seeds[set_still] = cv2.GC_PR_BGD
            seeds[set_still & (self.always_still | self._unlike_specimen(small, seeds == cv2.GC_FGD))] = cv2.GC_BGD
        else:
            seeds[inside & (distance > 3)] = cv2.GC_FGD
        seeds[self._shadow(small, seeds == cv2.GC_FGD)] = cv2.GC_PR_BGD
        seeds[distance < 1] = cv2.GC_BGD
        return _photo_size(grabcut(small, seeds, iterations), srgb.shape[:2])

    def _shadow(self, small: np.ndarray, specimen: np.ndarray) -> np.ndarray:
        """Sure specimen pixels (``specimen``) that are the specimen's shadow on the set: a
        set colour in shade (``SetColours.in_shade``) and no colour of the rest of the
        photo's sure specimen in shade, those colours learned 2 px inside it (an outline
        blends the specimen's colour with the set's) and a colour of under
        ``SPECIMEN_PLATE_MIN_SHARE`` of it (a highlight) left out. A shadow changes from
        photo to photo as the specimen turns and is far from the set's colours, so it
        would be seeded as specimen; a specimen whose shade is also the set's (grey on
        grey) keeps it."""
        shaded = specimen & self.colours.in_shade(small)
        rest = cv2.erode((specimen & ~shaded).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        known = _colours_of(_weighted_lab(small)[rest], self.colours.noise, SPECIMEN_PLATE_MIN_SHARE)
        if known is None:
            return np.zeros(small.shape[:2], bool)
        return shaded & ~known.in_shade(small) & (known.distance(small) > 3)

    def _unlike_specimen(self, small: np.ndarray, specimen: np.ndarray) -> np.ndarray:
        """Pixels farther than three noise units from every colour of ``specimen`` (the
        photo's sure specimen pixels, thin lines left out, sorted into a few colours): a
        still pixel of such a colour is the room, even beside the specimen, where the
        smoothness of GrabCut's cut would take it in."""
        known = _colours_of(_weighted_lab(small)[_solid(specimen)], self.colours.noise)
        return known.distance(small) > 3 if known is not None else np.zeros(small.shape[:2], bool)


def segment_plate_difference(
    linear: np.ndarray,
    plate: np.ndarray,
    threshold: float,
    iterations: int,
    working_size: int,
    shadows_are_background: bool = True,
) -> np.ndarray:
    """Pixels that differ from the empty-set plate by more than ``threshold`` noise sigmas.

    The noise sigma is estimated robustly (median absolute deviation) from the
    difference itself, most of which is background. A darker pixel whose colour
    did not change is the specimen's shadow on the set, not the specimen (unless
    ``shadows_are_background`` is off, for dark grey specimens on a light set).
    GrabCut then settles the uncertain band.
    """
    small, small_plate = _working_copy(linear, working_size), _working_copy(plate, working_size)
    root, plate_root = np.sqrt(np.clip(small, 0, None)), np.sqrt(np.clip(small_plate, 0, None))
    difference = np.linalg.norm(root - plate_root, axis=-1)
    sigma = 1.4826 * np.median(np.abs(difference - np.median(difference))) + 1e-6
    seeds = np.full(difference.shape, cv2.GC_PR_BGD, np.uint8)
    seeds[difference > threshold * sigma] = cv2.GC_PR_FGD
    seeds[difference > 3 * threshold * sigma] = cv2.GC_FGD
    srgb = np.round(srgb_encode(small) * 255).astype(np.uint8)
    if shadows_are_background:
        plate_srgb = np.round(srgb_encode(small_plate) * 255).astype(np.uint8)
        darker = root.mean(axis=-1) < plate_root.mean(axis=-1)
        same_colour = np.abs(chroma(srgb) - chroma(plate_srgb)) < SHADOW_CHROMA_CHANGE
        seeds[darker & same_colour] = cv2.GC_BGD
    seeds[difference < sigma] = cv2.GC_BGD
    mask = grabcut(srgb, seeds, iterations) if iterations else seeds % 2 == 1
    return _photo_size(mask, linear.shape[:2])


def clean(mask: np.ndarray, min_component_fraction: float, max_hole_fraction: float) -> np.ndarray:
    """Keep components at least ``min_component_fraction`` of the largest; fill the
    holes smaller than ``max_hole_fraction`` of the silhouette's area (specimen pixels
    taken for backdrop), keep larger ones open (the backdrop seen through a colonnade
    or a handle, which the visual hull must carve)."""
    labels, count = ndimage.label(mask)
    if count == 0:
        return mask
    sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, count + 1))
    keep = np.flatnonzero(sizes >= min_component_fraction * sizes.max()) + 1
    mask = np.isin(labels, keep)
    holes, count = ndimage.label(ndimage.binary_fill_holes(mask) & ~mask)
    if count == 0:
        return mask
    hole_sizes = ndimage.sum_labels(np.ones_like(mask), holes, index=np.arange(1, count + 1))
    small = np.flatnonzero(hole_sizes < max_hole_fraction * (mask.sum() + hole_sizes.sum())) + 1
    return mask | np.isin(holes, small)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def read_user_mask(path: Path) -> np.ndarray:
    """A user's mask as booleans: any nonzero value is specimen (read as linear so that
    8-bit 255 is 1.0 and label images with small values count too)."""
    return read_photo(path, "linear").pixels[..., 0] > 0.5 / 255


def on_mask(mask_path: Path, pixels: np.ndarray) -> np.ndarray:
    """Whether each pixel (x, y) lies on the mask's foreground (outside the photo: no)."""
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) > 127
    x, y = np.round(pixels[:, 0]).astype(int), np.round(pixels[:, 1]).astype(int)
    within = (x >= 0) & (y >= 0) & (x < mask.shape[1]) & (y < mask.shape[0])
    return within & mask[np.clip(y, 0, mask.shape[0] - 1), np.clip(x, 0, mask.shape[1] - 1)]


def learn_fixed_sets(
    settings: Iterable[tuple[list[str], Iterable[np.ndarray]]], working_size: int, camera_fixed: bool
) -> dict[str, tuple[FixedSet, int]]:
    """set_colours: for each camera setting (its photos' names, and their 8-bit RGB
    pixels in that order) the set learned from all its photos; by photo name, the set and
    the photo's index among them, as ``segment`` takes them."""
    fixed_sets = {}
    for names, photos in settings:
        learned = FixedSet.learn(photos, working_size, camera_fixed)
        logger.info(
            "%d photos: %d set colours (noise %.1f)%s",
            len(names),
            len(learned.colours.colours),
            learned.colours.noise,
            ", still pixels of the fixed camera" if learned.still is not None else "",
        )
        fixed_sets |= {name: (learned, index) for index, name in enumerate(names)}
    return fixed_sets


def resolve_segmenter(segmenter: str, rig: str, board_in_photos: Callable[[], bool]) -> str:
    """``auto``: set_colours for a turntable or ring without the printed board in its
    photos, whose photos one fixed set frames; neutral_backdrop for a handheld capture
    (its borders show the room from every side) and for a capture on the board, whose
    black and white turn with the specimen (neither along the border nor still) and which
    the capture checklist puts on a neutral set. ``board_in_photos`` is asked only for
    a turntable or ring: a board in capture.toml may have been shot for calibration only,
    off the set, and finding it costs a detection per photo."""
    if segmenter != "auto":
        return segmenter
    if rig not in ("turntable", "ring"):
        return "neutral_backdrop"
    return "neutral_backdrop" if board_in_photos() else "set_colours"


OUTLINE_MIN_CONTRAST = 12.0
"""Least difference (8-bit levels, RGB distance) between the specimen's and the set's
colours beside an outline pixel for ``snap_outline`` to re-decide it: with sensor noise of
a few levels, a pixel's share of each is then known to about a quarter."""

OUTLINE_MAX_OFF_LINE = 0.2
"""Largest distance of an outline pixel's colour from the line between the local
specimen's and set's colours, as a fraction of their difference, for ``snap_outline`` to
re-decide it: farther, the pixel is no blend of the two (a shaded rim, a texture)."""


def snap_outline(srgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``mask`` with the pixels on either side of its outline re-decided by their colour.

    A segmenter's cut is a pixel or so off the outline, mostly outward: the photo's blur
    mixes the specimen's colour into the set's over a pixel or two, and a pixel that is
    mostly set but far from its colour is taken in. Each outline pixel's colour is
    projected onto the line between the local specimen's (the mask's pixels 2-4 px
    inside) and the local set's (2-4 px outside); it is specimen where it is at least
    half-way, as the outline of a sharp photo would be. Pixels where the two differ by
    less than ``OUTLINE_MIN_CONTRAST``, or whose colour is no blend of them
    (``OUTLINE_MAX_OFF_LINE``), keep their label.

    Limitations: a textured or shaded specimen's colour 2-4 px inside is not always the
    colour at its outline; on such a specimen on the printed board the masks came out
    slightly worse, so only the set_colours segmenter snaps (docs/decisions.md, "Masks").
    """
    image = srgb.astype(np.float32)
    blurred = cv2.GaussianBlur(image, (0, 0), 0.7)
    labels = mask.astype(np.uint8)

    def local_mean(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        weight = cv2.boxFilter(pixels.astype(np.float32), -1, (9, 9), normalize=False)
        total = cv2.boxFilter(blurred * pixels[..., None], -1, (9, 9), normalize=False)
        return total / np.maximum(weight, 1e-6)[..., None], weight > 0

    specimen, has_specimen = local_mean(cv2.erode(labels, np.ones((5, 5), np.uint8)) > 0)
    backdrop, has_backdrop = local_mean(~(cv2.dilate(labels, np.ones((5, 5), np.uint8)) > 0))
    outline = (cv2.dilate(labels, np.ones((3, 3), np.uint8)) > 0) & ~(cv2.erode(labels, np.ones((3, 3), np.uint8)) > 0)
    contrast = specimen - backdrop
    squared = np.sum(contrast * contrast, axis=-1)
    share = np.sum((image - backdrop) * contrast, axis=-1) / np.maximum(squared, 1e-6)
    off_line = np.linalg.norm(image - backdrop - share[..., None] * contrast, axis=-1)
    decided = outline & has_specimen & has_backdrop & (squared > OUTLINE_MIN_CONTRAST**2)
    decided &= off_line <= OUTLINE_MAX_OFF_LINE * np.sqrt(squared)
    snapped = mask.copy()
    snapped[decided] = share[decided] >= 0.5
    return snapped


def segment(
    srgb: np.ndarray,
    segmenter: str,
    backdrop_chroma: float,
    centre_fraction: float,
    grabcut_iterations: int,
    working_size: int,
    fixed_set: tuple[FixedSet, int] | None = None,
) -> np.ndarray:
    """The automatic segmenter ``segmenter`` (resolved: not auto) on an 8-bit RGB photo,
    before cleaning; set_colours needs ``fixed_set``: the set learned from the photo's
    camera setting and the photo's index among them, and its outline is snapped to the
    photo (``snap_outline``)."""
    if segmenter == "neutral_backdrop":
        return segment_neutral_backdrop(srgb, backdrop_chroma, centre_fraction, grabcut_iterations, working_size)
    if segmenter == "set_colours":
        learned, index = fixed_set
        return snap_outline(srgb, learned.segment(srgb, index, centre_fraction, grabcut_iterations, working_size))
    return segment_centre_prior(srgb, centre_fraction, grabcut_iterations, working_size)
