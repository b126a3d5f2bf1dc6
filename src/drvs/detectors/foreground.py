"""``foreground``: anything on the floor that is not the empty floor.

Two cues, combined per pixel:

- Motion: a per-camera background model (OpenCV's MOG2 subtractor, shadow detection on and
  shadows dropped) learns from every frame (`observe`), so things that move are found at once;
  things that stop fade into that model after a while.
- The empty floor: when the camera's configuration names a picture of it (``background:
  empty.png``, taken with ``drvs-camera snapshot``), every frame is compared with that picture,
  so things that never move are found too.

Lighting: each frame is first scaled by one global gain (the median brightness ratio between the
frame and the picture, or the first frame when there is none), so a slow change of the building's
light moves nothing. What is left is compared colour vector by colour vector in the way shadow
detectors do (Horprasert et al. 1999): a pixel is a *shadow* (not an object) when its colour points
the same way as the floor's (chromaticity distortion small) and it is darker, down to
`SHADOW_MIN_BRIGHTNESS` of the floor's brightness; it is an *object* when its colour points
elsewhere, or it is brighter than the floor, or darker than any shadow. Where the picture has
texture, a patch whose texture no longer correlates with the picture's and has faded is an object
too (a shadow or a change of light scales texture, an object hides it). The price: on a floor
without texture, an object of exactly the floor's hue and a little darker is a shadow to this
detector while it stands still.

The floor's own edges: a printed marker, tape and tile joints in the picture never come back at
quite the same pixels (sub-pixel jitter between frames, JPEG ringing, noise), so where the picture
has strong gradients a pixel that differs from it by no more than the source's own frame-to-frame
noise there (learnt per pixel from the first frames observed) is floor, for every cue (see
GRADIENT_MIN). So is a pixel the sensor clipped where the picture, in this light, would clip too.

All the pixel work runs at a reduced scale (at most `WORK_WIDTH` pixels wide); outlines are traced
on the mask brought back to the frame's size.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from drvs.core.errors import FailedPrecondition, InvalidArgument
from drvs.core.model import Detection
from drvs.core.object_types import FOREGROUND, parse_foreground

from .base import CameraView, Detector, Frame, FrameAnalysis, ObjectType, register

#: Pixel work happens on frames scaled down to at most this width (640x480 -> 320x240).
WORK_WIDTH = 320
#: The motion model's memory in frames (MOG2's history): after its first WARMUP_FRAMES it learns
#: at 1/HISTORY_FRAMES a frame, so a thing that stops fades into it after some 50 frames (MOG2's
#: default, 1/frames seen, would absorb a slow object's own pixels within a few frames of a start).
HISTORY_FRAMES = 500
#: MOG2's squared Mahalanobis distance for a pixel to match its model (OpenCV's default is 16).
VAR_THRESHOLD = 25.0
#: Frames the motion model must have seen before its mask counts (its first frames are all new).
WARMUP_FRAMES = 5
#: A pixel whose colour direction departs from the floor's by more than this (the tangent of the
#: angle between the two colour vectors) is not floor, whatever its brightness. Sensor noise of
#: sigma 3 grey levels (also MJPG-compressed, also halved by a shadow) reaches 0.03 at the working
#: scale; real shadows on grass under a blue sky shift it by 0.04-0.09 (vtest.avi), so some of
#: those become objects, and an object whose colour is within 0.06 of the floor's is found only
#: when it is brighter or far darker than the floor.
CHROMA_THRESHOLD = 0.06
#: Brightness relative to the floor (after the global gain): above HIGH is an object (a shadow
#: never brightens; noise moves it 2 %), below SHADOW_MIN_BRIGHTNESS is darker than any shadow
#: (also MOG2's shadow threshold).
BRIGHTNESS_HIGH = 1.15
SHADOW_MIN_BRIGHTNESS = 0.35
#: A working pixel with a channel at this level or above is clipped by the sensor (after the 3x3
#: median filter and the scaling down, a clipped patch still reads 255).
CLIP_LEVEL = 250
#: Where the empty floor's picture has texture (local standard deviation of grey, in TEXTURE_PX
#: windows at the working scale, above TEXTURE_MIN_STD grey levels: well above sensor noise there),
#: a frame whose texture no longer correlates with it (normalised cross-correlation below
#: TEXTURE_MIN_CORRELATION) and has faded shows an object, even one of the floor's colour: a shadow
#: or a change of light scales the texture but keeps it.
TEXTURE_PX = 5
TEXTURE_MIN_STD = 4.0
TEXTURE_MIN_CORRELATION = 0.4
#: ... and whose texture has faded to below this fraction of the floor's contrast (std / mean).
TEXTURE_FADED = 0.7
#: Cleaning, in working pixels: openings remove speckle (a 2x2 one keeps a robot 15 m away, 4
#: pixels thick in the frame), closings join an object's parts.
OPEN_PX = 2
CLOSE_PX = 5
#: The floor's own high-contrast features (marker and tape edges, tile joints) in the empty floor's
#: picture: where its gradient (the largest of the channels', grey levels per working pixel,
#: Scharr's, dilated by a pixel since edges move) is above GRADIENT_MIN, a frame may differ from
#: the picture by the source's own frame-to-frame noise there and still be floor: sub-pixel jitter
#: between frames, JPEG ringing, sensor noise, and a thin joint the median filter half erases in one
#: frame and not the next all change an edge's pixels by far more than the flat floor's. The noise
#: is learnt per pixel and channel from the first NOISE_FRAMES frames observed: the NOISE_QUANTILE
#: of the absolute differences between consecutive frames (lighting gain taken out), as a normal
#: sigma; a pixel is floor when every channel is within NOISE_K sigmas of the picture. A high
#: quantile, not the median: the large jitters are rare, and a thing that crosses the view while
#: the noise is learnt raises the tolerance only on the floor's edges, where it applies. Before
#: that, and as the least it may be after, it is assumed from the picture: sensor noise of
#: PRIOR_NOISE grey levels, and edges moving by PRIOR_JITTER_PX working pixels.
GRADIENT_MIN = 6.0
NOISE_FRAMES = 16
NOISE_QUANTILE = 0.9
NOISE_K = 4.0
PRIOR_NOISE = 3.0
PRIOR_JITTER_PX = 0.25
#: The NOISE_QUANTILE of a normal variable's absolute value, in sigmas.
_QUANTILE_SIGMAS = 1.645
#: Frames whose motion masks are kept for requests that ask about them a little later.
MASK_CACHE = 4
#: Sums a float image's three channels (cv2.transform is ten times faster than numpy's sum).
_SUM = np.ones((1, 3), dtype=np.float32)
_MEAN = _SUM / 3


def _gray(image: NDArray[np.float32]) -> NDArray[np.float32]:
    return np.asarray(cv2.transform(image, _MEAN), dtype=np.float32)


def _box(image: NDArray[np.float32]) -> NDArray[np.float32]:
    """Local means over TEXTURE_PX windows."""
    return np.asarray(cv2.blur(image, (TEXTURE_PX, TEXTURE_PX)), dtype=np.float32)


def _work_size(image_size: tuple[int, int]) -> tuple[int, int]:
    width, height = image_size
    if width <= WORK_WIDTH:
        return width, height
    scale = WORK_WIDTH / width
    return WORK_WIDTH, max(1, round(height * scale))


@register
class ForegroundDetector(Detector):
    """Motion (MOG2) and, when configured, difference from a picture of the empty floor."""

    prefix = "foreground"
    example = FOREGROUND
    observes = True

    def __init__(
        self, view: CameraView, options: Mapping[str, Any] | None = None, *, texture_noise: bool = True
    ) -> None:
        super().__init__(view, options)
        self.refuse_unknown_options("background")
        #: The texture-aware noise model (a camera always has it; False is kept to measure it against).
        self.texture_noise = texture_noise
        self._work = _work_size(view.image_size)
        work_w, work_h = self._work
        self._fov = cv2.resize(view.fov_mask, self._work, interpolation=cv2.INTER_NEAREST) > 0
        # Sample of the field of view the gain is measured on (every 4th pixel is plenty for a median).
        sample = np.zeros((work_h, work_w), dtype=bool)
        sample[::4, ::4] = True
        sample &= self._fov
        self._sample = np.nonzero(sample if sample.any() else self._fov)
        self._open = cv2.getStructuringElement(cv2.MORPH_RECT, (OPEN_PX, OPEN_PX))
        self._close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (CLOSE_PX, CLOSE_PX))
        self._texture_open = cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3))
        self._texture_grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (TEXTURE_PX + 2, TEXTURE_PX + 2))
        self.background_path: Path | None = None
        self._reference: NDArray[np.float32] | None = None
        self._reference_norm2: NDArray[np.float32] | None = None
        self._reference_brightness: NDArray[np.float32] | None = None
        self._reference_peak = np.zeros(self._work[::-1], np.float32)
        self._reference_gray = self._reference_mean = self._reference_std = np.zeros(self._work[::-1], np.float32)
        self._textured = np.zeros(self._work[::-1], dtype=bool)
        #: Where the picture has strong gradients, and each channel's tolerance there (grey levels).
        self._edges = np.zeros(self._work[::-1], dtype=bool)
        self._tolerance = np.zeros((*self._work[::-1], 3), dtype=np.float32)
        self._noise_frames: list[NDArray[np.float32]] = []
        #: Whether the tolerance is the source's measured noise (False: assumed from the picture).
        self.noise_learnt = False
        self._target_brightness: float | None = None
        background = self.options.get("background")
        if background is not None:
            self._load_background(background)
        self._lock = threading.Lock()
        self._subtractor = cv2.createBackgroundSubtractorMOG2(
            history=HISTORY_FRAMES, varThreshold=VAR_THRESHOLD, detectShadows=True
        )
        self._observed = 0
        self._subtractor.setShadowThreshold(SHADOW_MIN_BRIGHTNESS)
        self._masks: OrderedDict[int, NDArray[np.uint8]] = OrderedDict()
        self._frames: OrderedDict[int, tuple[NDArray[np.uint8], NDArray[np.uint8], float]] = OrderedDict()

    # --- configuration -----------------------------------------------------------------------

    def _load_background(self, background: Any) -> None:
        if not isinstance(background, (str, Path)) or not str(background).strip():
            raise InvalidArgument(f"foreground: background: {background!r} is not a file path")
        path = Path(background)
        self.background_path = path
        if not path.is_file():
            reason = "no such file" if not path.exists() else "not a file"
            raise FailedPrecondition(f"foreground: background {path}: {reason} (take one with drvs-camera snapshot)")
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise FailedPrecondition(f"foreground: background {path}: unreadable, not an image OpenCV can decode")
        size = (int(image.shape[1]), int(image.shape[0]))
        if size != self.view.image_size:
            raise FailedPrecondition(
                f"foreground: background {path}: {size[0]}x{size[1]}, but the camera's frames are "
                f"{self.view.image_size[0]}x{self.view.image_size[1]} (take it again with drvs-camera snapshot)"
            )
        work = self._prepare(np.asarray(image, dtype=np.uint8))
        self._reference = work.astype(np.float32) + 1.0
        self._reference_norm2 = np.asarray(cv2.transform(cv2.multiply(self._reference, self._reference), _SUM))
        self._reference_brightness = work[self._sample].astype(np.float32).sum(axis=1) + 3.0
        self._reference_peak = work.max(axis=2).astype(np.float32)
        gray = _gray(self._reference)
        self._reference_gray = gray
        self._reference_mean = _box(gray)
        variance = _box(gray * gray) - self._reference_mean * self._reference_mean
        self._reference_std = np.sqrt(np.maximum(variance, 0.0))
        self._textured = self._reference_std > TEXTURE_MIN_STD
        self._edge_model(self._reference)

    def _edge_model(self, reference: NDArray[np.float32]) -> None:
        """The strong-gradient pixels of the picture, and the tolerance there assumed before any
        frame's noise is measured: sensor noise and PRIOR_JITTER_PX of movement along the gradient."""
        grow = np.ones((3, 3), np.uint8)
        # Replicated borders: a tile joint along the image's edge has its gradient there too.
        gx = cv2.Scharr(reference, cv2.CV_32F, 1, 0, scale=1.0 / 32, borderType=cv2.BORDER_REPLICATE)
        gy = cv2.Scharr(reference, cv2.CV_32F, 0, 1, scale=1.0 / 32, borderType=cv2.BORDER_REPLICATE)
        gradient = np.asarray(cv2.dilate(cv2.magnitude(gx, gy), grow), dtype=np.float32)  # an edge moves
        self._edges = gradient.max(axis=2) > GRADIENT_MIN
        prior = np.sqrt(np.float32(PRIOR_NOISE**2) + (np.float32(PRIOR_JITTER_PX) * gradient) ** 2)
        self._tolerance = (np.float32(NOISE_K) * prior).astype(np.float32)

    def _learn_noise(self, work: NDArray[np.uint8], gain: float) -> None:
        """Collect the first NOISE_FRAMES frames (levelled); then the tolerance is their noise."""
        self._noise_frames.append(work.astype(np.float32) / np.float32(gain))
        if len(self._noise_frames) < NOISE_FRAMES:
            return
        stack = np.stack(self._noise_frames)
        self._noise_frames = []
        differences = np.abs(np.diff(stack, axis=0))
        sigma = np.quantile(differences, NOISE_QUANTILE, axis=0).astype(np.float32) / np.float32(_QUANTILE_SIGMAS)
        # The next frame's jitter may put an edge's pixel where its neighbour's noise was measured.
        sigma = np.asarray(cv2.dilate(sigma, np.ones((3, 3), np.uint8)), dtype=np.float32)
        # Never below the assumption (a few frames may all have had small jitters); a noisier source raises it.
        self._tolerance = np.maximum(self._tolerance, np.float32(NOISE_K) * sigma)
        self.noise_learnt = True

    @classmethod
    def parse(cls, filter_def: str) -> ObjectType:
        return parse_foreground(filter_def)

    # --- pixel work ----------------------------------------------------------------------------

    def _prepare(self, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """The frame at the working scale, smoothed against sensor noise (BGR)."""
        if image.ndim == 2:
            image = np.asarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), dtype=np.uint8)
        small = cv2.resize(image, self._work, interpolation=cv2.INTER_AREA)
        return np.asarray(cv2.medianBlur(small, 3), dtype=np.uint8)

    def _gain(self, work: NDArray[np.uint8]) -> float:
        """The frame's global lighting gain: against the empty floor's picture, or the first frame."""
        brightness = work[self._sample].astype(np.float32).sum(axis=1) + 3.0
        if self._reference_brightness is not None:
            gain = float(np.median(brightness / self._reference_brightness))
        else:
            level = float(np.median(brightness))
            if self._target_brightness is None:
                self._target_brightness = level
            gain = level / self._target_brightness
        return gain if np.isfinite(gain) and gain > 0.05 else 1.0

    def _motion(self, work: NDArray[np.uint8], gain: float, learning_rate: float) -> NDArray[np.uint8]:
        """MOG2's foreground (shadows, marked 127, dropped) for a working frame, lighting gain taken out."""
        levelled = cv2.convertScaleAbs(work, alpha=1.0 / gain)
        mask = self._subtractor.apply(levelled, learningRate=learning_rate)
        return np.asarray(cv2.threshold(mask, 200, 255, cv2.THRESH_BINARY)[1], dtype=np.uint8)

    def _static(
        self, work: NDArray[np.uint8], gain: float, explained: NDArray[np.bool_] | None = None
    ) -> NDArray[np.uint8]:
        """Pixels that differ from the empty floor in a way no shadow or lighting change explains,
        nor (`explained`, the texture-aware model's) the source's own noise on the floor's edges."""
        assert self._reference is not None and self._reference_norm2 is not None
        frame = work.astype(np.float32) + 1.0
        dot = cv2.transform(cv2.multiply(frame, self._reference), _SUM)  # |F| |R| cos(angle)
        norm2 = cv2.transform(cv2.multiply(frame, frame), _SUM)
        ref2 = self._reference_norm2
        # Colour direction: tan(angle)^2 > T^2  <=>  dot^2 (1 + T^2) < |F|^2 |R|^2.
        hue_changed = dot * dot * np.float32(1.0 + CHROMA_THRESHOLD**2) < norm2 * ref2
        # Brightness along the floor's colour, relative to the floor's, after the global gain.
        brightness = dot / (ref2 * np.float32(gain))
        changed = hue_changed | (brightness > BRIGHTNESS_HIGH) | (brightness < SHADOW_MIN_BRIGHTNESS)
        if explained is not None:
            changed &= ~explained
        if self._textured.any():
            # Where the floor has texture, a shadow or a change of light keeps it (scaled), and an
            # object hides it: the floor's texture no longer correlates with the frame's.
            gray = _gray(frame)
            mean = _box(gray)
            std = np.sqrt(np.maximum(_box(gray * gray) - mean * mean, 0.0))
            covariance = _box(gray * self._reference_gray) - mean * self._reference_mean
            correlation = covariance / np.maximum(std * self._reference_std, 1e-3)
            # Only where the texture has faded too (relative to the local brightness): a shadow's
            # edge inside a window decorrelates it as well, but adds contrast rather than hiding it.
            faded = std * self._reference_mean < TEXTURE_FADED * self._reference_std * mean
            hidden: Any = self._textured & (correlation < TEXTURE_MIN_CORRELATION) & faded
            if explained is not None:
                hidden &= ~explained  # before it grows: the floor's edges, moved by noise, seed nothing
            hidden = np.asarray(hidden, dtype=np.uint8)
            # Windows that straddle an object's edge see the edge's contrast, not faded texture: the
            # found region stops some pixels inside the object (3 at the working scale, measured on a
            # rendered disc). Grow it back by that much, speckle removed first.
            # Windows that reach over the image's border see part of the floor twice (reflected), and
            # a frame's jitter changes both parts: no texture judgement there.
            edge = TEXTURE_PX // 2 + 1
            hidden[:edge], hidden[-edge:], hidden[:, :edge], hidden[:, -edge:] = 0, 0, 0, 0
            hidden = cv2.dilate(cv2.morphologyEx(hidden, cv2.MORPH_OPEN, self._texture_open), self._texture_grow)
            changed |= hidden > 0
        return np.asarray(changed, dtype=np.uint8) * np.uint8(255)

    def _explained(self, work: NDArray[np.uint8], gain: float) -> NDArray[np.bool_]:
        """Pixels on the picture's strong gradients that differ from it, in every channel, by no
        more than the tolerance there: the floor's own edges, moved by the source's noise."""
        assert self._reference is not None
        with self._lock:
            tolerance = self._tolerance
        scale = np.float32(1.0 / gain)
        levelled = np.multiply(work, scale, dtype=np.float32)
        levelled += scale  # the picture is kept plus one
        excess = cv2.subtract(cv2.absdiff(levelled, self._reference), tolerance)
        # The worst channel's excess (OpenCV's reduce over each pixel's three values: numpy's max over
        # the last axis took three times as long).
        worst = cv2.reduce(excess.reshape(-1, 3), 1, cv2.REDUCE_MAX).reshape(self._edges.shape)
        return np.asarray(self._edges & (worst <= 0), dtype=bool)

    def _prepared(self, frame: Frame) -> tuple[NDArray[np.uint8], float]:
        """The frame's working image and gain (computed by observe when it has seen the frame)."""
        with self._lock:
            cached = self._frames.get(frame.sequence)
            if cached is not None and cached[0] is frame.image:
                return cached[1], cached[2]
        work = self._prepare(frame.image)
        with self._lock:
            return work, self._gain(work)

    def observe(self, frame: Frame) -> None:
        self.view.check_frame(frame)
        work = self._prepare(frame.image)
        with self._lock:
            gain = self._gain(work)
            rate = 1.0 / (self._observed + 1) if self._observed < WARMUP_FRAMES else 1.0 / HISTORY_FRAMES
            mask = self._motion(work, gain, rate)
            if self.texture_noise and self._reference is not None and not self.noise_learnt:
                self._learn_noise(work, gain)
            self._observed += 1
            self._frames[frame.sequence] = (frame.image, work, gain)
            self._masks[frame.sequence] = mask
            while len(self._masks) > MASK_CACHE:
                self._masks.popitem(last=False)
            while len(self._frames) > MASK_CACHE:
                self._frames.popitem(last=False)

    def _motion_mask(self, frame: Frame, work: NDArray[np.uint8], gain: float) -> NDArray[np.uint8] | None:
        """This frame's motion mask: the one observe made, or the model's verdict without learning."""
        with self._lock:
            if self._observed < WARMUP_FRAMES:
                return None
            mask = self._masks.get(frame.sequence)
            if mask is None:
                mask = self._motion(work, gain, 0.0)
            return mask

    def masks(self, frame: Frame) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """The frame's foreground (0/255) at the frame's size within the field of view: as found,
        and cleaned (speckle removed, an object's parts joined)."""
        self.view.check_frame(frame)
        work, gain = self._prepared(frame)
        found = np.zeros(work.shape[:2], dtype=np.uint8)
        motion = self._motion_mask(frame, work, gain)
        if motion is not None:
            found |= motion
        if self._reference is not None:
            # A channel the sensor clipped says only "at least this bright": where the floor's picture,
            # in this frame's light, would clip too (bright tape as the light rises), the pixel is
            # taken for floor by every cue, motion too.
            explained = (work.max(axis=2) >= CLIP_LEVEL) & (self._reference_peak * np.float32(gain) >= CLIP_LEVEL)
            if self.texture_noise:
                explained |= self._explained(work, gain)
            found[explained] = 0  # the motion model's pixels too: jitter moves edges between frames
            found |= self._static(work, gain, explained)
        found[~self._fov] = 0
        # An opening by an even kernel: erode and dilate about opposite corners, or it shifts the mask.
        opened = cv2.dilate(cv2.erode(found, self._open, anchor=(0, 0)), self._open, anchor=(OPEN_PX - 1, OPEN_PX - 1))
        cleaned = np.asarray(cv2.morphologyEx(opened, cv2.MORPH_CLOSE, self._close), dtype=np.uint8)
        return self._full_size(found), self._full_size(cleaned)

    def _full_size(self, mask: NDArray[np.uint8]) -> NDArray[np.uint8]:
        full: Any = mask
        if self._work != self.view.image_size:
            full = cv2.resize(mask, self.view.image_size, interpolation=cv2.INTER_LINEAR)
            full = cv2.threshold(full, 127, 255, cv2.THRESH_BINARY)[1]
        return np.asarray(cv2.bitwise_and(full, self.view.fov_mask), dtype=np.uint8)

    def find(self, analysis: FrameAnalysis, object_type: ObjectType) -> tuple[Detection, ...]:
        frame = analysis.frame
        raw, cleaned = self.masks(frame)
        return self.view.blobs(raw, cleaned, object_type, frame.capture_time)
